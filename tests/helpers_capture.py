"""Tiny LeRobot v3.0 datasets for capture tests, written through lerobot's own LeRobotDataset.create."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

# (frames, task) per episode; two tasks share words so their token ids overlap
EPISODES: tuple[tuple[int, str], ...] = (
    (3, "open the top drawer"),
    (2, "close the top drawer"),
    (4, "open the top drawer"),
    (2, "put the bowl on the plate"),
)


def make_lerobot_dataset(
    root: Path,
    episodes: Sequence[tuple[int, str]] = EPISODES,
    *,
    image_size: int = 16,
    cameras: Sequence[str] = ("image", "wrist_image"),
    seed: int = 0,
) -> Path:
    """Write a LeRobot dataset with random uint8 cameras, `state` (8,) and `actions` (7,); return `root`."""
    from lerobot.datasets.lerobot_dataset import (
        LeRobotDataset,  # slow import: only when a dataset is built
    )

    camera = {"dtype": "image", "shape": (image_size, image_size, 3), "names": ["height", "width", "channel"]}
    features = {name: dict(camera) for name in cameras}
    features["state"] = {"dtype": "float32", "shape": (8,), "names": None}
    features["actions"] = {"dtype": "float32", "shape": (7,), "names": None}
    dataset = LeRobotDataset.create(
        repo_id=f"local/{root.name}", root=root, fps=10, robot_type="panda", features=features, use_videos=False
    )
    rng = np.random.default_rng(seed)
    for frames, task in episodes:
        for _ in range(frames):
            frame = {name: rng.integers(0, 256, (image_size, image_size, 3), dtype=np.uint8) for name in cameras}
            frame["state"] = rng.uniform(-1, 1, 8).astype(np.float32)
            frame["actions"] = rng.uniform(-1, 1, 7).astype(np.float32)
            dataset.add_frame({**frame, "task": task})
        dataset.save_episode()
    dataset.finalize()
    return root
