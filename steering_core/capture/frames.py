"""Frames for capture: LeRobot frames (v3.0 through lerobot, v2.x through `V2Frames`) batched by a DataLoader whose workers decode and resize the cameras."""

from __future__ import annotations

import functools
import multiprocessing
from collections.abc import Sequence
from typing import Any

import numpy as np
from torch.utils.data import DataLoader, Dataset, default_collate

from steering_core.data.dataset import DatasetMeta
from steering_core.data.v2_frames import V2Frames
from steering_core.pi05 import libero_camera_slots
from steering_core.pi05.preprocess import LIBERO_IMAGE_KEYS

# Modules the frame workers' forkserver imports once, so that each worker starts as fast as a fork.
WORKER_PRELOAD = ("torch", "lerobot.datasets.lerobot_dataset", "steering_core.capture.frames")
FRAME_KEYS = (*LIBERO_IMAGE_KEYS, "task", "index", "episode_index", "frame_index")  # what capture reads per frame


class FrameDataset(Dataset):
    """The dataset's frames reduced to what capture reads (cameras, state, task, index columns)."""

    def __init__(self, frames: Any, keys: Sequence[str]):
        self.frames, self.keys = frames, tuple(keys)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, position: int) -> dict[str, Any]:
        item = self.frames[position]
        return {key: item[key] for key in self.keys}


def _collate(items: list[dict[str, Any]], image_size: int) -> dict[str, Any]:
    """Return one batch with the three camera slots already resized (runs in a DataLoader worker)."""
    batch = default_collate(items)
    batch["images"], batch["image_masks"] = libero_camera_slots(
        batch.pop(LIBERO_IMAGE_KEYS[0]), batch.pop(LIBERO_IMAGE_KEYS[1]), image_size
    )
    return batch


def frame_source(meta: DatasetMeta, repo_id: str, episodes: Sequence[int], video_backend: str | None) -> Any:
    """Return the frames of `episodes`: lerobot's LeRobotDataset for v3.0, `V2Frames` for v2.x (same items)."""
    if meta.is_v2:
        return V2Frames(meta, episodes, video_backend)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # slow import (torchvision, datasets)

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
    frames: Any, plan: list[tuple[str, list[int]]], keys: Sequence[str], image_size: int, num_workers: int,
    pin_memory: bool,
) -> DataLoader:
    """Return a DataLoader yielding one batch per `plan` entry, cameras already in pi0.5's three slots."""
    return DataLoader(
        FrameDataset(frames, keys),
        batch_sampler=[positions for _, positions in plan],
        num_workers=num_workers,
        multiprocessing_context=worker_start_method(num_workers),
        collate_fn=functools.partial(_collate, image_size=image_size),
        pin_memory=pin_memory,
    )


def worker_start_method(num_workers: int) -> str | None:
    """Return how frame workers start: from a forkserver that imported torch and lerobot once (None: no workers).

    Forking the capturing process itself copies every lock but only the forking thread: inside a Prefect
    flow (API and log threads) workers then died at shutdown. A forkserver is a fresh single-threaded
    process; preloading the heavy imports there keeps each worker's start as cheap as a plain fork.
    """
    if num_workers == 0:
        return None
    multiprocessing.set_forkserver_preload(list(WORKER_PRELOAD))
    return "forkserver"
