"""Phase 2 tasks: capture residuals for a group of episodes (GPU), write run metadata, slice by concept."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import get_run_logger, task

from steering_core.capture import CaptureSettings, shards, slicing
from steering_core.capture import loop as capture
from steering_core.capture.run_identity import checkpoint_fingerprint, episode_records
from steering_core.capture.slicing import SliceSettings
from steering_core.data.concept_map import read_concept_map
from steering_core.data.convert import SOURCES_FILE, read_sources
from steering_core.data.dataset import INFO_FILE, read_meta
from steering_core.identity import plain
from steering_core.layout import layer_dir
from steering_core.pi05.checkpoint import resolve_model_file
from steering_core.pi05.tokenizer import PromptFormat
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import read_json
from tasks.artifacts import ProgressArtifact, artifact_key
from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS
from tasks.results import RESULTS
from tasks.retries import (
    GPU_RETRIES,
    GPU_RETRY_DELAYS,
    IO_RETRIES,
    IO_RETRY_DELAYS,
    retry_if,
    transient_gpu,
    transient_io,
)

GPU_TAG = "gpu"  # a tag concurrency limit of this name caps running GPU tasks (latent-steering deploy)
_READING_ONLY = ("num_workers", "video_backend")  # how frames are read, never what the rows hold


# ----------------------------------------------------------------------------- input fingerprints

def model_inputs(settings: CaptureSettings) -> dict[str, Any]:
    """Return the capture settings that shape the rows, plus the content of the files they name (the statistics
    only where the prompt reads the state: openpi's norm_stats.json, lerobot's config and processor files)."""
    robot = settings.model.robot_side()
    reads_state = robot.prompt_format is PromptFormat.DISCRETE_STATE
    return {
        "settings": plain(settings.model_dump(mode="json", exclude=set(_READING_ONLY))),
        "checkpoint": checkpoint_fingerprint(resolve_model_file(settings.model.checkpoint)),
        "tokenizer": file_digest(settings.model.require_tokenizer()),
        "norm_stats": [file_digest(path) for path in robot.normalization.files] if reads_state else None,
    }


def episode_sources(inputs: dict[str, Any]) -> Any:
    """Return where the requested episodes came from (file, demo, sha256, length) and how they were converted.

    A dataset not converted by us (no `meta/libero_sources.json`, e.g. openpi's, read in place) is
    identified by its info.json and each requested episode's tasks, length, first index and state hash.
    """
    root = Path(inputs["dataset_root"])
    if not (root / SOURCES_FILE).is_file():
        meta = read_meta(root)
        return {"info": file_digest(root / INFO_FILE),
                "episodes": list(episode_records(meta, sorted(set(inputs["episodes"]))).values())}
    record = read_sources(root)
    wanted = set(inputs["episodes"])
    return {
        "conversion": plain(record.model_copy(update={"episodes": ()})),
        "episodes": [plain(e) for e in record.episodes if e.episode_index in wanted],
    }


def run_sidecars(inputs: dict[str, Any]) -> Any:
    """Return the digests of run.json and every shard sidecar of the run: what metadata.json is built from."""
    run_dir = Path(inputs["run_dir"])
    return {str(p.relative_to(run_dir)): file_digest(p)
            for p in sorted(run_dir.glob(f"**/{shards.SIDECAR_FILE.format(key='*')}")) + [run_dir / shards.RUN_FILE]}


def concept_rows(path: str) -> Any:
    """Return the segments of a concept map (what slicing reads), not its dataset-wide counts."""
    return {name: [plain(row) for row in rows] for name, rows in read_concept_map(path).concepts.items()}


def sliced_shards(inputs: dict[str, Any]) -> Any:
    """Return the run identity and the (file, sha256) of the shards holding the concept map's episodes."""
    metadata = shards.read_run_metadata(inputs["run_dir"])
    episodes = {row.episode_index for rows in read_concept_map(inputs["concept_map_path"]).concepts.values()
                for row in rows}
    return {
        "run": metadata.run.identity(),
        "shards": [(r.file, r.sha256) for layer in inputs["settings"].layers for r in metadata.layer_shards(layer)
                   if episodes & set(r.episodes)],
    }


def shard_files(run_dir: str, settings: CaptureSettings, episodes: list[int]) -> list[str]:
    """Return the shard files and their sidecars (every layer) that hold `episodes`: each shard before its sidecar,
    which is published after it, as it is written after it."""
    keys = shards.group_episodes(episodes, settings.episodes_per_shard)
    return [str(where(run_dir, settings.token_type, layer, key)) for layer in settings.layers for key in keys
            for where in (shards.shard_path, shards.sidecar_path)]


# ----------------------------------------------------------------------------- tasks

@task(
    name="capture-residuals",
    task_run_name="capture {label}",
    tags=[GPU_TAG],
    cache_policy=content_key("steering_core.capture.loop", settings=model_inputs,
                             derived={"episodes": episode_sources}, ignore=("label",)),
    retries=GPU_RETRIES, retry_delay_seconds=GPU_RETRY_DELAYS, retry_condition_fn=retry_if(transient_gpu),
    **RESULTS,
)
def capture_episodes(
    label: str, dataset_root: str, repo_id: str, run_dir: str, settings: CaptureSettings, episodes: list[int]
) -> dict:
    """Capture the residuals of `episodes` (whole shard groups) into the run; return what was written."""
    progress = ProgressArtifact(artifact_key("capture", Path(run_dir).name, label), "frames",
                                 f"capture {label} into {run_dir}")
    result = capture.capture(dataset_root, repo_id, run_dir, settings, episodes=episodes, progress=progress)
    progress.finish()
    get_run_logger().info("%s: %d shard group(s) written, %d already complete, %d frames",
                          label, len(result.written), len(result.skipped), result.frames)
    if result.reduced_batch_size is not None:
        get_run_logger().warning("%s: CUDA ran out of memory; captured %d frame(s) per pass instead of %d",
                                 label, result.reduced_batch_size, settings.batch_size)
    files = [*shard_files(run_dir, settings, episodes), str(Path(run_dir) / shards.RUN_FILE)]
    return {OUTPUTS: files, "written": list(result.written),
            "skipped": list(result.skipped), "frames": result.frames, "reduced_batch_size": result.reduced_batch_size}


@task(
    name="write-run-metadata",
    task_run_name="run metadata {run_dir}",
    cache_policy=content_key("steering_core.capture.shards", derived={"sidecars": run_sidecars}),
    retries=IO_RETRIES, retry_delay_seconds=IO_RETRY_DELAYS, retry_condition_fn=retry_if(transient_io),
    **RESULTS,
)
def write_run_metadata(run_dir: str) -> dict:
    """Rebuild the run's metadata.json from its sidecars; return episode and shard counts."""
    path = shards.write_run_metadata(run_dir)
    metadata = shards.read_run_metadata(run_dir)
    return {OUTPUTS: [str(path)], "episodes": len(metadata.episodes), "shards": len(metadata.shards)}


@task(
    name="slice-concepts",
    task_run_name="slice {pair} layer {layer}",
    cache_policy=content_key("steering_core.capture.slicing", concept_map_path=concept_rows,
                             derived={"shards": sliced_shards}),
    retries=IO_RETRIES, retry_delay_seconds=IO_RETRY_DELAYS, retry_condition_fn=retry_if(transient_io),
    **RESULTS,
)
def slice_layer(pair: str, layer: int, run_dir: str, concept_map_path: str, output_dir: str, settings: SliceSettings) -> dict:
    """Write one pair's per-concept residual tensors for one layer; return concept -> .pt path."""
    stream = [settings.token_type] if settings.token_type in shards.ACTION_TOKEN_TYPES else []  # decision slices
    progress = ProgressArtifact(artifact_key("slice", pair, *stream, layer_dir(layer)), "shards",
                                 f"slice {pair} {layer_dir(layer)} into {output_dir}")
    index_path = slicing.slice_concepts(run_dir, concept_map_path, output_dir, settings, progress=progress)[layer]
    progress.finish()
    folder = Path(output_dir) / layer_dir(layer)
    concepts = {name: str(folder / entry["pt"]) for name, entry in read_json(index_path)["concepts"].items()}
    return {OUTPUTS: [str(index_path), *concepts.values()], "concepts": concepts, "index": str(index_path),
            "folder": str(folder)}
