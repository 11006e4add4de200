"""Residual capture: every frame of a LeRobot dataset through pi0.5's prefix, selected tokens kept.

Frames come from `steering_core.capture.frames`; each frame's task is tokenised in the checkpoint's
prompt format; the model runs once per batch for all requested layers, and only the selected prompt
tokens' rows are kept. Rows are written per episode group (`steering_core.capture.shards`), so an
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
from tqdm import tqdm

from steering_core.capture.frames import FRAME_KEYS, batch_plan, frame_loader, frame_source
from steering_core.capture.identity import episode_records, run_spec
from steering_core.capture.settings import (
    N_CAMERAS,
    STATE_KEY,
    CaptureInputs,
    CaptureSettings,
    check_inputs,
    select_tokens,
)
from steering_core.capture.shards import (
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
from steering_core.data.dataset import DatasetMeta, read_meta
from steering_core.devices import resolve_device
from steering_core.fileio import sha256_json
from steering_core.pi05 import TokenizedPrompt, quantile_normalize

if TYPE_CHECKING:
    from steering_core.pi05.model import Pi05Prefix

logger = logging.getLogger(__name__)

Progress = Callable[[int, int], None]  # (frames done, frames in total)


@dataclass(frozen=True)
class CaptureResult:
    """What one `capture` call did: shard keys written and skipped, frames run through the model."""

    run_dir: Path
    written: tuple[str, ...]
    skipped: tuple[str, ...]
    frames: int
    metadata: RunMetadata | None  # None when only some episodes were captured (a worker of a split run)


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
    progress: Progress | None = None,
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
    meta = read_meta(dataset_root)
    inputs = check_inputs(meta, settings)
    groups = _episode_groups(meta, settings.episodes_per_shard, episodes)
    if max_frames is not None:
        groups = _first_groups(groups, {e.episode_index: e.length for e in meta.episodes}, max_frames)
    spec = run_spec(meta, repo_id, inputs, settings)
    check_run_spec(run_dir, spec)

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
    if todo:
        job = CaptureJob(meta, repo_id, run_dir, spec, settings, inputs, todo, group_inputs, frames)
        _capture_groups(job, progress)
    else:
        write_run_spec(run_dir, spec)  # records this call's sources
    metadata = None
    if episodes is None:
        write_run_metadata(run_dir)
        metadata = read_run_metadata(run_dir)
    return CaptureResult(run_dir=run_dir, written=tuple(todo), skipped=skipped, frames=frames, metadata=metadata)


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


def _capture_groups(job: CaptureJob, progress: Progress | None) -> None:
    """Run the model over the groups' frames and write each group's shards as soon as it is complete."""
    from steering_core.pi05.model import Pi05Prefix

    settings = job.settings
    episodes = sorted(e for members in job.groups.values() for e in members)
    frames = frame_source(job.meta, job.repo_id, episodes, settings.video_backend)
    plan = batch_plan(frames, job.groups, settings.batch_size)
    keys = [*FRAME_KEYS, *([STATE_KEY] if job.inputs.norm_stats is not None else [])]
    # Start the workers first: they decode the first batches while the checkpoint loads, and they fork
    # before CUDA is initialised.
    batches = iter(frame_loader(frames, plan, keys, settings.arch.image_size, settings.num_workers,
                                pin_memory=resolve_device(settings.device).type == "cuda"))
    model = Pi05Prefix.from_checkpoint(
        settings.checkpoint_path, settings.arch, max(settings.layers), settings.device, settings.dtype
    )
    write_run_spec(job.run_dir, job.spec)  # only once the checkpoint loaded: a bad one leaves no run folder behind
    remaining = {key: sum(1 for k, _ in plan if k == key) for key in job.groups}
    prompts: dict[str, TokenizedPrompt] = {}
    done = 0
    buffers: dict[str, _GroupRows] = {}
    with tqdm(total=job.frames, desc="capture", unit="frame", disable=None) as bar:
        for (key, _), batch in zip(plan, batches, strict=True):
            buffer = buffers.setdefault(key, _GroupRows(per_layer={layer: [] for layer in settings.layers}))
            _capture_batch(model, batch, job, prompts, buffer)
            remaining[key] -= 1
            if remaining[key] == 0:
                _write_group(job, key, buffers.pop(key))
            size = len(batch["task"])
            done += size
            bar.update(size)
            if progress is not None:
                progress(done, job.frames)


def _prompt(job: CaptureJob, task: str, state: torch.Tensor | None, cache: dict[str, TokenizedPrompt]) -> TokenizedPrompt:
    """Return the tokenised prompt of one frame, cached per task when the state stays out of the prompt.

    Discrete-state prompts are not cached: nearly every frame has its own state bins.
    """
    tokenizer, norm_stats = job.inputs.tokenizer, job.inputs.norm_stats
    if norm_stats is not None:
        return tokenizer.tokenize(task, quantile_normalize(state.numpy(), norm_stats))
    if task not in cache:
        cache[task] = tokenizer.tokenize(task)
    return cache[task]


def _capture_batch(
    model: Pi05Prefix, batch: dict[str, Any], job: CaptureJob, cache: dict[str, TokenizedPrompt], buffer: _GroupRows
) -> None:
    """Run one batch and append its selected rows (all layers) and their columns to `buffer`."""
    settings = job.settings
    tasks = list(batch["task"])
    states = batch.get(STATE_KEY)
    prompts = [_prompt(job, task, states[b] if states is not None else None, cache) for b, task in enumerate(tasks)]
    tokens = torch.from_numpy(np.stack([p.ids for p in prompts]))
    token_mask = torch.from_numpy(np.stack([p.mask for p in prompts]))
    residuals = model.residuals(batch["images"], batch["image_masks"], tokens, token_mask, settings.layers)
    language_start = settings.arch.prefix_length(N_CAMERAS, 0)  # language follows every camera slot
    selected = [select_tokens(p, settings.token_type) for p in prompts]
    frame_of_row = np.concatenate([np.full(len(s), b, dtype=np.int64) for b, s in enumerate(selected)])
    language_index = np.concatenate(selected)
    positions = language_start + language_index
    rows_b, rows_p = torch.from_numpy(frame_of_row), torch.from_numpy(positions)
    for layer in settings.layers:
        buffer.per_layer[layer].append(residuals[layer][rows_b.to(model.device), rows_p.to(model.device)].cpu())
    columns = {
        "index": batch["index"].numpy()[frame_of_row],
        "episode_index": batch["episode_index"].numpy()[frame_of_row],
        "frame_index": batch["frame_index"].numpy()[frame_of_row],
        "token_position": positions,
        "token_id": np.concatenate([p.ids[s] for p, s in zip(prompts, selected)]),
    }
    for name, values in columns.items():
        buffer.columns.setdefault(name, []).append(values.astype(np.int64))
    for task, prompt, chosen in zip(tasks, prompts, selected):
        _record_task(buffer.tasks, task, prompt, chosen, language_start)


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
    """Write one shard per layer for a finished episode group."""
    episodes = job.groups[key]
    columns = {name: torch.from_numpy(np.concatenate(parts)) for name, parts in buffer.columns.items()}
    for layer, parts in buffer.per_layer.items():
        rows = ShardRows(residuals=torch.cat(parts), **columns)
        write_shard(job.run_dir, job.spec, layer, key, rows, episodes=episodes, inputs=job.group_inputs[key],
                    tasks=buffer.tasks)
    logger.debug("shard group %s (episodes %s): %d rows per layer", key, list(episodes), len(columns["index"]))
