"""Frames for capture: LeRobot frames (v3.0 through lerobot, v2.x through `V2Frames`) batched by a DataLoader whose
workers decode the cameras to uint8, then resized into pi0.5's camera slots on the model's device."""

from __future__ import annotations

import functools
import logging
import multiprocessing
from collections.abc import Iterator, Sequence
from multiprocessing import forkserver
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch.utils.data import DataLoader, Dataset, default_collate

from steering_core.data.dataset import NO_VIDEO_BACKEND, DatasetMeta
from steering_core.data.image_cells import PNG_HEADER_BYTES, check_image_cells, png_problem
from steering_core.data.v2_frames import V2Frames
from steering_core.devices import usable_cores
from steering_core.pi05.preprocess import LIBERO_IMAGE_KEYS, Cameras
from steering_core.processes import children_ignore_ctrl_c

logger = logging.getLogger(__name__)

# Modules the frame workers' forkserver imports once, so that each worker starts as fast as a fork; the first one
# makes the forkserver die with this process and ignore Ctrl-C (from exec on already, `children_ignore_ctrl_c`,
# when the main thread starts it).
WORKER_PRELOAD = ("steering_core.processes.child_start", "torch", "lerobot.datasets.lerobot_dataset",
                  "steering_core.capture.frames")
FRAME_KEYS = (*LIBERO_IMAGE_KEYS, "task", "index", "episode_index", "frame_index")  # what capture reads per frame
# Default worker cap: a worker decodes 70-220 frames/s of two 256 px PNG cameras on a shared core, so 8 keep
# ahead of pi0.5 on one GPU (~240 frames/s at layer 12 on an H200; BENCHMARKS.md §15) while each worker's copy
# of torch and lerobot (a few hundred MB) stays bounded on a many-core machine.
MAX_DEFAULT_WORKERS = 8


class FrameDataset(Dataset):
    """The dataset's frames reduced to what capture reads (cameras, state, task, index columns).

    With the dataset's `meta`, each frame is checked as it is read, and refused in one ValueError naming the data
    file, episode and frame: a PNG camera whose header (read before any pixel is decoded, so a small file declaring
    a huge image allocates nothing) is no RGB PNG of the size info.json declares, a camera that cannot be decoded,
    or one that decodes to another shape (the first frame of each file was checked before the run,
    `image_cells.check_png_headers`).
    """

    def __init__(self, frames: Any, keys: Sequence[str], meta: DatasetMeta | None = None):
        self.frames, self.keys, self.meta = frames, tuple(keys), meta
        features = meta.info["features"] if meta else {}
        self.shapes = {key: (3, *features[key]["shape"][:2]) for key in LIBERO_IMAGE_KEYS if key in features}
        self.pngs = {key: tuple(features[key]["shape"]) for key in self.shapes if features[key]["dtype"] == "image"}

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, position: int) -> dict[str, Any]:
        for key, shape in self.pngs.items():
            problem = png_problem(stored_png_header(self.frames, position, key), shape)
            if problem:
                raise ValueError(f"{self._where(position)}: camera {key!r} {problem} (`features.{key}.shape` in "
                                 "meta/info.json); re-create the dataset")
        try:
            item = self.frames[position]
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as err:  # Pillow's decoding errors
            raise ValueError(f"{self._where(position)} cannot be decoded ({err}); expected PNG cameras, "
                             "re-create the dataset") from None
        bad = {key: tuple(item[key].shape) for key, shape in self.shapes.items() if tuple(item[key].shape) != shape}
        if bad:
            raise ValueError(f"{self._where(position)} has camera(s) {bad}, expected {self.shapes} "
                             "(`features.<camera>.shape` in meta/info.json); re-create the dataset")
        return {key: item[key] for key in self.keys}

    def _where(self, position: int) -> str:
        """Return where the frame at `position` is stored: its data file, episode and frame (or its position)."""
        if self.meta is None:
            return f"the frame at dataset position {position}"
        episode, frame = stored_frame(self.frames, position)
        return f"{self.meta.root / self.meta.episode(episode).data_file}: episode {episode} frame {frame}"


def stored_png_header(frames: Any, position: int, key: str) -> bytes:
    """Return the first bytes (the PNG header) of camera `key`'s image cell at `position`, read without decoding."""
    if isinstance(frames, V2Frames):
        return frames.stored_png(position, key)[:PNG_HEADER_BYTES]
    cell = frames.hf_dataset.data.column(key)[position]["bytes"]  # lerobot's arrow table, before HF's decoding
    return b"" if not cell.is_valid else cell.as_buffer()[:PNG_HEADER_BYTES].to_pybytes()


def stored_frame(frames: Any, position: int) -> tuple[int, int]:
    """Return the (episode, frame index) of `position` in a frame source, from its stored columns."""
    if isinstance(frames, V2Frames):
        return int(frames.episode_index[position]), int(frames.row[position])
    table = frames.hf_dataset.data
    return tuple(int(table.column(name)[position].as_py()) for name in ("episode_index", "frame_index"))


def _collate(items: list[dict[str, Any]], cameras: Cameras = Cameras()) -> dict[str, Any]:
    """Return one batch with both cameras as uint8 (B, 3, H, W) (runs in a DataLoader worker)."""
    batch = default_collate(items)
    for key, frames in zip(LIBERO_IMAGE_KEYS, cameras.worker_uint8(*(batch[key] for key in LIBERO_IMAGE_KEYS))):
        batch[key] = frames
    return batch


def slots_on_device(batch: dict[str, Any], image_size: int, device: torch.device,
                    cameras: Cameras = Cameras()) -> dict[str, Any]:
    """Return the batch with its uint8 cameras replaced by the checkpoint's camera slots computed on `device`.

    `images`: the slots (openpi: [base, left wrist, right wrist]) float32 (B, 3, size, size) in [-1, 1] on `device`;
    `image_masks`: (B,) bool (`pi05.preprocess.Cameras`). The copy is asynchronous from pinned memory.
    """
    frames = [batch[key].to(device, non_blocking=True) for key in LIBERO_IMAGE_KEYS]
    slots = dict(zip(("images", "image_masks"), cameras.from_uint8(*frames, image_size)))
    return {**{key: value for key, value in batch.items() if key not in LIBERO_IMAGE_KEYS}, **slots}


def frame_source(meta: DatasetMeta, repo_id: str, episodes: Sequence[int], video_backend: str | None) -> Any:
    """Return the frames of `episodes`: lerobot's LeRobotDataset for v3.0, `V2Frames` for v2.x (same items)."""
    if meta.is_v2:
        return V2Frames(meta, episodes, video_backend)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # slow import (torchvision, datasets)

    check_image_cells(meta, episodes)  # lerobot would open a path a cell names
    if video_backend is None and not meta.has_videos:
        video_backend = NO_VIDEO_BACKEND
    return LeRobotDataset(repo_id, root=meta.root, episodes=list(episodes), video_backend=video_backend)


def position_columns(frames: Any) -> tuple[np.ndarray, np.ndarray]:
    """Return the (frames,) episode index and global index of every position of a frame source."""
    if isinstance(frames, V2Frames):
        return frames.episode_index, frames.index
    columns = frames.hf_dataset.select_columns(["episode_index", "index"]).with_format("numpy")[:]
    return columns["episode_index"], columns["index"]


def batch_plan(frames: Any, groups: dict[str, tuple[int, ...]], batch_size: int) -> list[tuple[str, list[int]]]:
    """Return (shard key, dataset positions) per batch: groups in order, each from its first frame."""
    episode_of, index_of = position_columns(frames)
    plan = []
    for key, members in groups.items():
        positions = np.flatnonzero(np.isin(episode_of, members))
        positions = positions[np.argsort(index_of[positions], kind="stable")]
        plan += [(key, positions[i : i + batch_size].tolist()) for i in range(0, len(positions), batch_size)]
    return plan


def frame_loader(
    frames: Any, plan: list[tuple[str, list[int]]], keys: Sequence[str], num_workers: int, pin_memory: bool,
    meta: DatasetMeta | None = None, cameras: Cameras = Cameras(),
) -> DataLoader:
    """Return a DataLoader yielding one batch per `plan` entry, both cameras uint8 (B, 3, H, W); with `meta`, each
    frame is checked against the dataset's declared cameras (`FrameDataset`)."""
    return DataLoader(
        FrameDataset(frames, keys, meta),
        batch_sampler=[positions for _, positions in plan],
        num_workers=num_workers,
        multiprocessing_context=worker_start_method(num_workers),
        collate_fn=functools.partial(_collate, cameras=cameras),
        pin_memory=pin_memory,
    )


def frame_batches(
    frames: Any, plan: list[tuple[str, list[int]]], keys: Sequence[str], image_size: int, num_workers: int | None,
    device: torch.device, meta: DatasetMeta | None = None, cameras: Cameras = Cameras(),
) -> Iterator[dict[str, Any]]:
    """Return an iterator of one batch per `plan` entry, cameras in pi0.5's three slots on `device`.

    The workers (`frame_workers(num_workers)`) start now, so they decode while the caller loads its model.
    A frame refused in a worker (`FrameDataset`) is raised here as the worker's one-line ValueError.
    """
    loader = frame_loader(frames, plan, keys, frame_workers(num_workers), device.type == "cuda", meta, cameras)
    return (slots_on_device(batch, image_size, device, cameras) for batch in _worker_errors(iter(loader)))


def _worker_errors(batches: Iterator[dict[str, Any]]) -> Iterator[dict[str, Any]]:
    """Yield `batches`, raising a worker's ValueError with its own message (torch adds the worker's traceback)."""
    try:
        yield from batches
    except ValueError as err:
        lines = str(err).strip().splitlines()
        if len(lines) > 1 and lines[-1].startswith("ValueError: "):
            raise ValueError(lines[-1].removeprefix("ValueError: ")) from None
        raise


def frame_workers(num_workers: int | None) -> int:
    """Return how many frame workers to start: for None one per core this process may run on (its CPU affinity)
    less one for the main process, which copies frames to the device and drives the model, at most
    `MAX_DEFAULT_WORKERS`: 0 (decode in-process) on one core, 1 on two, 8 on a 16-core GPU machine.

    A given `num_workers` is capped by the usable cores, with a warning stating both: each worker is a process
    holding torch and a batch of decoded frames (a few hundred MB), and workers beyond the cores only add memory.
    """
    cores = usable_cores()
    if num_workers is None:
        return max(0, min(cores - 1, MAX_DEFAULT_WORKERS))
    if num_workers > cores:
        logger.warning("capture.num_workers %d is more than the %d usable cores of this process (CPU affinity); "
                       "starting %d frame workers", num_workers, cores, cores)
    return min(num_workers, cores)


def worker_start_method(num_workers: int) -> str | None:
    """Return how frame workers start: from a forkserver that imported torch and lerobot once (None: no workers).

    Forking the capturing process itself copies every lock but only the forking thread: inside a Prefect
    flow (API and log threads) workers then died at shutdown. A forkserver is a fresh single-threaded
    process; preloading the heavy imports there keeps each worker's start as cheap as a plain fork. It is
    started here, ignoring Ctrl-C from its first instruction on (`processes.children_ignore_ctrl_c`).
    """
    if num_workers == 0:
        return None
    multiprocessing.set_forkserver_preload(list(WORKER_PRELOAD))
    with children_ignore_ctrl_c():  # started now (its imports run after): Ctrl-C is this process's, which stops it
        forkserver.ensure_running()
    return "forkserver"
