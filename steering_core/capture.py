"""Residual capture: every frame of a LeRobot dataset through pi0.5's prefix, selected tokens kept.

Frames are read by lerobot's `LeRobotDataset` and batched by a DataLoader whose workers decode and
resize images while the model runs. Each frame's task is tokenised in the checkpoint's prompt format;
the model runs once per batch for all requested layers, and only the selected prompt tokens' rows are
kept. Rows are written per episode group (`steering_core.shards`), so an interrupted run resumes where
it stopped and several workers can split one run by `episodes`.

Batches never cross an episode group and always start at its first frame, so recomputing a group
gives byte-identical shards.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import multiprocessing
import os
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import Field, field_validator
from torch.utils.data import DataLoader, Dataset, default_collate
from tqdm import tqdm

from steering_core.dataset import DatasetMeta, dataset_fingerprint, read_episode_columns, read_meta
from steering_core.fileio import sha256_file, sha256_json
from steering_core.pi05 import (
    NormStats,
    Pi05Arch,
    PromptFormat,
    PromptTokenizer,
    TokenizedPrompt,
    libero_camera_slots,
    quantile_normalize,
    read_norm_stats,
)
from steering_core.pi05.checkpoint import resolve_model_file
from steering_core.pi05.norm_stats import LIBERO_ASSET_ID, norm_stats_path
from steering_core.pi05.preprocess import LIBERO_IMAGE_KEYS
from steering_core.pi05.tokenizer import MAX_TOKEN_LEN
from steering_core.schema import StrictModel
from steering_core.shards import (
    RunMetadata,
    RunSpec,
    ShardRows,
    StorageDtype,
    TokenType,
    check_run_spec,
    find_complete_shard,
    group_episodes,
    read_run_metadata,
    write_run_metadata,
    write_run_spec,
    write_shard,
)

logger = logging.getLogger(__name__)

STATE_KEY = "state"  # the dataset feature the discrete-state prompt reads
CAMERA_DTYPES = ("image", "video")
N_CAMERAS = 3  # pi0.5's camera slots: base, left wrist, right wrist (absent in LIBERO, mask False)
# Modules the frame workers' forkserver imports once, so that each worker starts as fast as a fork.
WORKER_PRELOAD = ("torch", "lerobot.datasets.lerobot_dataset", "steering_core.capture")
_FINGERPRINT_SAMPLES = 16  # data blocks hashed by checkpoint_fingerprint, evenly spaced
_FINGERPRINT_BLOCK = 1 << 16  # 64 KiB each: 1 MiB read whatever the checkpoint size


class CaptureSettings(StrictModel):
    """What to capture and how; the seed's `save_residuals.py` flags plus the new ones."""

    checkpoint_path: Path  # openpi PyTorch checkpoint folder (model.safetensors) or the file itself
    tokenizer_path: Path  # PaliGemma SentencePiece model (paligemma_tokenizer.model)
    layers: tuple[int, ...] = (12,)  # the seed's SAE layer
    token_type: TokenType = "instructions"
    prompt_format: PromptFormat = PromptFormat.LIBERO  # pi05_libero's; other pi0.5 checkpoints: discrete_state
    max_token_len: int = Field(MAX_TOKEN_LEN, ge=1)
    norm_stats_path: Path | None = None  # discrete_state only; default <checkpoint>/assets/<asset id>/norm_stats.json
    norm_stats_asset_id: str = LIBERO_ASSET_ID
    skip_norm_stats: bool = False  # the seed's flag: never read norm stats (the libero format needs none)
    arch: Pi05Arch = Pi05Arch()
    batch_size: int = Field(32, ge=1)  # frames per forward pass; the seed used 128 on a large GPU
    device: str | None = None  # default CUDA when available, else CPU
    dtype: str | None = None  # compute dtype; default openpi's bfloat16 policy on CUDA, float32 on CPU
    storage_dtype: StorageDtype = "float32"
    episodes_per_shard: int = Field(1, ge=1)  # 1: adding demos never rewrites a shard
    num_workers: int = Field(2, ge=0)  # DataLoader processes decoding and resizing frames
    video_backend: str | None = None  # lerobot's decoder for video datasets (None: lerobot's default)

    @field_validator("layers")
    @classmethod
    def _layers_sorted(cls, layers: tuple[int, ...]) -> tuple[int, ...]:
        if not layers:
            raise ValueError("layers is empty; pass at least one decoder layer, e.g. 12")
        return tuple(sorted(set(layers)))


@dataclass(frozen=True)
class CaptureResult:
    """What one `capture` call did: shard keys written and skipped, frames run through the model."""

    run_dir: Path
    written: tuple[str, ...]
    skipped: tuple[str, ...]
    frames: int
    metadata: RunMetadata | None  # None when only some episodes were captured (a worker of a split run)


@dataclass
class _GroupRows:
    """Selected rows of one episode group accumulated across its batches."""

    per_layer: dict[int, list[torch.Tensor]]
    columns: dict[str, list[np.ndarray]] = field(default_factory=dict)
    tasks: dict[str, dict[str, Any]] = field(default_factory=dict)


def select_tokens(prompt: TokenizedPrompt, token_type: str) -> np.ndarray:
    """Return the language indices (n,) int64 a token type keeps from one tokenised prompt.

    `instructions`: the task's own tokens; `prompt`: every valid token (BOS, scaffolding, state);
    `last`: the last valid token.
    """
    if token_type == "instructions":
        return np.arange(*prompt.instruction, dtype=np.int64)
    if token_type == "prompt":
        return np.arange(prompt.n_valid, dtype=np.int64)
    if token_type == "last":
        return np.array([prompt.n_valid - 1], dtype=np.int64)
    raise ValueError(f"token_type {token_type!r} unknown; expected instructions, prompt or last")


def checkpoint_fingerprint(model_file: str | os.PathLike) -> str:
    """Return a sha256 over a safetensors file's header, its size and 16 evenly spaced 64 KiB data blocks.

    The header names every tensor with its dtype, shape and offsets; the sampled blocks tell apart two
    checkpoints of the same layout (e.g. base and fine-tuned). It reads about 1 MiB, so it cannot see
    a change confined to a few weights; hash the file with `sha256_file` when that matters.
    """
    path = Path(model_file)
    size = path.stat().st_size
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        header_length = struct.unpack("<Q", handle.read(8))[0]  # safetensors: u64 little-endian header size
        digest.update(handle.read(header_length))
        start = 8 + header_length
        span = max(size - start - _FINGERPRINT_BLOCK, 0)
        for sample in range(_FINGERPRINT_SAMPLES):
            handle.seek(start + span * sample // max(_FINGERPRINT_SAMPLES - 1, 1))
            digest.update(handle.read(_FINGERPRINT_BLOCK))
    digest.update(str(size).encode())
    return digest.hexdigest()


def capture(
    dataset_root: str | os.PathLike,
    repo_id: str,
    run_dir: str | os.PathLike,
    settings: CaptureSettings,
    episodes: Sequence[int] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> CaptureResult:
    """Capture the residuals of every frame (or of `episodes`) into `run_dir`; return what was done.

    Complete, checksum-valid shards computed from the same inputs are skipped. With `episodes`, only
    those episode groups are captured (whole groups only) and `metadata.json` is left to
    `write_run_metadata`, so several workers can split one run.
    """
    run_dir = Path(run_dir)
    meta = read_meta(dataset_root)
    model_file, tokenizer, norm_stats = _check_inputs(meta, settings)
    groups = _episode_groups(meta, settings.episodes_per_shard, episodes)
    spec = _run_spec(meta, repo_id, model_file, tokenizer, norm_stats, settings)
    check_run_spec(run_dir, spec)

    records = _episode_records(meta, [e for members in groups.values() for e in members])
    inputs = {key: sha256_json({"run": spec.identity(), "episodes": [records[e] for e in members]})
              for key, members in groups.items()}
    todo = {key: members for key, members in groups.items()
            if any(find_complete_shard(run_dir, spec, layer, key, inputs[key]) is None for layer in settings.layers)}
    skipped = tuple(key for key in groups if key not in todo)
    if skipped:
        logger.info("%d of %d shard group(s) already complete, skipped", len(skipped), len(groups))
    lengths = {e.episode_index: e.length for e in meta.episodes}
    frames = sum(lengths[e] for members in todo.values() for e in members)
    if todo:
        _capture_groups(meta, repo_id, run_dir, spec, settings, todo, inputs, tokenizer, norm_stats, frames, progress)
    else:
        write_run_spec(run_dir, spec)  # records this call's sources
    metadata = None
    if episodes is None:
        write_run_metadata(run_dir)
        metadata = read_run_metadata(run_dir)
    return CaptureResult(run_dir=run_dir, written=tuple(todo), skipped=skipped, frames=frames, metadata=metadata)


def _check_inputs(
    meta: DatasetMeta, settings: CaptureSettings
) -> tuple[Path, PromptTokenizer, NormStats | None]:
    """Return the checkpoint file, tokenizer and state norm stats after checking every input once."""
    model_file = resolve_model_file(settings.checkpoint_path)
    tokenizer = PromptTokenizer(settings.tokenizer_path, settings.max_token_len, settings.prompt_format)
    discrete = settings.prompt_format is PromptFormat.DISCRETE_STATE
    problems = []
    features = meta.info["features"]
    needed = [*LIBERO_IMAGE_KEYS, *([STATE_KEY] if discrete else [])]
    for name in needed:
        found = features.get(name, {}).get("dtype")
        wanted = CAMERA_DTYPES if name in LIBERO_IMAGE_KEYS else None
        if name not in features or (wanted and found not in wanted):
            problems.append(
                f"{meta.root}: feature `{name}` is {'missing' if name not in features else repr(found)}, "
                f"expected {'a camera (image or video)' if wanted else 'present'}; the dataset has "
                f"{sorted(features)} (convert LIBERO with `latent-steering convert`)"
            )
    depth = settings.arch.depth
    bad_layers = [layer for layer in settings.layers if not 0 <= layer < depth]
    if bad_layers:
        problems.append(
            f"layers {bad_layers} out of range: the language model has {depth} decoder layers (0..{depth - 1})"
        )
    if tokenizer.vocab_size > settings.arch.vocab_size:
        problems.append(
            f"{settings.tokenizer_path}: {tokenizer.vocab_size} pieces, more than the model's vocab_size "
            f"{settings.arch.vocab_size}; pass the tokenizer the checkpoint was trained with"
        )
    if discrete and settings.skip_norm_stats:
        problems.append(
            "the discrete_state prompt needs the quantile-normalised state: drop --skip-norm-stats, "
            "or use the libero prompt format (pi05_libero)"
        )
    if problems:
        raise ValueError("\n".join(problems))
    norm_stats = None
    if discrete:
        source = settings.norm_stats_path or settings.checkpoint_path
        stats = read_norm_stats(source, settings.norm_stats_asset_id)
        if STATE_KEY not in stats:
            raise ValueError(f"{norm_stats_path(source, settings.norm_stats_asset_id)}: no `{STATE_KEY}` entry")
        norm_stats = stats[STATE_KEY]
    return model_file, tokenizer, norm_stats


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
                "pass whole groups (see steering_core.shards.group_episodes)"
            )
    if problems:
        raise ValueError("\n".join(problems))
    return {key: members for key, members in groups.items() if wanted & set(members)}


def _run_spec(
    meta: DatasetMeta,
    repo_id: str,
    model_file: Path,
    tokenizer: PromptTokenizer,
    norm_stats: NormStats | None,
    settings: CaptureSettings,
) -> RunSpec:
    """Return the run spec: what the rows depend on (`inputs`) and where it was read from (`sources`)."""
    from steering_core.pi05.model import resolve_device, resolve_dtype  # imports transformers: only when capturing

    stats_file = None
    if norm_stats is not None:
        stats_file = norm_stats_path(settings.norm_stats_path or settings.checkpoint_path, settings.norm_stats_asset_id)
    inputs = {
        "checkpoint_fingerprint": checkpoint_fingerprint(model_file),
        "arch": settings.arch.model_dump(mode="json"),
        "compute_dtype": str(resolve_dtype(settings.dtype, resolve_device(settings.device))).removeprefix("torch."),
        "prompt_format": settings.prompt_format.value,
        "max_token_len": settings.max_token_len,
        "tokenizer_sha256": sha256_file(tokenizer.path),
        "norm_stats_sha256": sha256_file(stats_file) if stats_file else None,
    }
    sources = {  # absolute, so the record still points at its inputs when read from elsewhere
        "checkpoint": str(model_file.resolve()),
        "tokenizer": str(tokenizer.path.resolve()),
        "norm_stats": str(stats_file.resolve()) if stats_file else None,
        "dataset_root": str(meta.root.resolve()),
        "repo_id": repo_id,
        "dataset_fingerprint": dataset_fingerprint(meta.root),
    }
    return RunSpec(
        token_type=settings.token_type,
        layers=settings.layers,
        width=settings.arch.width,
        storage_dtype=settings.storage_dtype,
        episodes_per_shard=settings.episodes_per_shard,
        inputs=inputs,
        sources=sources,
    )


def _episode_records(meta: DatasetMeta, episodes: Sequence[int]) -> dict[int, dict[str, Any]]:
    """Return episode -> what its shard depends on: tasks, length, first global index, state hash.

    The state trajectory (numeric, read without decoding frames) stands in for the episode's content:
    a re-recorded demo changes it, an appended one leaves every other record unchanged.
    """
    states = read_episode_columns(meta.root, episodes, STATE_KEY) if STATE_KEY in meta.info["features"] else {}
    by_index = {e.episode_index: e for e in meta.episodes}
    records = {}
    for index in episodes:
        episode = by_index[index]
        state = states.get(index)
        records[index] = {
            "episode_index": index,
            "tasks": list(episode.tasks),
            "length": episode.length,
            "from_index": episode.from_index,
            "state_sha256": hashlib.sha256(state.tobytes()).hexdigest() if state is not None else None,
        }
    return records


class _Frames(Dataset):
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


def _batch_plan(frames: Any, groups: dict[str, tuple[int, ...]], batch_size: int) -> list[tuple[str, list[int]]]:
    """Return (shard key, dataset positions) per batch: groups in order, each from its first frame."""
    columns = frames.hf_dataset.select_columns(["episode_index", "index"]).with_format("numpy")[:]
    episode_of, index_of = columns["episode_index"], columns["index"]
    plan = []
    for key, members in groups.items():
        positions = np.flatnonzero(np.isin(episode_of, members))
        positions = positions[np.argsort(index_of[positions], kind="stable")]
        plan += [(key, positions[i : i + batch_size].tolist()) for i in range(0, len(positions), batch_size)]
    return plan


def _capture_groups(
    meta: DatasetMeta,
    repo_id: str,
    run_dir: Path,
    spec: RunSpec,
    settings: CaptureSettings,
    groups: dict[str, tuple[int, ...]],
    inputs: dict[str, str],
    tokenizer: PromptTokenizer,
    norm_stats: NormStats | None,
    total: int,
    progress: Callable[[int, int], None] | None,
) -> None:
    """Run the model over the groups' frames and write each group's shards as soon as it is complete."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset  # slow import (torchvision, datasets)

    from steering_core.pi05.model import Pi05Prefix, resolve_device

    episodes = sorted(e for members in groups.values() for e in members)
    frames = LeRobotDataset(repo_id, root=meta.root, episodes=episodes, video_backend=settings.video_backend)
    plan = _batch_plan(frames, groups, settings.batch_size)
    keys = [*LIBERO_IMAGE_KEYS, "task", "index", "episode_index", "frame_index"]
    if norm_stats is not None:
        keys.append(STATE_KEY)
    loader = DataLoader(
        _Frames(frames, keys),
        batch_sampler=[positions for _, positions in plan],
        num_workers=settings.num_workers,
        multiprocessing_context=worker_start_method(settings.num_workers),
        collate_fn=functools.partial(_collate, image_size=settings.arch.image_size),
        pin_memory=resolve_device(settings.device).type == "cuda",
    )
    # Start the workers first: they decode the first batches while the checkpoint loads, and they fork
    # before CUDA is initialised.
    batches = iter(loader)
    model = Pi05Prefix.from_checkpoint(
        settings.checkpoint_path, settings.arch, max(settings.layers), settings.device, settings.dtype
    )
    write_run_spec(run_dir, spec)  # only once the checkpoint loaded: a bad one leaves no run folder behind
    remaining = {key: sum(1 for k, _ in plan if k == key) for key in groups}
    prompts: dict[str, TokenizedPrompt] = {}
    done = 0
    buffers: dict[str, _GroupRows] = {}
    with tqdm(total=total, desc="capture", unit="frame", disable=None) as bar:
        for (key, _), batch in zip(plan, batches, strict=True):
            buffer = buffers.setdefault(key, _GroupRows(per_layer={layer: [] for layer in settings.layers}))
            _capture_batch(model, batch, settings, tokenizer, norm_stats, prompts, buffer)
            remaining[key] -= 1
            if remaining[key] == 0:
                _write_group(run_dir, spec, key, groups[key], inputs[key], buffers.pop(key))
            size = len(batch["task"])
            done += size
            bar.update(size)
            if progress is not None:
                progress(done, total)


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


def _prompt(
    tokenizer: PromptTokenizer,
    norm_stats: NormStats | None,
    task: str,
    state: torch.Tensor | None,
    cache: dict[str, TokenizedPrompt],
) -> TokenizedPrompt:
    """Return the tokenised prompt of one frame, cached per task when the state stays out of the prompt.

    Discrete-state prompts are not cached: nearly every frame has its own state bins.
    """
    if norm_stats is not None:
        return tokenizer.tokenize(task, quantile_normalize(state.numpy(), norm_stats))
    if task not in cache:
        cache[task] = tokenizer.tokenize(task)
    return cache[task]


def _capture_batch(
    model: Any,
    batch: dict[str, Any],
    settings: CaptureSettings,
    tokenizer: PromptTokenizer,
    norm_stats: NormStats | None,
    cache: dict[str, TokenizedPrompt],
    buffer: _GroupRows,
) -> None:
    """Run one batch and append its selected rows (all layers) and their columns to `buffer`."""
    tasks = list(batch["task"])
    states = batch.get(STATE_KEY)
    prompts = [_prompt(tokenizer, norm_stats, task, states[b] if states is not None else None, cache)
               for b, task in enumerate(tasks)]
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


def _write_group(
    run_dir: Path, spec: RunSpec, key: str, episodes: tuple[int, ...], inputs: str, buffer: _GroupRows
) -> None:
    """Write one shard per layer for a finished episode group."""
    columns = {name: torch.from_numpy(np.concatenate(parts)) for name, parts in buffer.columns.items()}
    for layer, parts in buffer.per_layer.items():
        rows = ShardRows(residuals=torch.cat(parts), **columns)
        write_shard(run_dir, spec, layer, key, rows, episodes=episodes, inputs=inputs, tasks=buffer.tasks)
    logger.debug("shard group %s (episodes %s): %d rows per layer", key, list(episodes), len(columns["index"]))
