"""Tiny LeRobot v3.0 datasets with designed state motion, written through lerobot's own API.

The schema is the converter's (`state` float32 (8,), `actions` float32 (7,), a camera of
dtype image) with a 4x4 camera, so frames exist as PNG bytes in the data parquet and a
reader that touched them would have to decode them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

os.environ.setdefault("HF_HUB_OFFLINE", "1")

STATE_DIM = 8
ACTION_DIM = 7
IMAGE_SHAPE = (4, 4, 3)
FEATURES = {
    "image": {"dtype": "image", "shape": IMAGE_SHAPE, "names": ["height", "width", "channel"]},
    "state": {"dtype": "float32", "shape": (STATE_DIM,), "names": None},
    "actions": {"dtype": "float32", "shape": (ACTION_DIM,), "names": None},
}

OPEN = "open the top drawer of the cabinet"
CLOSE = "close the top drawer of the cabinet"
STOVE = "turn on the stove"

# The contrast axis is 3. Axis 0 differs more between OPEN and CLOSE but moves the same
# way in both; axis 6 differs most but CLOSE barely moves on it (|-0.01| < 0.05).
CONTRAST_AXIS = 3
NOISE = 1e-3


def ramp_states(length: int, moves: dict[int, float], start: int, end: int, seed: int) -> np.ndarray:
    """Return (length, 8) float32 states: each axis in `moves` goes linearly by its delta over frames start..end.

    Before `start` the axis holds its initial value, after `end` its final one; every
    axis also carries small deterministic noise, as real end-effector traces do.
    """
    rng = np.random.default_rng(seed)
    states = rng.normal(0.0, NOISE, size=(length, STATE_DIM)) + np.linspace(0.1, 0.8, STATE_DIM)
    progress = np.clip((np.arange(length) - start) / (end - start), 0.0, 1.0)
    for axis, delta in moves.items():
        states[:, axis] += delta * progress
    return states.astype(np.float32)


def contrast_episodes() -> list[tuple[str, np.ndarray]]:
    """Return the designed (task, states) episodes, in dataset order: 3 OPEN, 3 CLOSE, 1 STOVE."""
    plan = [
        # task, length, ramp start, ramp end, {axis: terminal displacement}
        (OPEN, 30, 6, 20, {0: 0.55, 3: 0.20, 6: 0.40}),
        (CLOSE, 26, 3, 15, {0: 0.10, 3: -0.15, 6: -0.01}),
        (STOVE, 18, 2, 12, {0: 0.30, 3: 0.10, 6: 0.20}),
        (OPEN, 34, 0, 14, {0: 0.55, 3: 0.21, 6: 0.40}),
        (CLOSE, 28, 12, 25, {0: 0.10, 3: -0.17, 6: -0.01}),
        (OPEN, 32, 10, 29, {0: 0.55, 3: 0.22, 6: 0.40}),
        (CLOSE, 24, 5, 18, {0: 0.10, 3: -0.19, 6: -0.01}),
    ]
    return [
        (task, ramp_states(length, moves, start, end, seed=i))
        for i, (task, length, start, end, moves) in enumerate(plan)
    ]


def write_dataset(
    root: Path,
    episodes: Sequence[tuple[str, np.ndarray]],
    *,
    reopen_after: int | None = None,
    repo_id: str = "local/test",
) -> Path:
    """Write `episodes` as a LeRobot v3.0 dataset at `root` (which must not exist); return `root`.

    With `reopen_after=k`, the dataset is finalized after k episodes and reopened to
    append the rest, which puts them in a second data file (`file-001.parquet`).
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from steering_core.data.convert import open_for_append

    dataset = LeRobotDataset.create(
        repo_id=repo_id, root=root, fps=10, robot_type="panda", features=FEATURES, use_videos=False
    )
    for number, (task, states) in enumerate(episodes):
        if reopen_after is not None and number == reopen_after:
            dataset.finalize()
            dataset = open_for_append(repo_id, root)
        for frame, state in enumerate(states):
            shade = (number * 37 + frame * 11) % 256
            dataset.add_frame(
                {
                    "image": np.full(IMAGE_SHAPE, shade, dtype=np.uint8),
                    "state": np.asarray(state, dtype=np.float32),
                    "actions": np.full(ACTION_DIM, frame / 100.0, dtype=np.float32),
                    "task": task,
                }
            )
        dataset.save_episode()
    dataset.finalize()
    return root


def write_contrast_dataset(root: Path) -> Path:
    """Write the designed contrast episodes over two data files; return `root`."""
    return write_dataset(root, contrast_episodes(), reopen_after=4)


def brute_force_rows(root: Path, repo_id: str = "local/test") -> dict[str, np.ndarray]:
    """Return episode_index, frame_index, index, task_index and task of every item, walking LeRobotDataset."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(repo_id, root=root)
    rows: dict[str, list] = {"episode_index": [], "frame_index": [], "index": [], "task_index": [], "task": []}
    for i in range(len(dataset)):
        item = dataset[i]
        for key in rows:
            rows[key].append(item[key] if key == "task" else int(item[key]))
    return {key: np.asarray(values) for key, values in rows.items()}
