"""Phase 1 tasks: filter demo files, convert them to LeRobot, build contrast manifests and concept maps."""

from __future__ import annotations

from pathlib import Path

from prefect import get_run_logger, task

from steering_core.data import concept_map, contrast, convert, filtering, split
from steering_core.data.contrast import ContrastSettings
from steering_core.data.convert import ConvertSettings
from steering_core.data.dataset import dataset_fingerprint
from steering_core.data.filtering import FilterSettings
from steering_core.identity import tree_listing
from steering_core.layout import SELECTION_FILE
from steering_core.storage.digests import file_digest
from tasks.artifacts import ProgressArtifact, artifact_key
from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS
from tasks.results import RESULTS
from tasks.retries import IO_RETRIES, IO_RETRY_DELAYS, retry_if, transient_io


def selection_digest(folder: str) -> str:
    """Return the sha256 of a filtered folder's selection.json (which holds every selected file's sha256)."""
    return file_digest(Path(folder) / SELECTION_FILE)


@task(
    name="filter-demos",
    task_run_name="filter demos into {output_dir}",
    cache_policy=content_key("steering_core.data.filtering", sources=tree_listing),
    retries=IO_RETRIES, retry_delay_seconds=IO_RETRY_DELAYS, retry_condition_fn=retry_if(transient_io),
    **RESULTS,
)
def filter_demos(sources: list[str], output_dir: str, settings: FilterSettings) -> dict:
    """Select demo files into `output_dir` (links + selection.json); return the selected file names."""
    selection = filtering.filter_demos(sources, output_dir, settings)
    get_run_logger().info("%d file(s) selected into %s", len(selection.files), output_dir)
    # on a bucket root the folder is published whole, its links as copies of the files they name
    return {OUTPUTS: [str(Path(output_dir) / SELECTION_FILE)], "files": [f.name for f in selection.files],
            "folder": output_dir}


@task(
    name="convert-dataset",
    task_run_name="convert to LeRobot {settings.repo_id}",
    cache_policy=content_key("steering_core.data.convert", filtered_dir=selection_digest),
    retries=IO_RETRIES, retry_delay_seconds=IO_RETRY_DELAYS, retry_condition_fn=retry_if(transient_io),
    **RESULTS,
)
def convert_dataset(filtered_dir: str, dataset_root: str, settings: ConvertSettings) -> dict:
    """Convert (or append new episodes to) the LeRobot dataset; return what was done."""
    progress = ProgressArtifact(artifact_key("convert", settings.repo_id), "episodes",
                                 f"convert {filtered_dir} into {dataset_root}")
    result = convert.convert_libero([filtered_dir], dataset_root, settings, progress=progress)
    progress.finish()
    get_run_logger().info("%s: %s, %d episode(s) added, %d in total",
                          dataset_root, result.action, result.episodes_added, result.episodes_total)
    return {OUTPUTS: [dataset_root], "action": result.action, "episodes_added": result.episodes_added,
            "episodes_total": result.episodes_total, "frames_total": result.frames_total}


@task(
    name="build-manifest",
    task_run_name="manifest {pair}",
    cache_policy=content_key("steering_core.data.contrast", dataset_root=dataset_fingerprint),
    **RESULTS,
)
def build_manifest(
    pair: str, dataset_root: str, task_a: str, task_b: str, settings: ContrastSettings, repo_id: str, output: str
) -> dict:
    """Write the contrast manifest of two tasks of the dataset; return its axis and segment count."""
    manifest = contrast.build_manifest(dataset_root, task_a, task_b, settings, repo_id=repo_id)
    contrast.write_manifest(manifest, output)
    return {OUTPUTS: [output], "tasks": list(manifest.axis.mean_delta_per_task),  # (A, B) as the dataset spells them
            "axis": manifest.axis.index, "effect_size": manifest.axis.effect_size, "segments": len(manifest.segments)}


@task(
    name="map-concepts",
    task_run_name="concept map {pair}",
    cache_policy=content_key("steering_core.data.concept_map", manifest_path=file_digest, dataset_root=dataset_fingerprint),
    **RESULTS,
)
def map_concepts(
    pair: str, manifest_path: str, dataset_root: str, repo_id: str, rename: dict[str, str], output: str
) -> dict:
    """Write the concept map of a manifest on the dataset; return the sample count per concept."""
    result = concept_map.build_concept_map(manifest_path, dataset_root, repo_id=repo_id, rename=rename)
    concept_map.write_concept_map(result, output)
    return {OUTPUTS: [output], "concepts": {name: sum(r.length for r in rows) for name, rows in result.concepts.items()}}


@task(
    name="split-episodes",
    task_run_name="held-out split {pair}",
    cache_policy=content_key("steering_core.data.split", manifest_path=file_digest),
    **RESULTS,
)
def split_episodes(pair: str, manifest_path: str, holdout_fraction: float, output: str) -> dict:
    """Write the held-out split of a manifest's episodes; return the held-out episode indices."""
    result = split.split_episodes(contrast.read_manifest(manifest_path), holdout_fraction, where=manifest_path)
    split.write_split(result, output)
    return {OUTPUTS: [output], "holdout_episodes": list(result.holdout_episodes)}
