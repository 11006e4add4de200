"""What a capture's rows depend on: the run spec (model, tokenizer, settings) and each episode's record."""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from steering_core.capture.settings import STATE_KEY, CaptureInputs, CaptureSettings
from steering_core.capture.shards import RunSpec
from steering_core.data import lerobot_v2
from steering_core.data.dataset import DatasetMeta, dataset_fingerprint, read_episode_columns
from steering_core.data.parquet_reads import read_table
from steering_core.devices import resolve_device, resolve_dtype
from steering_core.pi05.robot_side import RobotSide
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import sha256_file, sha256_json


def _statistics_digest(robot: RobotSide) -> str:
    """Return the sha256 of the files the state prompt's statistics come from (one file: its own sha256)."""
    files = robot.normalization.files
    return sha256_file(files[0]) if len(files) == 1 else sha256_json([sha256_file(path) for path in files])


def checkpoint_fingerprint(model_file: str | os.PathLike) -> str:
    """Return the sha256 of a checkpoint file's whole content (a fine-tune of one weight changes it).

    Read once per file version (`steering_core.identity.file_digest`): about 20 s for 7 GB, then remembered.
    """
    return file_digest(model_file)


def run_spec(
    meta: DatasetMeta,
    repo_id: str,
    inputs: CaptureInputs,
    settings: CaptureSettings,
) -> RunSpec:
    """Return the run spec: what the rows depend on (`inputs`) and where it was read from (`sources`)."""
    model_file, tokenizer, robot = inputs.model_file, inputs.tokenizer, inputs.robot
    stats_file = robot.normalization.source if inputs.reads_state else None
    depends_on = {
        "checkpoint_fingerprint": checkpoint_fingerprint(model_file),
        "layout": inputs.checkpoint.layout.name.value,
        "arch": settings.arch.model_dump(mode="json"),
        "compute_dtype": str(resolve_dtype(settings.run_dtype, resolve_device(settings.run_device))).removeprefix("torch."),
        "prompt_format": robot.prompt_format.value,
        "max_token_len": robot.max_token_len,
        "tokenizer_sha256": sha256_file(tokenizer.path),
        "norm_stats_sha256": _statistics_digest(robot) if stats_file else None,
    }
    width = settings.arch.width
    if inputs.expert_arch is not None:  # decision / adarms: the expert's stream, from the full sampler
        width = inputs.expert_arch.width
        depends_on |= {"expert_arch": inputs.expert_arch.model_dump(mode="json"), "num_steps": settings.num_steps,
                       "noise_seed": settings.noise_seed, "action_horizon": robot.action_horizon}
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
        width=width,
        storage_dtype=settings.storage_dtype,
        episodes_per_shard=settings.episodes_per_shard,
        inputs=depends_on,
        sources=sources,
    )


def episode_records(meta: DatasetMeta, episodes: Sequence[int]) -> dict[int, dict[str, Any]]:
    """Return episode -> what its shard depends on: tasks, length, first global index, state and frame hashes.

    The frames count by their stored bytes (PNG in the data parquet, never decoded), so a re-conversion
    with another orientation or image size changes the record; an appended episode leaves the others alone.
    """
    states = read_episode_columns(meta.root, episodes, STATE_KEY) if STATE_KEY in meta.info["features"] else {}
    frames = episode_frame_digests(meta, episodes)
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
            "frames_sha256": frames[index],
        }
    return records


def episode_frame_digests(meta: DatasetMeta, episodes: Sequence[int]) -> dict[int, str]:
    """Return episode -> sha256 of its encoded camera frames, in frame order, camera by camera.

    Image features are hashed from the data parquet's stored bytes (read, never decoded). Video features
    count by the content of every video file of that camera (memoised per file): exact, but an appended
    episode then changes the hash of the episodes sharing its video file.
    """
    features = meta.info["features"]
    images = sorted(k for k, f in features.items() if f.get("dtype") == "image")
    videos = sorted(k for k, f in features.items() if f.get("dtype") == "video")
    video_files = _video_files(meta, videos)
    by_file: dict[str, list[int]] = {}
    for index in dict.fromkeys(int(e) for e in episodes):
        by_file.setdefault(meta.episode(index).data_file, []).append(index)
    digests: dict[int, str] = {}
    for rel, members in by_file.items():
        table = read_table(meta.root / rel, columns=["episode_index", "frame_index", *images],
                              filters=[("episode_index", "in", members)])
        episode_of, frame_of = table.column("episode_index").to_numpy(), table.column("frame_index").to_numpy()
        encoded = {key: table.column(key).combine_chunks() for key in images}
        for index in members:
            rows = np.flatnonzero(episode_of == index)
            rows = rows[np.argsort(frame_of[rows], kind="stable")]
            digest = hashlib.sha256(sha256_json(video_files(index)).encode())
            for key in images:
                digest.update(key.encode())
                for value in encoded[key].take(rows).to_pylist():
                    data = _image_bytes(meta, value)
                    digest.update(len(data).to_bytes(8, "little"))
                    digest.update(data)
            digests[index] = digest.hexdigest()
    return digests


def _video_files(meta: DatasetMeta, keys: Sequence[str]) -> Callable[[int], dict[str, str]]:
    """Return episode -> {video file: sha256} of its cameras: its own files (v2.x), or every file of the camera (v3.0)."""
    if not keys:
        return lambda index: {}
    if meta.info["codebase_version"] in lerobot_v2.V2_VERSIONS:  # one video per episode and camera
        return lambda index: {rel: file_digest(meta.root / rel)
                              for rel in (lerobot_v2.episode_video_file(meta.info, index, key) for key in keys)}
    shared = {p.relative_to(meta.root).as_posix(): file_digest(p)
              for key in keys for p in sorted((meta.root / "videos" / key).rglob("*")) if p.is_file()}
    return lambda index: shared


def _image_bytes(meta: DatasetMeta, value: Any) -> bytes:
    """Return the encoded bytes of one image cell (`{bytes, path}`; the bytes, or the file the path names)."""
    if isinstance(value, dict):
        if value.get("bytes") is not None:
            return value["bytes"]
        if value.get("path"):
            return (meta.root / value["path"]).read_bytes()
    raise ValueError(f"{meta.root}: an image cell holds {type(value).__name__}, expected encoded bytes or a path")
