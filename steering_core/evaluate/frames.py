"""Evaluation frames: evenly spaced frames of the held-out episodes of both tasks, inside the contrast windows."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from steering_core.data.concept_map import ConceptMap
from steering_core.data.contrast import ContrastManifest
from steering_core.data.split import HoldoutSplit
from steering_core.pairs import SIDES
from steering_core.pi05.preprocess import LIBERO_IMAGE_KEYS, Cameras


@dataclass(frozen=True)
class EvalFrame:
    """One evaluation frame: its task side, dataset position and global dataset `index`."""

    side: str           # "positive" or "negative": which task's instruction is the frame's own
    episode_index: int
    frame_index: int
    index: int          # global dataset index

    def as_json(self) -> dict[str, Any]:
        return {"side": self.side, "episode_index": self.episode_index, "frame_index": self.frame_index,
                "index": self.index}


def evenly_spaced(count: int, limit: int) -> list[int]:
    """Return positions floor(j * count / limit) for j < limit (all positions when count <= limit)."""
    if count <= limit:
        return list(range(count))
    return [(j * count) // limit for j in range(limit)]


def select_frames(
    manifest: ContrastManifest, concept_map: ConceptMap, split: HoldoutSplit, tasks: tuple[str, str], max_frames: int
) -> list[EvalFrame]:
    """Return up to `max_frames` frames: ceil(max/2) of the positive task, the rest of the negative one.

    `tasks` is (positive, negative) as the manifest spells them. Candidates are every frame of every
    contrast window of the task's evaluation episodes (held-out ones; training ones when nothing is
    held out), in (episode, frame) order. `concept_map` must be the map of the whole manifest.
    """
    budgets = ((max_frames + 1) // 2, max_frames // 2)
    frames: list[EvalFrame] = []
    for side, task, budget in zip(SIDES, tasks, budgets, strict=True):
        episodes = set(split.evaluation_episodes(task))
        candidates = [
            EvalFrame(side, row.episode_index, frame, row.start_index + frame - row.frame_start)
            for rows in concept_map.concepts.values() for row in rows
            if manifest.segments[row.segment_id].task == task and row.episode_index in episodes
            for frame in range(row.frame_start, row.frame_end + 1)
        ]
        if not candidates:
            raise ValueError(f"task {task!r}: no contrast-window frames in its evaluation episodes {sorted(episodes)}; "
                             "the concept map does not belong to this manifest")
        candidates.sort(key=lambda f: (f.episode_index, f.frame_index))
        frames += [candidates[i] for i in evenly_spaced(len(candidates), budget)]
    return frames


def frame_halves(frames: Sequence[EvalFrame]) -> tuple[list[int], str]:
    """Return each frame's half (0 or 1) for cross-fitting, and what was split: "episodes" or "frames".

    Per side, its episodes alternate between the halves (in episode order); a side with one episode
    alternates its frames instead (then the halves share an episode: not independent, and said so).
    """
    halves, by = [0] * len(frames), "episodes"
    for side in SIDES:
        members = [i for i, f in enumerate(frames) if f.side == side]
        episodes = sorted({frames[i].episode_index for i in members})
        if len(episodes) >= 2:
            for i in members:
                halves[i] = episodes.index(frames[i].episode_index) % 2
        else:
            by = "frames"
            for j, i in enumerate(sorted(members, key=lambda i: frames[i].frame_index)):
                halves[i] = j % 2
    return halves, by


def load_frames(
    dataset_root: Path, repo_id: str, frames: Sequence[EvalFrame], image_size: int, video_backend: str | None = None,
    cameras: Cameras = Cameras(),
) -> dict[str, Any]:
    """Return the frames' cameras in the checkpoint's slots and their states, in `frames` order: {"images": [...],
    "image_masks": [...], "states": (F, D) float64 or None (a dataset without `state`)}.

    Reads only the frames' episodes; cameras are preprocessed exactly as capture does (`cameras`, default openpi's).
    """
    from steering_core.capture.frames import FrameDataset, frame_source, position_columns
    from steering_core.capture.settings import STATE_KEY
    from steering_core.data.dataset import read_meta

    episodes = sorted({f.episode_index for f in frames})
    meta = read_meta(dataset_root)
    dataset = frame_source(meta, repo_id, episodes, video_backend)  # v3.0, v2.1 or v2.0
    index_column = position_columns(dataset)[1]
    position = {int(index): p for p, index in enumerate(index_column)}
    missing = [f.index for f in frames if f.index not in position]
    if missing:
        raise ValueError(f"{dataset_root}: frames with index {missing[:5]} are not in the dataset; the concept map "
                         "belongs to another dataset")
    keys = (*LIBERO_IMAGE_KEYS, *([STATE_KEY] if STATE_KEY in meta.info["features"] else []))
    checked = FrameDataset(dataset, keys, meta)  # a bad camera: one line naming its file, episode and frame
    items = [checked[position[f.index]] for f in frames]
    image, wrist = (torch.stack([item[key] for item in items]) for key in LIBERO_IMAGE_KEYS)
    images, image_masks = cameras.from_float(image, wrist, image_size)
    states = np.stack([np.asarray(item[STATE_KEY], dtype=np.float64) for item in items]) \
        if items and STATE_KEY in items[0] else None
    return {"images": images, "image_masks": image_masks, "states": states}
