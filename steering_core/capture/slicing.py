"""Slice captured residuals by concept: shards + concept map -> one tensor per concept and layer.

Rows are matched by (episode_index, frame_index) against the concept map's segments, never
by their position in a stream, so slices stay right when a dataset grows. Two passes over
each layer's shards: the first reads only the small int64 row columns (to validate the
concept map against the run and to choose rows), the second reads each shard once through one
bounded buffer, copying its selected rows to their place in the concepts' output files
(`slice_copy`, `slice_files`), so no concept is ever held whole in memory. Peak memory is that
buffer plus, for frame means, one shard's rows. The same read checks each shard against its
record (`shard_checks`); a mismatch stops the layer before its folder replaces the old one.
A run under a mounted URL root whose shards stay in the bucket is read by ranges (`tensor_files.open_read`):
each shard's header and row columns, then only the runs of rows the concepts select (`slice_copy`); such a
shard's identity check is its object's size and ETag against its publication record, when the first pass
opens it.

Outputs, per layer (the seed's layout):

    <output-dir>/layerNN/<concept>.pt            (rows, width) float32, torch.load(weights_only=True)
    <output-dir>/layerNN/<concept>.safetensors   `residuals` + per-row int64 columns
    <output-dir>/layerNN/index.json              concept -> files, rows, segments, token selection, run
"""

from __future__ import annotations

import logging
import os
import unicodedata
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import field_validator

from steering_core.capture.shard_checks import ShardChecks
from steering_core.capture.shards import STEP, RunMetadata, ShardRecord, TokenType, open_shard, read_run_metadata
from steering_core.capture.slice_copy import Part, copy_shard
from steering_core.capture.slice_files import SliceFile
from steering_core.data.concept_map import ConceptMap, ConceptRow, read_concept_map
from steering_core.data.dataset import INFO_FILE, dataset_fingerprint
from steering_core.devices import parse_device
from steering_core.layout import SLICE_INDEX_FILE, layer_dir
from steering_core.remote.locks import output_lock
from steering_core.remote.reads import RemoteFile
from steering_core.reporting.progress import Progress, ProgressCallback
from steering_core.storage.fileio import atomic_dir, read_json, sha256_file, sha256_json, write_json
from steering_core.storage.schema import StrictModel, describe_ranges
from steering_core.tensor_files import TensorLocation, open_read

logger = logging.getLogger(__name__)

SLICE_PT = "{name}.pt"
SLICE_SAFETENSORS = "{name}.safetensors"
SLICE_FORMAT_VERSION = 1
_BUFFER_BYTES = 8 << 20  # shard bytes read at a time in the second pass
_MAX_NAME_BYTES = 200  # file systems cap names at 255 bytes; leave room for suffixes and a hash
_UNSAFE = {"/", "\\", "\0", ":"}  # path separators (and ':' for Windows/macOS shares)


Reduce = Literal["token", "frame"]  # rows per captured frame in a slice
Opened = tuple[Path | RemoteFile, TensorLocation]  # a shard of the first pass: its file or checked object, its rows


class SliceSettings(StrictModel):
    """How concept slices are cut from a run."""

    layers: tuple[int, ...] = (12,)  # the seed's SAE layer
    token_type: TokenType = "instructions"
    reduce: Reduce = "token"  # one row per captured token, or their mean per frame
    max_samples_per_concept: int | None = None  # cap on rows (token) or frames (frame), evenly spaced
    verify_checksums: bool = True  # check every shard read against its record's CRC-32 (or sha256): a damaged one stops
    # (shards read by ranges from a bucket are checked by their objects' size and ETag instead, see shard_checks)
    device: str = "cpu"  # where frame means are computed; outputs are always saved from CPU
    holdout_episodes: tuple[int, ...] = ()  # episodes held out for evaluation: their frames are never sliced

    @field_validator("device")
    @classmethod
    def _torch_device(cls, device: str) -> str:
        parse_device(device)  # a name torch does not know fails here, not after the first pass
        return device


@dataclass
class _Selection:
    """Rows of one concept found in the first pass, per shard position: row numbers and their columns."""

    rows: dict[int, np.ndarray] = field(default_factory=dict)  # shard position -> (n,) ascending row numbers
    columns: dict[int, dict[str, np.ndarray]] = field(default_factory=dict)  # shard position -> row columns, (n,)


def safe_file_name(concept: str) -> str:
    """Return a readable file stem for a concept: no path separators, control characters or leading dots."""
    cleaned = "".join(
        "_" if ch in _UNSAFE or unicodedata.category(ch).startswith("C") else ch
        for ch in unicodedata.normalize("NFC", concept)
    ).strip().lstrip(".")
    encoded = cleaned.encode("utf-8")
    if len(encoded) > _MAX_NAME_BYTES:
        cleaned = encoded[:_MAX_NAME_BYTES].decode("utf-8", errors="ignore").rstrip()
    return cleaned or "concept"


def slice_file_names(concepts: Sequence[str]) -> dict[str, str]:
    """Return concept -> unique file stem; clashes (also case-insensitive ones) get a short hash suffix."""
    stems = {concept: safe_file_name(concept) for concept in concepts}
    counts: dict[str, int] = {}
    for stem in stems.values():
        counts[stem.casefold()] = counts.get(stem.casefold(), 0) + 1
    return {
        concept: stem if counts[stem.casefold()] == 1 else f"{stem} [{sha256_json(concept)[:8]}]"
        for concept, stem in stems.items()
    }


def slice_concepts(
    run_dir: str | os.PathLike,
    concept_map_path: str | os.PathLike,
    output_dir: str | os.PathLike,
    settings: SliceSettings = SliceSettings(),
    progress: ProgressCallback | None = None,
) -> dict[int, Path]:
    """Write per-concept residual tensors for every requested layer; return layer -> index.json path.

    Raises ValueError when the run lacks a layer or the token type, when the concept map names
    frames the run never captured (a map of another dataset), or when a concept is empty.
    """
    run_dir, output_dir = Path(run_dir), Path(output_dir)
    metadata = read_run_metadata(run_dir)
    concept_map = read_concept_map(concept_map_path).without_episodes(settings.holdout_episodes)
    _check_request(run_dir, metadata, concept_map, concept_map_path, settings)
    layers = list(settings.layers)
    total = sum(len(metadata.layer_shards(layer)) for layer in layers)
    written: dict[int, Path] = {}
    with Progress(total, f"slice {Path(output_dir).name}", "shard", callback=progress, logger=logger) as bar:
        for layer in layers:
            written[layer] = _slice_layer(
                run_dir, metadata, concept_map, Path(concept_map_path), output_dir, layer, settings, bar.update
            )
    return written


def _check_request(
    run_dir: Path, metadata: RunMetadata, concept_map: ConceptMap, map_path: str | os.PathLike, settings: SliceSettings
) -> None:
    """Raise once listing every mismatch between the request, the run and the concept map."""
    problems = []
    run = metadata.run
    if settings.token_type != run.token_type:
        problems.append(
            f"{run_dir}: the run captured `{run.token_type}` tokens, not `{settings.token_type}`; "
            f"pass --token-type {run.token_type} or capture with --token-type {settings.token_type}"
        )
    missing_layers = [layer for layer in settings.layers if layer not in run.layers]
    if missing_layers:
        problems.append(
            f"{run_dir}: the run has layers {list(run.layers)}, not {missing_layers}; "
            f"re-run capture with --layers {','.join(str(layer) for layer in missing_layers)}"
        )
    problems += _dataset_problems(run_dir, run.sources, concept_map, map_path)
    captured = set(metadata.episodes)
    for concept, segments in concept_map.concepts.items():
        if not segments:
            problems.append(f"{map_path}: concept {concept!r} has no segments; remove it or rebuild the concept map")
        for number, segment in enumerate(segments):
            if segment.episode_index not in captured:
                problems.append(
                    f"{map_path}: concept {concept!r} segment {number} needs episode {segment.episode_index} "
                    f"(frames {segment.frame_start}-{segment.frame_end}), which run {run_dir} never captured "
                    f"(it holds episodes {describe_ranges(sorted(captured))}); the concept map belongs to another "
                    "dataset or the capture is incomplete"
                )
    if problems:
        raise ValueError("\n".join(problems))


def _dataset_problems(run_dir: Path, sources: dict[str, Any], concept_map: ConceptMap, map_path: Any) -> list[str]:
    """Return why the concept map is of another dataset than the run's: its repo_id, or its dataset's content.

    The content is compared when the map's dataset folder is still there (the fingerprint is location-free);
    a run recorded before sources were kept, or a map whose folder moved, is compared by what remains.
    """
    problems = []
    if sources.get("repo_id") and concept_map.repo_id != sources["repo_id"]:
        problems.append(
            f"{map_path}: the concept map is of dataset {concept_map.repo_id!r}, but run {run_dir} captured "
            f"{sources['repo_id']!r}; build the concept map from the run's dataset"
        )
    root = Path(concept_map.lerobot_root)
    recorded = sources.get("dataset_fingerprint")
    if recorded and (root / INFO_FILE).is_file() and (found := dataset_fingerprint(root)) != recorded:
        problems.append(
            f"{map_path}: its dataset {root} has fingerprint {found[:12]}..., run {run_dir} captured a dataset with "
            f"fingerprint {recorded[:12]}...; build the concept map from the run's dataset, or capture this one"
        )
    return problems


def _slice_layer(
    run_dir: Path,
    metadata: RunMetadata,
    concept_map: ConceptMap,
    map_path: Path,
    output_dir: Path,
    layer: int,
    settings: SliceSettings,
    advance: Callable[[], None],
) -> Path:
    """Select, read and write the slices of one layer; return its index.json path.

    The layer folder is locked while it is written; a complete folder from the same run, concept map and
    settings (its index.json says so and its files exist) is kept, so a second run waits, then skips it.
    """
    records = metadata.layer_shards(layer)
    target = output_dir / layer_dir(layer)
    header = {
        "format_version": SLICE_FORMAT_VERSION,
        "layer": layer,
        "width": metadata.run.width,
        "settings": settings.model_dump(mode="json", exclude={"layers", "device"}),
        "run_dir": str(run_dir.resolve()),
        "run_fingerprint": metadata.run_fingerprint,
        "concept_map": str(map_path.resolve()),
        "concept_map_sha256": sha256_file(map_path),
        "token_selection": {"token_type": metadata.run.token_type, "tasks": metadata.tasks},
    }
    with output_lock(target):
        if _complete_layer(target, header):
            logger.info("layer %d: %s already holds these slices; kept", layer, target)
            for _ in records:
                advance()
            return target / SLICE_INDEX_FILE
        checks = ShardChecks(run_dir, records, _positions_read(records, concept_map), settings.verify_checksums)
        with checks.blame():
            selections, opened = _select_rows(run_dir, records, concept_map, map_path, settings)
            plans = {concept: _plan(selection, settings.reduce) for concept, selection in selections.items()}
            with atomic_dir(target, overwrite=True) as staging:
                staging.mkdir(parents=True)
                files = _write_slices(staging, plans, len(records), opened, checks, metadata.run.width, settings,
                                      advance)
                _write_index(staging, header, files, concept_map)
                checks.check()  # before the staging folder takes the target's place
    logger.info("layer %d: wrote %d concept slices to %s", layer, len(plans), target)
    return target / SLICE_INDEX_FILE


def _complete_layer(target: Path, header: dict[str, Any]) -> bool:
    """Return True if `target` holds the slices `header` describes, every listed file present."""
    index_path = target / SLICE_INDEX_FILE
    if not index_path.is_file():
        return False
    try:
        index = read_json(index_path)
    except ValueError:
        return False
    if not isinstance(index, dict) or {k: index.get(k) for k in header} != header:
        return False
    entries = index.get("concepts")
    return isinstance(entries, dict) and all(
        isinstance(entry, dict) and (target / str(entry.get("pt"))).is_file()
        and (target / str(entry.get("safetensors"))).is_file() for entry in entries.values())


def _write_index(staging: Path, header: dict[str, Any], files: dict[str, SliceFile], concept_map: ConceptMap) -> None:
    """Write the layer's index.json: the header, then per concept its files, rows, frames and segments."""
    entries = {
        concept: {
            "pt": file.path.with_suffix(".pt").name,
            "safetensors": file.path.name,
            "rows": file.rows,
            "frames": file.frames,
            "segments": [segment.model_dump(mode="json") for segment in concept_map.concepts[concept]],
        }
        for concept, file in files.items()
    }
    write_json(staging / SLICE_INDEX_FILE, {**header, "concepts": entries})


def _positions_read(records: Sequence[ShardRecord], concept_map: ConceptMap) -> list[int]:
    """Return the positions of the shards holding an episode of the concept map: the only ones read."""
    episodes = {segment.episode_index for segments in concept_map.concepts.values() for segment in segments}
    return [position for position, record in enumerate(records) if episodes.intersection(record.episodes)]


def _select_rows(
    run_dir: Path, records: Sequence[ShardRecord], concept_map: ConceptMap, map_path: Path, settings: SliceSettings
) -> tuple[dict[str, _Selection], dict[int, Opened]]:
    """First pass over the row columns: return each concept's rows, checking every segment is fully captured,
    and per opened shard (by position) what `open_read` opens again and where it keeps its residual matrix."""
    by_episode: dict[int, list[tuple[str, int, ConceptRow]]] = {}
    for concept, segments in concept_map.concepts.items():
        for number, segment in enumerate(segments):
            by_episode.setdefault(segment.episode_index, []).append((concept, number, segment))
    selections = {concept: _Selection() for concept in concept_map.concepts}
    opened: dict[int, Opened] = {}
    frames_found: dict[tuple[str, int], set[int]] = {}
    problems: list[str] = []
    for position, record in enumerate(records):
        wanted = [item for episode in record.episodes for item in by_episode.get(episode, [])]
        if not wanted:
            continue
        with open_shard(run_dir / record.file, width=record.width, dtype=record.dtype, rows=record.rows) as reader:
            cols = reader.columns()
            opened[position] = reader.source, reader.residual_location()
        per_concept: dict[str, np.ndarray] = {}
        for concept, number, segment in wanted:
            hit = (
                (cols["episode_index"] == segment.episode_index)
                & (cols["frame_index"] >= segment.frame_start)
                & (cols["frame_index"] <= segment.frame_end)
            )
            frames = cols["frame_index"][hit]
            expected_index = segment.start_index + frames - segment.frame_start
            wrong = cols["index"][hit] != expected_index
            if wrong.any():
                at = int(np.argmax(wrong))
                problems.append(
                    f"{map_path}: concept {concept!r} segment {number} puts episode {segment.episode_index} frame "
                    f"{int(frames[at])} at index {int(expected_index[at])}, but run {run_dir} captured it at index "
                    f"{int(cols['index'][hit][at])}; the concept map belongs to another dataset"
                )
            frames_found.setdefault((concept, number), set()).update(frames.tolist())
            per_concept[concept] = per_concept.get(concept, np.zeros_like(hit)) | hit
        for concept, hit in per_concept.items():
            rows = np.flatnonzero(hit)
            selections[concept].rows[position] = rows
            selections[concept].columns[position] = {name: values[rows] for name, values in cols.items()}
    for concept, segments in concept_map.concepts.items():
        for number, segment in enumerate(segments):
            expected = set(range(segment.frame_start, segment.frame_end + 1))
            missing = sorted(expected - frames_found.get((concept, number), set()))
            if missing:
                problems.append(
                    f"{map_path}: concept {concept!r} segment {number} needs episode {segment.episode_index} frames "
                    f"{describe_ranges(missing)}, which run {run_dir} never captured; the concept map belongs to another "
                    "dataset or the capture is incomplete"
                )
    problems += [
        f"{map_path}: concept {concept!r} selects no {run_dir} rows (its frames have no "
        f"`{settings.token_type}` tokens); check the concept map and the capture's token type"
        for concept, selection in selections.items()
        if not any(len(rows) for rows in selection.rows.values())
    ]
    if problems:
        raise ValueError("\n".join(problems))
    if settings.max_samples_per_concept is not None:
        for selection in selections.values():
            _subsample(selection, settings.max_samples_per_concept, by_frame=settings.reduce == "frame")
    return selections, opened


def _subsample(selection: _Selection, limit: int, *, by_frame: bool) -> None:
    """Keep `limit` evenly spaced units (rows, or frames with all their rows) in dataset order.

    Unit i of n is kept when it is floor(j * n / limit) for some j < limit: deterministic, no
    random seed, and spread over every segment rather than the first ones.
    """
    positions = sorted(selection.rows)
    if not positions:
        return
    columns = {name: np.concatenate([selection.columns[p][name] for p in positions]) for name in selection.columns[positions[0]]}
    owner = np.concatenate([np.full(len(selection.rows[p]), p) for p in positions])
    local = np.concatenate([selection.rows[p] for p in positions])
    order = np.lexsort((_within_frame(columns), columns["index"]))
    units = columns["index"][order] if by_frame else np.arange(len(order))
    unique_units, unit_of_row = np.unique(units, return_inverse=True)
    if unique_units.size <= limit:
        return
    chosen = np.zeros(unique_units.size, dtype=bool)
    chosen[(np.arange(limit) * unique_units.size) // limit] = True
    keep = order[chosen[unit_of_row]]
    for p in positions:
        mine = keep[owner[keep] == p]
        mine.sort()
        if mine.size:
            selection.rows[p] = local[mine]
            selection.columns[p] = {name: values[mine] for name, values in columns.items()}
        else:
            del selection.rows[p], selection.columns[p]


def _write_slices(
    staging: Path,
    plans: dict[str, tuple[dict[int, Part], dict[str, np.ndarray]]],
    shards: int,
    opened: dict[int, Opened],
    checks: ShardChecks,
    width: int,
    settings: SliceSettings,
    advance: Callable[[], None],
) -> dict[str, SliceFile]:
    """Second pass: copy each concept's rows from the layer's `shards` into its files in `staging`; return
    concept -> file.

    Each shard read in the first pass is read once more, through one bounded buffer, its rows going to
    their place in each concept's `.safetensors` (in dataset order, `_plan`) and its bytes to its check
    (`slice_copy.copy_shard`). Each `.pt` is then saved from its finished `.safetensors`.
    """
    stems = slice_file_names(list(plans))
    files = {concept: SliceFile(staging / SLICE_SAFETENSORS.format(name=stems[concept]), columns, width)
             for concept, (_, columns) in plans.items()}
    buffer = torch.empty(max([_BUFFER_BYTES, *(where.row_bytes for _, where in opened.values())]), dtype=torch.uint8)
    try:
        for position in range(shards):
            parts = [(shares[position], files[concept]) for concept, (shares, _) in plans.items() if position in shares]
            digest = checks.digest(position)
            if parts or digest is not None:
                source, location = opened[position]
                with open_read(source) as (handle, _):
                    copy_shard(handle, location, parts, buffer, settings.device, digest)
                if digest is not None:
                    checks.found(position, digest)
            advance()
    finally:
        for file in files.values():
            file.close()
    for file in files.values():
        file.save_pt(file.path.with_suffix(".pt"))
    return files


def _plan(selection: _Selection, reduce: str) -> tuple[dict[int, Part], dict[str, np.ndarray]]:
    """Return one concept's parts per shard position and its output columns, in dataset order.

    Output units are rows (reduce=token, ordered by index, then token position) or frames
    (reduce=frame, ordered by index; columns index, episode_index, frame_index and `tokens`,
    the number of rows averaged).
    """
    positions = sorted(selection.rows)
    units: list[dict[str, np.ndarray]] = []
    frame_of_row: dict[int, np.ndarray | None] = {}
    for p in positions:
        columns = selection.columns[p]
        if reduce == "frame":
            _, first, inverse, counts = np.unique(
                columns["index"], return_index=True, return_inverse=True, return_counts=True
            )
            units.append({name: columns[name][first] for name in ("index", "episode_index", "frame_index")}
                         | {"tokens": counts.astype(np.int64)})
            frame_of_row[p] = inverse
        else:
            units.append(columns)
            frame_of_row[p] = None
    columns = {name: np.concatenate([unit[name] for unit in units]) for name in units[0]}
    secondary = _within_frame(columns) if reduce == "token" else np.zeros_like(columns["index"])
    order = np.lexsort((secondary, columns["index"]))
    dest = np.empty_like(order)
    dest[order] = np.arange(len(order))
    bounds = np.cumsum([0] + [len(unit["index"]) for unit in units])
    parts = {
        p: Part(selection.rows[p], dest[bounds[i] : bounds[i + 1]], frame_of_row[p]) for i, p in enumerate(positions)
    }
    return parts, {name: np.ascontiguousarray(values[order]) for name, values in columns.items()}


def _within_frame(columns: dict[str, np.ndarray]) -> np.ndarray:
    """Return the order of rows within a frame: the denoising step (action token types), else the token position."""
    return columns[STEP] if STEP in columns else columns["token_position"]
