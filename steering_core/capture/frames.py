"""Frames for capture: LeRobot frames (v3.0 through lerobot, v2.x through `V2Frames`) batched by a DataLoader whose
workers decode the cameras to uint8, then resized into pi0.5's camera slots on the model's device."""

from __future__ import annotations

import functools
import multiprocessing
import os
from collections.abc import Iterator, Mapping, Sequence
from multiprocessing import forkserver
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch.utils.data import DataLoader, Dataset, default_collate

from steering_core.data.dataset import NO_VIDEO_BACKEND, DatasetMeta
from steering_core.data.image_cells import check_image_cells
from steering_core.data.v2_frames import V2Frames
from steering_core.pi05.preprocess import LIBERO_IMAGE_KEYS, Cameras
from steering_core.processes import children_ignore_ctrl_c

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

    A frame whose camera cannot be decoded, or decodes to another shape than info.json declares, is refused in
    one ValueError naming the dataset, episode and frame (the first frame of each file was checked before the run,
    `image_cells.check_png_headers`; the rest are checked here, as they are decoded).
    """

    def __init__(self, frames: Any, keys: Sequence[str], shapes: Mapping[str, tuple[int, ...]] | None = None):
        self.frames, self.keys, self.shapes = frames, tuple(keys), dict(shapes or {})  # camera -> (3, H, W)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, position: int) -> dict[str, Any]:
        try:
            item = self.frames[position]
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as err:  # Pillow's decoding errors
            raise ValueError(f"the frame at dataset position {position} cannot be decoded ({err}); "
                             "expected PNG cameras, re-create the dataset") from None
        bad = {key: tuple(item[key].shape) for key, shape in self.shapes.items() if tuple(item[key].shape) != shape}
        if bad:
            raise ValueError(f"episode {int(item['episode_index'])} frame "
                             f"{int(item['frame_index'])} has camera(s) {bad}, expected {self.shapes} "
                             "(`features.<camera>.shape` in meta/info.json); re-create the dataset")
        return {key: item[key] for key in self.keys}


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


def camera_shapes(meta: DatasetMeta) -> dict[str, tuple[int, int, int]]:
    """Return camera -> (3, H, W) as info.json declares (H, W, 3), what a decoded frame must be."""
    features = meta.info["features"]
    return {key: (3, *features[key]["shape"][:2]) for key in LIBERO_IMAGE_KEYS if key in features}


def frame_loader(
    frames: Any, plan: list[tuple[str, list[int]]], keys: Sequence[str], num_workers: int, pin_memory: bool,
    shapes: Mapping[str, tuple[int, ...]] | None = None, cameras: Cameras = Cameras(),
) -> DataLoader:
    """Return a DataLoader yielding one batch per `plan` entry, both cameras uint8 (B, 3, H, W)."""
    return DataLoader(
        FrameDataset(frames, keys, shapes),
        batch_sampler=[positions for _, positions in plan],
        num_workers=num_workers,
        multiprocessing_context=worker_start_method(num_workers),
        collate_fn=functools.partial(_collate, cameras=cameras),
        pin_memory=pin_memory,
    )


def frame_batches(
    frames: Any, plan: list[tuple[str, list[int]]], keys: Sequence[str], image_size: int, num_workers: int | None,
    device: torch.device, shapes: Mapping[str, tuple[int, ...]] | None = None, cameras: Cameras = Cameras(),
) -> Iterator[dict[str, Any]]:
    """Return an iterator of one batch per `plan` entry, cameras in pi0.5's three slots on `device`.

    The workers (`frame_workers(num_workers)`) start now, so they decode while the caller loads its model.
    A frame refused in a worker (`FrameDataset`) is raised here as the worker's one-line ValueError.
    """
    loader = frame_loader(frames, plan, keys, frame_workers(num_workers), device.type == "cuda", shapes, cameras)
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
    """Return how many frame workers to start: `num_workers`, or for None one per core this process may run
    on (its CPU affinity) less one for the main process, which copies frames to the device and drives the model,
    at most `MAX_DEFAULT_WORKERS`: 0 (decode in-process) on one core, 1 on two, 8 on a 16-core GPU machine."""
    if num_workers is not None:
        return num_workers
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(0, min(cores - 1, MAX_DEFAULT_WORKERS))


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
