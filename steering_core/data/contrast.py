"""Contrast manifests: the state axis two tasks move along in opposite directions, and each demo's window on it.

Generalises the seed's `build_contrasting_pairs.py` (LeRobot backend) to any two tasks of a
LeRobot dataset (v3.0 or v2.x). For every selected demo the terminal displacement (last - first
frame) of each state dimension is taken; per task its mean and population std. The axis
is the one with the largest |mean_a - mean_b| whose two means have opposite signs and
both reach `min_abs_delta`; its effect size is (mean_a - mean_b) / pooled std. Each demo
then contributes the window in which that axis makes its progress.

The manifest JSON keeps the seed's fields exactly, so manifests written by the research
code load unchanged; an optional `dataset` record (ignored by seed readers) ties a manifest
to the dataset it was built from.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, Field, model_validator

from steering_core.data.dataset import (
    DatasetMeta,
    EpisodeInfo,
    dataset_fingerprint,
    read_episode_columns,
    resolve_task,
)
from steering_core.data.dataset_checks import check_dataset
from steering_core.storage.fileio import write_json
from steering_core.storage.schema import SHORT, StrictModel, read_model

logger = logging.getLogger(__name__)

STATE_COLUMN = "state"
DEMO_NAME = "episode_{episode_index:06d}"
# The seed adds this to the pooled std so that tasks whose demos all move identically
# still get a finite (very large) effect size instead of a division by zero.
EFFECT_SIZE_EPS = 1e-9
MAX_EPISODES = 1_000_000  # episode indices a list may name (ranges counted, not expanded): LIBERO-90 holds 4,500
# The seed's floor on the progress threshold: below it, float noise would count as progress.
MIN_PROGRESS_THRESHOLD = 1e-6
# Fallback window when an axis makes no measurable progress: the steps with the largest
# |change|, at least this many (or a tenth of the demo), as in the seed.
FALLBACK_MIN_STEPS = 5
_CLOSEST_AXES = 3


class ContrastSettings(StrictModel):
    """How a contrast manifest selects demos, the axis and the windows (seed defaults)."""

    min_abs_delta: float = Field(0.05, ge=0)       # state units (m for position, rad for axis-angle)
    progress_frac: float = Field(0.35, gt=0, le=1)  # share of the demo's total axis displacement
    pad: int = Field(8, ge=0)                        # frames added on both sides of each window
    max_demos_per_task: int | None = Field(None, gt=0)  # keep the lowest episode indices
    task_a_episodes: tuple[int, ...] | None = None   # explicit episodes of task A (default: all)
    task_b_episodes: tuple[int, ...] | None = None
    # Keep only this many segments per task: those progressing furthest in the task's
    # direction. The axis is still chosen from every selected demo.
    segments_per_class: int | None = Field(None, gt=0)
    # Names written as the segments' `task` (and so the concepts); default: the task text.
    task_a_label: str | None = Field(None, min_length=1)
    task_b_label: str | None = Field(None, min_length=1)


class AxisSummary(StrictModel):
    """The chosen state axis: its index, effect size and mean terminal displacement per task."""

    index: int = Field(ge=0)
    effect_size: float
    mean_delta_per_task: dict[str, float]


class Segment(StrictModel):
    """One demo's interaction window on the axis: frames start_step..end_step (inclusive)."""

    task: str
    file: str                  # the episode's data file, relative to the dataset root
    demo: str                  # episode_000042
    start_step: int
    end_step: int
    axis_delta: float          # axis value at end_step minus at start_step
    axis_values: tuple[float, ...]  # the axis over the window, (end_step - start_step + 1,)
    episode_index: int | None = None  # None only in manifests built by the seed from hdf5 files


class ManifestDataset(BaseModel):
    """Where a manifest came from: the dataset (with its fingerprint) and the settings used."""

    # StrictModel's rules, without its fingerprint() method, which the field below would shadow.
    model_config = StrictModel.model_config

    root: str
    repo_id: str
    fingerprint: str
    settings: ContrastSettings
    task_texts: dict[str, str] | None = None  # label -> the dataset's task text, when labels were given

    def mismatch(self, root: str | os.PathLike) -> str | None:
        """Return why the dataset at `root` is not the one this manifest was built from (its fingerprint), or None."""
        found = dataset_fingerprint(root)
        if found == self.fingerprint:
            return None
        return (f"the manifest was built from a dataset with fingerprint {self.fingerprint[:12]}..., "
                f"this one has {found[:12]}... (another dataset, or this one changed since)")


class ContrastManifest(StrictModel):
    """A contrast manifest: the axis, one segment per kept demo and, optionally, its provenance."""

    axis: AxisSummary
    segments: tuple[Segment, ...]
    dataset: ManifestDataset | None = None

    @model_validator(mode="after")
    def _consistent(self) -> ContrastManifest:
        """Return self after checking segments against the axis record; one ValueError lists every problem."""
        problems = []
        tasks = self.axis.mean_delta_per_task
        if len(tasks) != 2:
            problems.append(f"axis.mean_delta_per_task has {len(tasks)} task(s) {list(tasks)}, expected 2")
        first: dict[tuple[str, str, int, int], int] = {}  # a segment listed twice would double its samples
        for i, seg in enumerate(self.segments):
            where = f"segments[{i}] ({seg.demo})"
            if (seen := first.setdefault((seg.file, seg.demo, seg.start_step, seg.end_step), i)) != i:
                problems.append(f"{where}: the same segment as segments[{seen}]; expected each segment once")
            if seg.task not in tasks:
                problems.append(f"{where}: task {seg.task!r} is not in axis.mean_delta_per_task {list(tasks)}")
            if not 0 <= seg.start_step <= seg.end_step:
                problems.append(
                    f"{where}: start_step {seg.start_step}, end_step {seg.end_step}; expected 0 <= start <= end"
                )
            elif len(seg.axis_values) != seg.end_step - seg.start_step + 1:
                problems.append(
                    f"{where}: axis_values has {len(seg.axis_values)} values, expected "
                    f"end_step - start_step + 1 = {seg.end_step - seg.start_step + 1}"
                )
        if problems:
            raise ValueError("; ".join(problems))
        return self

    def to_json(self) -> dict:
        """Return the manifest as JSON data, leaving out `dataset` when absent (as the seed wrote it)."""
        return self.model_dump(mode="json", exclude={"dataset"} if self.dataset is None else None)


def terminal_displacements(demos: Sequence[np.ndarray]) -> np.ndarray:
    """Return each demo's last minus first state, (demos, state_dim) float64."""
    return np.stack([np.asarray(states[-1], np.float64) - np.asarray(states[0], np.float64) for states in demos])


def select_axis(
    deltas_a: np.ndarray, deltas_b: np.ndarray, task_a: str, task_b: str, min_abs_delta: float
) -> AxisSummary:
    """Return the axis with the largest |mean_a - mean_b| among those the tasks move in opposite directions.

    `deltas_*` are (demos, state_dim) terminal displacements. Both task means must have
    opposite non-zero signs and reach `min_abs_delta` in absolute value. Ties keep the lower index.
    """
    mean_a, mean_b = deltas_a.mean(axis=0), deltas_b.mean(axis=0)
    std_a, std_b = deltas_a.std(axis=0), deltas_b.std(axis=0)  # population std, as the seed
    diff = mean_a - mean_b
    effect = diff / (np.sqrt(0.5 * (std_a**2 + std_b**2)) + EFFECT_SIZE_EPS)
    eligible = (
        (np.sign(mean_a) * np.sign(mean_b) < 0)
        & (np.abs(mean_a) >= min_abs_delta)
        & (np.abs(mean_b) >= min_abs_delta)
    )
    for axis in np.argsort(-np.abs(diff), kind="stable"):
        if eligible[axis]:
            return AxisSummary(
                index=int(axis),
                effect_size=float(effect[axis]),
                mean_delta_per_task={task_a: float(mean_a[axis]), task_b: float(mean_b[axis])},
            )
    raise ValueError(_no_axis_message(mean_a, mean_b, task_a, task_b, min_abs_delta))


def _no_axis_message(mean_a: np.ndarray, mean_b: np.ndarray, task_a: str, task_b: str, min_abs_delta: float) -> str:
    """Return the error text naming the axes that came closest to qualifying, with their means."""
    opposite = np.sign(mean_a) * np.sign(mean_b) < 0
    weaker = np.where(opposite, np.minimum(np.abs(mean_a), np.abs(mean_b)), -1.0)
    # Opposite-signed axes first, by their weaker mean; then the rest by |difference|.
    order = np.lexsort((-np.abs(mean_a - mean_b), -weaker))[:_CLOSEST_AXES]
    closest = []
    for axis in order:
        reason = "opposite signs but below min_abs_delta" if opposite[axis] else "same sign"
        closest.append(f"axis {axis} (mean {task_a!r} {mean_a[axis]:+.4f}, {task_b!r} {mean_b[axis]:+.4f}: {reason})")
    return (
        f"no state axis moves in opposite directions for {task_a!r} and {task_b!r} with |mean terminal "
        f"displacement| >= min_abs_delta {min_abs_delta} in both; closest: {'; '.join(closest)}. "
        "Lower --min-abs-delta or choose two tasks with opposite motion."
    )


def interaction_window(series: np.ndarray, progress_frac: float, pad: int) -> tuple[int, int]:
    """Return (start, end), inclusive frames where a (frames,) axis series makes its progress.

    The window spans the first to the last frame whose displacement from frame 0 reaches
    `progress_frac` of the total displacement, widened by `pad` frames each side and
    clipped to the demo. If no frame reaches it (an axis that barely moves), it spans the
    steps with the largest |change| instead, as in the seed.
    """
    series = np.asarray(series, dtype=np.float64)
    last = len(series) - 1
    displacement = series - series[0]
    threshold = max(abs(series[-1] - series[0]) * progress_frac, MIN_PROGRESS_THRESHOLD)
    active = np.flatnonzero(np.abs(displacement) >= threshold)
    if active.size:
        start, end = int(active[0]), int(active[-1])
    else:
        steps = np.abs(np.diff(series, prepend=series[0]))
        if not np.any(steps):
            return 0, last
        largest = np.sort(np.argsort(steps, kind="stable")[-max(FALLBACK_MIN_STEPS, len(series) // 10) :])
        start, end = int(largest[0]), int(largest[-1])
    start, end = max(start - pad, 0), min(end + pad, last)
    if end <= start:
        end = min(start + 1, last)
    return start, end


@dataclass(frozen=True)
class DemoStates:
    """One demo's state trajectory and where it lives: (frames, state_dim) float64."""

    file: str                  # data file (relative to the dataset root) or LIBERO hdf5 file
    demo: str                  # episode_000042 or demo_7
    episode_index: int | None  # None for a demo read from an hdf5 file
    states: np.ndarray


def contrast(
    label_a: str, label_b: str, demos_a: Sequence[DemoStates], demos_b: Sequence[DemoStates],
    settings: ContrastSettings,
) -> tuple[AxisSummary, tuple[Segment, ...]]:
    """Return the axis two demo sets move along in opposite directions and the kept segments, A's first."""
    if label_a == label_b:
        raise ValueError(f"task A and task B are both labelled {label_a!r}; a contrast needs two different labels")
    axis = select_axis(
        terminal_displacements([d.states for d in demos_a]),
        terminal_displacements([d.states for d in demos_b]),
        label_a,
        label_b,
        settings.min_abs_delta,
    )
    segments = []
    for label, demos in ((label_a, demos_a), (label_b, demos_b)):
        task_segments = [_segment(label, demo, axis.index, settings) for demo in demos]
        segments += _keep_furthest(task_segments, axis.mean_delta_per_task[label], settings.segments_per_class)
    return axis, tuple(segments)


def build_manifest(
    root: str | os.PathLike,
    task_a: str | int,
    task_b: str | int,
    settings: ContrastSettings | None = None,
    *,
    repo_id: str | None = None,
) -> ContrastManifest:
    """Return the contrast manifest of two tasks of the LeRobot dataset at `root`.

    A task is its text (matched exactly, else ignoring case and spacing) or its `task_index`.
    `settings` default to the seed's; `repo_id` is recorded in the manifest's `dataset`
    record (default: the dataset folder's name).
    """
    settings = settings or ContrastSettings()
    meta = check_dataset(root)
    text_a, text_b = _task_text(meta, task_a, "A"), _task_text(meta, task_b, "B")
    if text_a == text_b:
        raise ValueError(f"task A and task B are both {text_a!r}; a contrast needs two different tasks")
    cap = settings.max_demos_per_task
    episodes_a = _select_episodes(meta, text_a, settings.task_a_episodes, cap, "--task-a-episodes")
    episodes_b = _select_episodes(meta, text_b, settings.task_b_episodes, cap, "--task-b-episodes")
    states = read_episode_columns(meta.root, [e.episode_index for e in episodes_a + episodes_b], STATE_COLUMN)

    def demos(episodes: list[EpisodeInfo]) -> list[DemoStates]:
        return [DemoStates(e.data_file, DEMO_NAME.format(episode_index=e.episode_index), e.episode_index,
                           states[e.episode_index]) for e in episodes]

    label_a, label_b = settings.task_a_label or text_a, settings.task_b_label or text_b
    axis, segments = contrast(label_a, label_b, demos(episodes_a), demos(episodes_b), settings)
    labelled = settings.task_a_label is not None or settings.task_b_label is not None
    return ContrastManifest(
        axis=axis,
        segments=segments,
        dataset=ManifestDataset(
            root=str(root),
            repo_id=repo_id or meta.root.name,
            fingerprint=dataset_fingerprint(meta.root),
            settings=settings,
            task_texts={label_a: text_a, label_b: text_b} if labelled else None,
        ),
    )


def _task_text(meta: DatasetMeta, task: str | int, which: str) -> str:
    """Return the dataset's text of a task given by text or by `task_index`."""
    if isinstance(task, str):
        return resolve_task(meta, task)
    if task not in meta.tasks:
        raise ValueError(
            f"{meta.tasks_file}: task {which} index {task} is not in the dataset; task indices are {sorted(meta.tasks)}"
        )
    return meta.tasks[task]


def _select_episodes(
    meta: DatasetMeta, task: str, explicit: Sequence[int] | None, max_demos: int | None, flag: str
) -> list[EpisodeInfo]:
    """Return the task's demos to use, by episode index: all or `explicit`, then the first `max_demos`."""
    available = meta.episodes_for_task(task)
    if not available:
        raise ValueError(f"{meta.root}: task {task!r} has no episodes (it is listed in {meta.tasks_file.name} only)")
    if explicit is not None:
        by_index = {e.episode_index: e for e in available}
        foreign = sorted({i for i in explicit if i not in by_index})
        if foreign:
            owner = {e.episode_index: e.task for e in meta.episodes}
            found = SHORT.repr({i: owner.get(i, "not in the dataset") for i in foreign})
            raise ValueError(
                f"{flag}: episode(s) {found}{f' ({len(foreign):,} of them)' if len(foreign) > SHORT.maxdict else ''} "
                f"are not episodes of {task!r}; its episodes are {sorted(by_index)}"
            )
        if not explicit:
            raise ValueError(f"{flag}: the episode list for {task!r} is empty")
        available = [by_index[i] for i in sorted(set(explicit))]
    selected = available[:max_demos] if max_demos is not None else available
    logger.info("%s: %d demo(s), episodes %s", task, len(selected), [e.episode_index for e in selected])
    return selected


def _segment(task: str, demo: DemoStates, axis: int, settings: ContrastSettings) -> Segment:
    """Return one demo's segment on `axis`."""
    start, end = interaction_window(demo.states[:, axis], settings.progress_frac, settings.pad)
    values = demo.states[start : end + 1, axis]
    return Segment(
        task=task,
        file=demo.file,
        demo=demo.demo,
        start_step=start,
        end_step=end,
        axis_delta=float(values[-1] - values[0]),
        axis_values=tuple(float(v) for v in values),
        episode_index=demo.episode_index,
    )


def _keep_furthest(segments: list[Segment], task_mean: float, count: int | None) -> list[Segment]:
    """Return the `count` segments progressing furthest in the task's direction, in episode order."""
    if count is None or count >= len(segments):
        if count is not None and count > len(segments):
            task = segments[0].task
            logger.warning("segments_per_class %d > %d demo(s) of %r: keeping all", count, len(segments), task)
        return segments
    direction = np.sign(task_mean)
    ranked = sorted(range(len(segments)), key=lambda i: -direction * segments[i].axis_delta)
    return [segments[i] for i in sorted(ranked[:count])]


def write_manifest(manifest: ContrastManifest, path: str | os.PathLike) -> Path:
    """Write `manifest` as indented JSON atomically; return the path."""
    return write_json(path, manifest.to_json())


def read_manifest(path: str | os.PathLike) -> ContrastManifest:
    """Return the validated manifest at `path` (ours, or the seed's without a `dataset` record)."""
    return read_model(path, ContrastManifest, what="contrast manifest")
