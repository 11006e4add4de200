"""Concept maps: every manifest segment as a range of global dataset indices, grouped by concept.

A segment (episode, frames start_step..end_step) becomes the inclusive `index` range of
those frames in the LeRobot dataset, found from the index columns alone (no frame is
decoded). Concepts are the segments' task texts, optionally renamed. The JSON keeps the
fields of the seed's `map_concept_samples.py`, whose order it also keeps: concepts in order
of first appearance in the dataset, and each concept's rows by dataset position.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path

import numpy as np
from pydantic import Field, model_validator

from steering_core.data.contrast import ContrastManifest, read_manifest
from steering_core.data.dataset import DatasetMeta, IndexColumns, read_index_columns
from steering_core.data.dataset_checks import check_dataset
from steering_core.storage.fileio import read_json, write_json
from steering_core.storage.schema import StrictModel, read_model

logger = logging.getLogger(__name__)


class ConceptRow(StrictModel):
    """One segment's frames and their global dataset indices (both ranges inclusive)."""

    segment_id: int = Field(ge=0)    # position in the manifest's `segments`
    episode_index: int = Field(ge=0)
    frame_start: int                 # as requested by the manifest
    frame_end: int
    observed_frame_start: int        # as found in the dataset
    observed_frame_end: int
    start_index: int = Field(ge=0)   # global `index` of the first frame
    end_index: int = Field(ge=0)     # global `index` of the last frame (inclusive)
    length: int = Field(gt=0)        # end_index - start_index + 1


class ConceptMap(StrictModel):
    """Concept -> dataset index ranges for one manifest and one dataset."""

    manifest: str
    lerobot_root: str
    repo_id: str
    concept_count: dict[str, int]
    sample_count: int = Field(ge=0)  # frames in the whole dataset
    concepts: dict[str, tuple[ConceptRow, ...]]

    @model_validator(mode="after")
    def _consistent(self) -> ConceptMap:
        """Return self after checking counts, lengths and index bounds; one ValueError lists every problem."""
        problems = []
        if list(self.concept_count) != list(self.concepts):
            problems.append(
                f"concept_count has concepts {list(self.concept_count)}, concepts has {list(self.concepts)}"
            )
        for concept, rows in self.concepts.items():
            if self.concept_count.get(concept, len(rows)) != len(rows):
                count = self.concept_count[concept]
                problems.append(f"concept_count[{concept!r}] is {count}, but it has {len(rows)} rows")
            for row in rows:
                where = f"concepts[{concept!r}] segment {row.segment_id}"
                if row.length != row.end_index - row.start_index + 1:
                    problems.append(f"{where}: length {row.length}, expected end_index - start_index + 1")
                if row.end_index >= self.sample_count:
                    problems.append(f"{where}: end_index {row.end_index} >= sample_count {self.sample_count}")
        problems += _shared_rows(self.concepts)
        if problems:
            raise ValueError("; ".join(problems))
        return self

    def without_episodes(self, episodes: Collection[int]) -> ConceptMap:
        """Return this map without the segments of `episodes` (held-out episodes never reach slicing)."""
        dropped = set(episodes)
        if not dropped:
            return self
        concepts = {c: tuple(r for r in rows if r.episode_index not in dropped) for c, rows in self.concepts.items()}
        return self.model_copy(update={
            "concepts": concepts, "concept_count": {c: len(rows) for c, rows in concepts.items()},
        })


def _shared_rows(concepts: Mapping[str, Sequence[ConceptRow]]) -> list[str]:
    """Return the problem of two concepts covering the same dataset index (a frame on both sides of a contrast),
    else none. Rows of one concept may overlap: slicing keeps such a frame once."""
    spans = []  # (start, end, concept): each concept's rows merged into disjoint index ranges
    for concept, rows in concepts.items():
        for row in sorted(rows, key=lambda r: r.start_index):
            if spans and spans[-1][2] == concept and row.start_index <= spans[-1][1] + 1:
                spans[-1] = (spans[-1][0], max(spans[-1][1], row.end_index), concept)
            else:
                spans.append((row.start_index, row.end_index, concept))
    spans.sort()
    for (_, end, concept), (start, _, other) in zip(spans, spans[1:]):
        if start <= end:  # merged spans of one concept never overlap: these are two concepts
            return [f"concepts[{other!r}] and concepts[{concept!r}] share dataset index {start}; expected each "
                    "frame in one concept at most"]
    return []


def build_concept_map(
    manifest_path: str | os.PathLike,
    lerobot_root: str | os.PathLike,
    *,
    repo_id: str | None = None,
    rename: Mapping[str, str] | None = None,
) -> ConceptMap:
    """Return the concept map of the manifest at `manifest_path` on the dataset at `lerobot_root`.

    `rename` maps task texts to concept names (unlisted tasks keep their text; two tasks never share one); `repo_id`
    defaults to the dataset folder's name. Every problem (missing episode, segment outside
    its episode, task or fingerprint of another dataset) is collected, then raised at once.
    """
    manifest = read_manifest(manifest_path)
    if not manifest.segments:
        raise ValueError(f"{manifest_path}: the manifest has no segments; rebuild it with `latent-steering manifest`")
    meta = check_dataset(lerobot_root)
    manifest, from_sources = _locate_hdf5_demos(manifest, meta)
    problems = _dataset_problems(manifest, meta, from_sources)
    if problems:
        raise ValueError(
            f"{manifest_path} does not match the dataset {lerobot_root}: " + "; ".join(problems)
            + ". Rebuild the manifest from this dataset with `latent-steering manifest`."
        )
    columns = read_index_columns(meta.root)
    rows, problems = _locate_segments(manifest, columns)
    if problems:
        raise ValueError(
            f"{lerobot_root}: frames of {manifest_path} are missing or misplaced: " + "; ".join(problems)
            + ". The dataset's data files do not match its metadata; re-create the dataset."
        )
    rename = dict(rename or {})
    unused = sorted(set(rename) - {seg.task for seg in manifest.segments})
    if unused:
        logger.warning("concept map: rename entries for tasks not in the manifest: %s", unused)
    tasks_of: dict[str, set[str]] = {}
    for segment in manifest.segments:
        concept = rename.get(segment.task, segment.task)
        tasks_of.setdefault(concept.strip().casefold(), set()).add(segment.task)
    if merged := {concept: sorted(tasks) for concept, tasks in tasks_of.items() if len(tasks) > 1}:
        tasks = next(iter(merged.values()))
        raise ValueError(f"{manifest_path}: the rename gives the tasks {' and '.join(map(repr, tasks))} one concept "
                         f"{rename.get(tasks[0], tasks[0])!r} (case aside), which would merge their rows; give each "
                         "task its own concept name")
    concepts: dict[str, list[ConceptRow]] = {}
    for row in sorted(rows, key=lambda r: (r.start_index, r.segment_id)):
        task = manifest.segments[row.segment_id].task
        concepts.setdefault(rename.get(task, task), []).append(row)
    for concept, entries in concepts.items():
        logger.info("concept %r: %d segment(s), %d sample(s)", concept, len(entries), sum(r.length for r in entries))
    return ConceptMap(
        manifest=str(manifest_path),
        lerobot_root=str(lerobot_root),
        repo_id=repo_id or meta.root.name,
        concept_count={concept: len(entries) for concept, entries in concepts.items()},
        sample_count=len(columns),
        concepts={concept: tuple(entries) for concept, entries in concepts.items()},
    )


def _locate_hdf5_demos(manifest: ContrastManifest, meta: DatasetMeta) -> tuple[ContrastManifest, set[int]]:
    """Return the manifest with the episode of each hdf5 segment (file, demo_k) filled in, and their positions.

    A manifest built from hdf5 files names demos, not episodes; a dataset written by `convert` records
    which demo of which file became which episode (meta/libero_sources.json), so the two can be joined.
    """
    from steering_core.data.convert import SOURCES_FILE, read_sources  # only for hdf5 manifests

    pending = [i for i, seg in enumerate(manifest.segments) if seg.episode_index is None]
    if not pending or not (meta.root / SOURCES_FILE).is_file():
        return manifest, set()
    episode_of = {(source.file, source.demo): source.episode_index for source in read_sources(meta.root).episodes}
    segments = list(manifest.segments)
    found = set()
    for i in pending:
        episode = episode_of.get((Path(segments[i].file).name, segments[i].demo))
        if episode is not None:
            segments[i] = segments[i].model_copy(update={"episode_index": episode})
            found.add(i)
    return manifest.model_copy(update={"segments": tuple(segments)}), found


def _dataset_problems(manifest: ContrastManifest, meta: DatasetMeta, from_sources: set[int]) -> list[str]:
    """Return why the manifest cannot belong to this dataset (fingerprint, episodes, tasks, frame ranges).

    Segments in `from_sources` were matched by file and demo, so their (possibly relabelled) task is not compared.
    """
    problems = []
    if manifest.dataset is not None and (mismatch := manifest.dataset.mismatch(meta.root)):
        problems.append(mismatch)
    episodes = {e.episode_index: e for e in meta.episodes}
    texts = (manifest.dataset.task_texts if manifest.dataset is not None else None) or {}
    for i, seg in enumerate(manifest.segments):
        where = f"segments[{i}] ({seg.demo})"
        episode = episodes.get(seg.episode_index)
        if seg.episode_index is None:
            problems.append(
                f"{where}: no episode_index and {seg.file}:{seg.demo} is not in the dataset's "
                "meta/libero_sources.json (a manifest built from hdf5 files maps only onto a dataset that "
                "`latent-steering convert` made from the same files)"
            )
        elif episode is None:
            problems.append(f"{where}: episode {seg.episode_index} is not in the dataset ({len(episodes)} episodes)")
        elif i not in from_sources and texts.get(seg.task, seg.task) not in episode.tasks:
            problems.append(f"{where}: task {seg.task!r}, but episode {seg.episode_index} shows {episode.task!r}")
        elif seg.end_step >= episode.length:
            problems.append(
                f"{where}: frames {seg.start_step}..{seg.end_step} outside episode {seg.episode_index}'s "
                f"frames 0..{episode.length - 1}"
            )
    return problems


def _locate_segments(manifest: ContrastManifest, columns: IndexColumns) -> tuple[list[ConceptRow], list[str]]:
    """Return one ConceptRow per segment, found by binary search over (episode, frame), and the problems met."""
    # One sortable int64 key per frame; frame_index < stride for every frame.
    stride = int(columns.frame_index.max()) + 1
    keys = columns.episode_index * stride + columns.frame_index
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    frames, indices = columns.frame_index[order], columns.index[order]
    rows, problems = [], []
    if not np.array_equal(columns.index, np.arange(len(columns))):
        problems.append("the global `index` column is not 0..frames-1, so indices cannot address frames")
    for i, seg in enumerate(manifest.segments):
        first = np.searchsorted(keys, seg.episode_index * stride + seg.start_step, side="left")
        stop = np.searchsorted(keys, seg.episode_index * stride + seg.end_step, side="right")
        wanted = seg.end_step - seg.start_step + 1
        span = indices[first:stop]
        where = f"segments[{i}] ({seg.demo}): frames {seg.start_step}..{seg.end_step} of episode {seg.episode_index}"
        if stop - first != wanted:
            problems.append(f"{where}: the data files hold {stop - first} of these {wanted} frames")
            continue
        if span[-1] - span[0] + 1 != wanted:
            problems.append(f"{where}: at indices {span[0]}..{span[-1]}, which are not consecutive")
            continue
        rows.append(
            ConceptRow(
                segment_id=i,
                episode_index=seg.episode_index,
                frame_start=seg.start_step,
                frame_end=seg.end_step,
                observed_frame_start=int(frames[first]),
                observed_frame_end=int(frames[stop - 1]),
                start_index=int(span[0]),
                end_index=int(span[-1]),
                length=int(span[-1] - span[0] + 1),
            )
        )
    return rows, problems


def read_rename_map(path: str | os.PathLike) -> dict[str, str]:
    """Return the task -> concept renames of a JSON object file."""
    payload = read_json(path)
    if not isinstance(payload, dict):
        raise ValueError(f"{path}: expected a JSON object of task text -> concept name, found {type(payload).__name__}")
    bad = sorted(k for k, v in payload.items() if not isinstance(v, str) or not v)
    if bad:
        raise ValueError(f"{path}: concept names must be non-empty strings; check the entries for {bad}")
    return dict(payload)


def write_concept_map(concept_map: ConceptMap, path: str | os.PathLike) -> Path:
    """Write `concept_map` as indented JSON atomically; return the path."""
    return write_json(path, concept_map.model_dump(mode="json"))


def read_concept_map(path: str | os.PathLike) -> ConceptMap:
    """Return the validated concept map at `path` (ours or the seed's)."""
    return read_model(path, ConceptMap, what="concept map")
