"""Residual capture: every frame of a LeRobot dataset through pi0.5's prefix, selected tokens kept.

Frames come from `steering_core.capture.frames`; each frame's task is tokenised in the checkpoint's
prompt format; the model runs once per batch for all requested layers, and only the selected prompt
tokens' rows are kept. The action token types (`decision`, `adarms`) run the whole policy instead and
keep one row per frame and denoising step (`steering_core.capture.action_rows`). Rows are written per episode group (`steering_core.capture.shards`), so an
interrupted run resumes where it stopped and several workers can split one run by `episodes`.

Batches never cross an episode group and always start at its first frame, so recomputing a group
gives byte-identical shards.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from steering_core.capture.action_rows import adarms_rows, decision_rows, frame_noise
from steering_core.capture.frames import FRAME_KEYS, batch_plan, frame_batches, frame_source
from steering_core.capture.run_identity import episode_records, run_spec
from steering_core.capture.selected_rows import selected_residuals
from steering_core.capture.settings import (
    N_CAMERAS,
    STATE_KEY,
    CaptureInputs,
    CaptureSettings,
    check_inputs,
    select_tokens,
)
from steering_core.capture.shards import (
    ACTION_TOKEN_TYPES,
    STEP,
    RunMetadata,
    RunSpec,
    ShardRows,
    check_run_spec,
    find_complete_shard,
    group_episodes,
    read_run_metadata,
    write_run_metadata,
    write_run_spec,
    write_shard,
)
from steering_core.data.dataset import DatasetMeta
from steering_core.data.dataset_checks import check_dataset
from steering_core.data.image_cells import check_image_cells, check_png_headers
from steering_core.devices import resolve_device
from steering_core.pi05 import TokenizedPrompt
from steering_core.remote.locks import group_locks
from steering_core.reporting.progress import Progress, ProgressCallback
from steering_core.storage.fileio import check_output_dir, sha256_json

if TYPE_CHECKING:
    from steering_core.pi05.model import Pi05Prefix
    from steering_core.pi05.policy import Pi05Policy

logger = logging.getLogger(__name__)



@dataclass(frozen=True)
class CaptureResult:
    """What one `capture` call did: shard keys written and skipped, frames run through the model."""

    run_dir: Path
    written: tuple[str, ...]
    skipped: tuple[str, ...]
    frames: int
    metadata: RunMetadata | None  # None when only some episodes were captured (a worker of a split run)
    reduced_batch_size: int | None = None  # frames per forward pass after CUDA ran out of memory, if it did


@dataclass(frozen=True)
class CaptureJob:
    """Everything the capture loop needs: where, what, with which inputs, and which groups are still to do."""

    meta: DatasetMeta
    repo_id: str
    run_dir: Path
    spec: RunSpec
    settings: CaptureSettings
    inputs: CaptureInputs
    groups: dict[str, tuple[int, ...]]  # shard key -> episodes, only the groups to compute
    group_inputs: dict[str, str]  # shard key -> hash of what its rows depend on
    frames: int  # frames in `groups`
    limits: dict[str, int] = field(default_factory=dict)  # "batch_size": frames per forward pass after an OOM


@dataclass
class _GroupRows:
    """Selected rows of one episode group accumulated across its batches."""

    per_layer: dict[int, list[torch.Tensor]]
    columns: dict[str, list[np.ndarray]] = field(default_factory=dict)
    tasks: dict[str, dict[str, Any]] = field(default_factory=dict)


def capture(
    dataset_root: str | os.PathLike,
    repo_id: str,
    run_dir: str | os.PathLike,
    settings: CaptureSettings,
    episodes: Sequence[int] | None = None,
    progress: ProgressCallback | None = None,
    max_frames: int | None = None,
) -> CaptureResult:
    """Capture the residuals of every frame (or of `episodes`) into `run_dir`; return what was done.

    Complete, checksum-valid shards computed from the same inputs are skipped. With `episodes`, only
    those episode groups are captured (whole groups only) and `metadata.json` is left to
    `write_run_metadata`, so several workers can split one run. `max_frames` (the seed's
    `--max-samples-per-layer`) keeps the first episode groups until they hold that many frames: whole
    groups, so the last one may go past it and a later run with a larger limit reuses every shard.
    """
    run_dir = Path(run_dir)
    check_output_dir(run_dir, "run folder")  # before the model loads (~25 s on pi0.5), not after
    meta = check_dataset(dataset_root)
    inputs = check_inputs(meta, settings)
    groups = _episode_groups(meta, settings.episodes_per_shard, episodes)
    if max_frames is not None:
        groups = _first_groups(groups, {e.episode_index: e.length for e in meta.episodes}, max_frames)
    chosen = [e for members in groups.values() for e in members]
    check_image_cells(meta, chosen)  # before the run folder exists
    check_png_headers(meta, chosen)
    spec = run_spec(meta, repo_id, inputs, settings)
    check_run_spec(run_dir, spec)

    with group_locks(run_dir, (int(key) for key in groups)):  # another capture of these groups: wait, then skip
        todo, skipped, frames, reduced = _capture_missing(meta, repo_id, run_dir, spec, settings, inputs, groups,
                                                          progress)
    metadata = None
    if episodes is None:
        write_run_metadata(run_dir)
        metadata = read_run_metadata(run_dir)
    return CaptureResult(run_dir=run_dir, written=tuple(todo), skipped=skipped, frames=frames, metadata=metadata,
                         reduced_batch_size=reduced)


def _capture_missing(
    meta: DatasetMeta, repo_id: str, run_dir: Path, spec: RunSpec, settings: CaptureSettings, inputs: CaptureInputs,
    groups: dict[str, tuple[int, ...]], progress: ProgressCallback | None,
) -> tuple[dict[str, tuple[int, ...]], tuple[str, ...], int, int | None]:
    """Capture the groups without a complete shard; return (groups computed, skipped, frames, reduced batch size)."""
    records = episode_records(meta, [e for members in groups.values() for e in members])
    group_inputs = {key: sha256_json({"run": spec.identity(), "episodes": [records[e] for e in members]})
                    for key, members in groups.items()}
    todo = {key: members for key, members in groups.items()
            if any(find_complete_shard(run_dir, spec, layer, key, group_inputs[key]) is None
                   for layer in settings.layers)}
    skipped = tuple(key for key in groups if key not in todo)
    if skipped:
        logger.info("%d of %d shard group(s) already complete, skipped", len(skipped), len(groups))
    lengths = {e.episode_index: e.length for e in meta.episodes}
    frames = sum(lengths[e] for members in todo.values() for e in members)
    reduced = None
    if todo:
        job = CaptureJob(meta, repo_id, run_dir, spec, settings, inputs, todo, group_inputs, frames)
        _capture_groups(job, progress)
        reduced = job.limits.get("batch_size")
    else:
        write_run_spec(run_dir, spec)  # records this call's sources
    return todo, skipped, frames, reduced


def _episode_groups(
    meta: DatasetMeta, episodes_per_shard: int, episodes: Sequence[int] | None
) -> dict[str, tuple[int, ...]]:
    """Return shard key -> episodes to capture; `episodes` must exist and cover whole groups."""
    groups = group_episodes((e.episode_index for e in meta.episodes), episodes_per_shard)
    if episodes is None:
        return groups
    wanted = set(int(e) for e in episodes)
    known = {e for members in groups.values() for e in members}
    problems = []
    if unknown := sorted(wanted - known):
        problems.append(f"episodes {unknown} are not in the dataset {meta.root} ({len(known)} episodes)")
    for key, members in groups.items():
        if wanted & set(members) and not set(members) <= wanted:
            problems.append(
                f"episodes {sorted(wanted & set(members))} split shard group {key} (episodes {list(members)}); "
                "pass whole groups (see steering_core.capture.shards.group_episodes)"
            )
    if problems:
        raise ValueError("\n".join(problems))
    return {key: members for key, members in groups.items() if wanted & set(members)}


def _first_groups(
    groups: dict[str, tuple[int, ...]], lengths: dict[int, int], max_frames: int
) -> dict[str, tuple[int, ...]]:
    """Return the leading groups, in order, up to the first one that brings their frames to `max_frames`."""
    if max_frames < 1:
        raise ValueError(f"max_frames is {max_frames}, expected a positive number of frames")
    kept: dict[str, tuple[int, ...]] = {}
    frames = 0
    for key, members in groups.items():
        if frames >= max_frames:
            break
        kept[key] = members
        frames += sum(lengths[e] for e in members)
    logger.info("max %d frames: capturing %d of %d episode group(s), %d frames", max_frames, len(kept), len(groups),
                frames)
    return kept


def _capture_groups(job: CaptureJob, progress: ProgressCallback | None) -> None:
    """Run the model over the groups' frames and write each group's shards as soon as it is complete."""
    settings = job.settings
    episodes = sorted(e for members in job.groups.values() for e in members)
    frames = frame_source(job.meta, job.repo_id, episodes, settings.video_backend)
    plan = batch_plan(frames, job.groups, settings.batch_size)
    keys = [*FRAME_KEYS, *([STATE_KEY] if job.inputs.reads_state else [])]
    # Start the workers first: they decode the first batches while the checkpoint loads, and they fork
    # before CUDA is initialised. The cameras are resized on the model's device, not in the workers.
    batches = frame_batches(frames, plan, keys, settings.arch.image_size, settings.num_workers,
                            resolve_device(settings.run_device), job.meta, job.inputs.robot.cameras)
    model = _load_model(settings, job.inputs)
    remaining = {key: sum(1 for k, _ in plan if k == key) for key in job.groups}
    prompts: dict[str, TokenizedPrompt] = {}
    buffers: dict[str, _GroupRows] = {}
    with Progress(job.frames, "capture", "frame", callback=progress, logger=logger) as bar:
        for (key, _), batch in zip(plan, batches, strict=True):
            buffer = buffers.setdefault(key, _GroupRows(per_layer={layer: [] for layer in settings.layers}))
            _capture_batch(model, batch, job, prompts, buffer)
            remaining[key] -= 1
            if remaining[key] == 0:
                _write_group(job, key, buffers.pop(key))
            bar.update(len(batch["task"]))


def _load_model(settings: CaptureSettings, inputs: CaptureInputs) -> Pi05Prefix | Pi05Policy:
    """Return the prefix up to the deepest layer, or the whole policy for the action token types."""
    if settings.token_type in ACTION_TOKEN_TYPES:
        return settings.model.load_policy(settings.run_device, settings.run_dtype, expert_arch=inputs.expert_arch)
    return settings.model.load_prefix(max(settings.layers), settings.run_device, settings.run_dtype)


def _prompt(job: CaptureJob, task: str, state: torch.Tensor | None, cache: dict[str, TokenizedPrompt]) -> TokenizedPrompt:
    """Return the tokenised prompt of one frame, cached per task when the state stays out of the prompt.

    Discrete-state prompts are not cached: nearly every frame has its own state bins.
    """
    tokenizer = job.inputs.tokenizer
    if job.inputs.reads_state:
        return tokenizer.tokenize(task, job.inputs.robot.normalization.normalize_state(state.numpy()[None])[0])
    if task not in cache:
        cache[task] = tokenizer.tokenize(task)
    return cache[task]


RowsOf = Callable[[int, int], dict[int, torch.Tensor]]  # frames [start, stop) of a batch -> layer -> rows


def _capture_batch(
    model: Pi05Prefix | Pi05Policy, batch: dict[str, Any], job: CaptureJob, cache: dict[str, TokenizedPrompt],
    buffer: _GroupRows,
) -> None:
    """Run one batch and append its selected rows (all layers) and their columns to `buffer`."""
    settings = job.settings
    tasks = list(batch["task"])
    states = batch.get(STATE_KEY)
    prompts = [_prompt(job, task, states[b] if states is not None else None, cache) for b, task in enumerate(tasks)]
    tokens = torch.from_numpy(np.stack([p.ids for p in prompts]))
    token_mask = torch.from_numpy(np.stack([p.mask for p in prompts]))
    language_start = settings.arch.prefix_length(N_CAMERAS, 0)  # language follows every camera slot
    selected = [select_tokens(p, settings.token_type) for p in prompts]
    if settings.token_type in ACTION_TOKEN_TYPES:
        frame_of_row = np.repeat(np.arange(len(prompts), dtype=np.int64), settings.num_steps)
        rows_of = _action_rows_of(model, batch, tokens, token_mask, settings)
        positions = np.full(len(frame_of_row), _action_position(settings, model), dtype=np.int64)
        token_ids = np.full(len(frame_of_row), -1, dtype=np.int64)  # the action tokens have no vocabulary id
        steps = {STEP: np.tile(np.arange(settings.num_steps, dtype=np.int64), len(prompts))}
    else:
        frame_of_row = np.concatenate([np.full(len(s), b, dtype=np.int64) for b, s in enumerate(selected)])
        positions = language_start + np.concatenate(selected)
        rows_of = _token_rows_of(model, batch, tokens, token_mask, frame_of_row, positions, settings.layers)
        token_ids = np.concatenate([p.ids[s] for p, s in zip(prompts, selected)])
        steps = {}
    kept = _kept_rows(rows_of, len(prompts), job)
    _check_finite(kept, batch, frame_of_row)
    for layer, rows in kept.items():
        buffer.per_layer[layer].append(rows.cpu())
    columns = {
        "index": batch["index"].numpy()[frame_of_row],
        "episode_index": batch["episode_index"].numpy()[frame_of_row],
        "frame_index": batch["frame_index"].numpy()[frame_of_row],
        "token_position": positions,
        "token_id": token_ids,
        **steps,
    }
    for name, values in columns.items():
        buffer.columns.setdefault(name, []).append(values.astype(np.int64))
    for task, prompt, chosen in zip(tasks, prompts, selected):
        _record_task(buffer.tasks, task, prompt, chosen, language_start)


def _action_position(settings: CaptureSettings, policy: Pi05Policy) -> int:
    """Return the `token_position` of action rows: the decision token's index in the chunk, -1 for adarms."""
    return policy.action_horizon - 1 if settings.token_type == "decision" else -1


def _action_rows_of(
    policy: Pi05Policy, batch: dict[str, Any], tokens: torch.Tensor, token_mask: torch.Tensor,
    settings: CaptureSettings,
) -> RowsOf:
    """Return the row function of the action token types: frame-major, num_steps rows per frame."""
    indices = batch["index"].tolist()

    def rows_of(start: int, stop: int) -> dict[int, torch.Tensor]:
        if settings.token_type == "adarms":
            return adarms_rows(policy, stop - start, settings.layers, settings.num_steps)
        noise = frame_noise(indices[start:stop], policy.action_horizon, policy.action_dim, settings.noise_seed)
        return decision_rows(policy, [i[start:stop] for i in batch["images"]],
                             [m[start:stop] for m in batch["image_masks"]], tokens[start:stop],
                             token_mask[start:stop], noise, settings.layers, settings.num_steps)

    return rows_of


def _token_rows_of(
    model: Pi05Prefix, batch: dict[str, Any], tokens: torch.Tensor, token_mask: torch.Tensor,
    frame_of_row: np.ndarray, positions: np.ndarray, layers: Sequence[int],
) -> RowsOf:
    """Return the row function of the prompt token types: the selected positions' residuals, in row order."""

    def rows_of(start: int, stop: int) -> dict[int, torch.Tensor]:
        inside = (frame_of_row >= start) & (frame_of_row < stop)
        # only the kept rows come back, and the deepest layer runs only their queries (PI05_SPEC section 14)
        return selected_residuals(model, [i[start:stop] for i in batch["images"]],
                                  [m[start:stop] for m in batch["image_masks"]],
                                  tokens[start:stop], token_mask[start:stop], layers,
                                  torch.from_numpy(frame_of_row[inside] - start),
                                  torch.from_numpy(positions[inside]))

    return rows_of


def _kept_rows(rows_of: RowsOf, size: int, job: CaptureJob) -> dict[int, torch.Tensor]:
    """Return layer -> the kept rows (rows, width) of a batch of `size` frames, run in parts no larger than the
    job's limit (rows are frame-major, so the parts' rows concatenate in row order).

    On CUDA out-of-memory the part size is halved (down to one frame) and kept for the rest of the job,
    which records it (`CaptureResult.reduced_batch_size`), instead of failing or retrying the same size.
    """
    step = min(size, job.limits.get("batch_size", size))
    while True:
        try:
            parts: dict[int, list[torch.Tensor]] = {layer: [] for layer in job.settings.layers}
            for start in range(0, size, step):
                for layer, rows in rows_of(start, min(start + step, size)).items():
                    parts[layer].append(rows)
            return {layer: torch.cat(chunks) for layer, chunks in parts.items()}
        except torch.cuda.OutOfMemoryError:
            if step == 1:
                raise
            del parts
            step = (step + 1) // 2
            job.limits["batch_size"] = step
            if torch.cuda.is_available():
                torch.cuda.empty_cache()
            logger.warning("CUDA out of memory: running %d frame(s) at a time from now on (batch_size %d)",
                           step, job.settings.batch_size)


def _check_finite(kept: dict[int, torch.Tensor], batch: dict[str, Any], frame_of_row: np.ndarray) -> None:
    """Raise naming the first layer, episode and frame whose kept rows hold NaN or Inf (one device sync per batch)."""
    finite = torch.stack([torch.isfinite(rows).all() for rows in kept.values()])
    if bool(finite.all()):
        return
    layer = list(kept)[int((~finite).nonzero()[0])]
    row = int((~torch.isfinite(kept[layer]).all(dim=-1)).nonzero()[0])
    frame = int(frame_of_row[row])
    raise ValueError(
        f"non-finite residuals (NaN or Inf) at layer {layer} in episode {int(batch['episode_index'][frame])} "
        f"(frame {int(batch['frame_index'][frame])}); the checkpoint holds non-finite weights or the compute dtype "
        "overflows: check the checkpoint, or capture with --dtype float32"
    )


def _record_task(
    tasks: dict[str, dict[str, Any]], task: str, prompt: TokenizedPrompt, chosen: np.ndarray, language_start: int
) -> None:
    """Record a task's selected token ids and prefix positions; flag it when frames select differently."""
    record = {
        "token_ids": prompt.ids[chosen].tolist(),
        "token_positions": (language_start + chosen).tolist(),
        "instruction": list(prompt.instruction),
        "varies_per_frame": False,
    }
    known = tasks.setdefault(task, record)
    if known is not record and not known["varies_per_frame"]:
        same = all(known[k] == record[k] for k in ("token_ids", "token_positions", "instruction"))
        known["varies_per_frame"] = not same  # discrete-state prompts: the state tokens change per frame


def _write_group(job: CaptureJob, key: str, buffer: _GroupRows) -> None:
    """Write run.json, then one shard per layer for a finished episode group: a run refused before its first group
    is complete (a bad checkpoint or frame) leaves no run folder behind."""
    write_run_spec(job.run_dir, job.spec)
    episodes = job.groups[key]
    columns = {name: torch.from_numpy(np.concatenate(parts)) for name, parts in buffer.columns.items()}
    columns.setdefault(STEP, None)
    for layer, parts in buffer.per_layer.items():
        rows = ShardRows(residuals=torch.cat(parts), **columns)
        write_shard(job.run_dir, job.spec, layer, key, rows, episodes=episodes, inputs=job.group_inputs[key],
                    tasks=buffer.tasks)
    logger.debug("shard group %s (episodes %s): %d rows per layer", key, list(episodes), len(columns["index"]))
