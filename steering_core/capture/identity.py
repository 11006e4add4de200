"""What a capture's rows depend on: the run spec (model, tokenizer, settings) and each episode's record."""

from __future__ import annotations

import hashlib
import os
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from steering_core.capture.settings import STATE_KEY, CaptureInputs, CaptureSettings
from steering_core.capture.shards import RunSpec
from steering_core.data.dataset import (
    DatasetMeta,
    dataset_fingerprint,
    read_episode_columns,
)
from steering_core.devices import resolve_device, resolve_dtype
from steering_core.fileio import sha256_file
from steering_core.pi05.norm_stats import norm_stats_path

_FINGERPRINT_SAMPLES = 16  # data blocks hashed by checkpoint_fingerprint, evenly spaced
_FINGERPRINT_BLOCK = 1 << 16  # 64 KiB each: 1 MiB read whatever the checkpoint size


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


def run_spec(
    meta: DatasetMeta,
    repo_id: str,
    inputs: CaptureInputs,
    settings: CaptureSettings,
) -> RunSpec:
    """Return the run spec: what the rows depend on (`inputs`) and where it was read from (`sources`)."""
    model_file, tokenizer = inputs.model_file, inputs.tokenizer
    stats_file = None
    if inputs.norm_stats is not None:
        stats_file = norm_stats_path(settings.norm_stats_path or settings.checkpoint_path, settings.norm_stats_asset_id)
    depends_on = {
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
        inputs=depends_on,
        sources=sources,
    )


def episode_records(meta: DatasetMeta, episodes: Sequence[int]) -> dict[int, dict[str, Any]]:
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
