"""Held-out episodes: split each task of a contrast manifest into training and evaluation episodes.

Steering vectors are computed from the training episodes only (slicing drops the held-out ones),
and the evaluation runs the policy on held-out frames, so a vector is never judged on the frames
it was made from. The split is deterministic per task: episodes are ranked by the sha256 of
(task, episode index) and the first `max(1, round(fraction * n))` are held out. The rank of an
episode does not depend on the other episodes, so adding demos moves few episodes between sides.
`holdout_fraction = 0` holds nothing out (the vectors of a run without a split; in-sample evaluation).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from pydantic import Field, model_validator

from steering_core.data.contrast import ContrastManifest
from steering_core.storage.fileio import write_json
from steering_core.storage.schema import StrictModel, read_model

SPLIT_FORMAT_VERSION = 1


class TaskSplit(StrictModel):
    """One task's episodes on each side of the split (sorted episode indices)."""

    train: tuple[int, ...] = Field(min_length=1)
    holdout: tuple[int, ...]


class HoldoutSplit(StrictModel):
    """Every task of a manifest split into training and held-out episodes."""

    format_version: int = SPLIT_FORMAT_VERSION
    holdout_fraction: float = Field(ge=0, lt=1)
    tasks: dict[str, TaskSplit]

    @model_validator(mode="after")
    def _disjoint(self) -> HoldoutSplit:
        for task, split in self.tasks.items():
            if both := sorted(set(split.train) & set(split.holdout)):
                raise ValueError(f"task {task!r}: episodes {both} are both training and held-out")
        return self

    @property
    def holdout_episodes(self) -> tuple[int, ...]:
        """Return every held-out episode index, sorted."""
        return tuple(sorted({e for split in self.tasks.values() for e in split.holdout}))

    @property
    def in_sample(self) -> bool:
        """Return True when nothing is held out (the evaluation then runs on training episodes)."""
        return not self.holdout_episodes

    def evaluation_episodes(self, task: str) -> tuple[int, ...]:
        """Return the episodes a task is evaluated on: held-out ones, or the training ones when in sample."""
        split = self.tasks[task]
        return split.holdout or split.train


def _rank_key(task: str, episode: int) -> str:
    """Return the sort key of one episode within its task: independent of every other episode."""
    return hashlib.sha256(f"{task}\0{episode}".encode()).hexdigest()


def split_episodes(manifest: ContrastManifest, holdout_fraction: float, *, where: str = "manifest") -> HoldoutSplit:
    """Return the held-out split of every task of `manifest` (episodes as its segments list them).

    With a fraction above 0 each task holds out at least one episode and keeps at least one for
    training; a task with a single episode cannot be split and raises ValueError naming it.
    """
    if not 0 <= holdout_fraction < 1:
        raise ValueError(f"holdout_fraction is {holdout_fraction}, expected 0 <= fraction < 1")
    episodes: dict[str, set[int]] = {task: set() for task in manifest.axis.mean_delta_per_task}
    for i, segment in enumerate(manifest.segments):
        if segment.episode_index is None:
            raise ValueError(f"{where}: segments[{i}] ({segment.demo}) has no episode_index; rebuild the manifest "
                             "from the LeRobot dataset with `latent-steering manifest`")
        episodes[segment.task].add(segment.episode_index)
    tasks, problems = {}, []
    for task, found in episodes.items():
        ranked = sorted(found, key=lambda e: _rank_key(task, e))
        count = max(1, round(holdout_fraction * len(ranked))) if holdout_fraction > 0 else 0
        if len(ranked) - count < 1:
            problems.append(
                f"task {task!r} has {len(ranked)} episode(s) {sorted(found)}: holding out {count} leaves "
                f"{len(ranked) - count} for the steering vectors"
            )
            continue
        tasks[task] = TaskSplit(train=tuple(sorted(ranked[count:])), holdout=tuple(sorted(ranked[:count])))
    if problems:
        raise ValueError(f"{where}: cannot split episodes with holdout_fraction {holdout_fraction}: "
                         + "; ".join(problems) + ". Add demos of that task or set evaluate.holdout_fraction: 0")
    return HoldoutSplit(holdout_fraction=holdout_fraction, tasks=tasks)


def write_split(split: HoldoutSplit, path: str | os.PathLike) -> Path:
    """Write the split as JSON atomically; return the path."""
    return write_json(path, split.model_dump(mode="json"))


def read_split(path: str | os.PathLike) -> HoldoutSplit:
    """Return the validated split at `path`."""
    return read_model(path, HoldoutSplit, what="held-out split", format_version=SPLIT_FORMAT_VERSION,
                      fix="rebuild it with the run's phase 1")
