"""Phase 5 tasks: one chunk of a rollout cell in the LIBERO simulator, a cell's merged record, and the per-layer
summary. Chunks are cached on everything that changes their episodes: the code, the cell (its side, α, and the
method and mode it steers with), the steering vectors read (the pair's and, for the wrong-concept control, the
other pair's), the model and the settings."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import get_run_logger, task

from steering_core import layout
from steering_core.capture import CaptureSettings
from steering_core.identity import plain
from steering_core.rollout import records, report
from steering_core.rollout.local_run import chunk_in_worker
from steering_core.rollout.run import RolloutJob, run_chunk
from steering_core.rollout.settings import RolloutSettings
from steering_core.rollout.workers import CHUNK_RETRIES, SimulationWorkers, WorkerDied
from steering_core.storage.digests import file_digest
from tasks.artifacts import ProgressArtifact, artifact_key
from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS
from tasks.capture import model_inputs
from tasks.evaluate import folder_digests
from tasks.results import RESULTS
from tasks.retries import retry_if

# The modules a chunk runs (and, transitively, what they import: episodes, LIBERO, predicates, records, the
# policy clients, the π0.5 policy the evaluation loads)
CHUNK_CODE = "steering_core.rollout.run"
# Connection errors reach a policy server that is restarting, and a simulation worker may die (a MuJoCo crash):
# a second attempt can succeed. Nothing else retries.
SIM_RETRIES, SIM_RETRY_DELAYS = CHUNK_RETRIES, [10, 60]


def job_inputs(job: RolloutJob) -> dict[str, Any]:
    """Return the job and the content of the steering vectors it reads (none when unsteered)."""
    pair = job.cell.steering_pair
    vectors = folder_digests(job.vectors_root / layout.layer_dir(job.cell.layer) / pair) if pair else None
    return {"job": plain(job.model_dump(mode="json", exclude={"vectors_root", "output_dir"})), "vectors": vectors}


def settings_inputs(settings: RolloutSettings) -> dict[str, Any]:
    """Return the settings that change an episode (not how the policy is reached, where assets are read, how
    episodes are placed on task runs and envs, nor `methods` and `modes`: they only choose the grid's cells, and a
    cell names its own method and mode, so adding one leaves the other cells' chunks cached)."""
    return plain(settings.model_dump(mode="json", exclude={"policy", "api_key_file", "libero_assets", "device",
                                                           "compiled", "note", "chunk_episodes", "envs_per_worker",
                                                           "workers", "methods", "modes"}))


def transient(exc: BaseException) -> bool:
    """Return True for an error a policy server's restart or a lost simulation worker explains."""
    return isinstance(exc, ConnectionError | TimeoutError | WorkerDied)


@task(
    name="rollout-chunk",
    task_run_name="rollout {job.cell.pair} layer {job.cell.layer} {job.output_dir.name} chunk {job.chunk}",
    cache_policy=content_key(CHUNK_CODE, job=job_inputs, model=model_inputs, settings=settings_inputs,
                             ignore=("api_key", "workers")),
    retries=SIM_RETRIES, retry_delay_seconds=SIM_RETRY_DELAYS, retry_condition_fn=retry_if(transient),
    **RESULTS,
)
def rollout_chunk(job: RolloutJob, model: CaptureSettings, settings: RolloutSettings, api_key: str | None,
                  workers: SimulationWorkers | None = None) -> dict:
    """Run one chunk of a cell in the simulator, here or on one of `workers`; return its record files."""
    progress = ProgressArtifact(artifact_key("rollout", job.cell.pair, job.cell.layer, job.output_dir.name, job.chunk),
                                "episodes", f"rollout {job.cell.pair} layer {job.cell.layer} {job.output_dir.name}")
    if workers is None:
        folder = run_chunk(job, model, settings, api_key=api_key, progress=progress)
    else:
        folder = workers.run(chunk_in_worker, job, model, settings, api_key)
        progress(len(job.init_states), len(job.init_states))
    progress.finish()
    return {OUTPUTS: record_files(folder), "chunk": str(folder)}


def record_files(folder: Path) -> list[str]:
    """Return a cell record's two files (records.write_cell)."""
    return [str(folder / f"{layout.ROLLOUT_FILE}.{suffix}") for suffix in ("json", "safetensors")]


def chunk_contents(inputs: dict[str, Any]) -> list[list[str]]:
    return [[file_digest(path) for path in record_files(Path(chunk))] for chunk in inputs["chunks"]]


@task(
    name="rollout-cell",
    task_run_name="merge rollout {label}",
    cache_policy=content_key("steering_core.rollout.records", derived={"chunks": chunk_contents}),
    **RESULTS,
)
def rollout_cell(cell_dir: str, chunks: list[str], label: str) -> dict:
    """Merge a cell's chunks into rollouts.json/.safetensors (and its first episode's MP4); `label` names the run."""
    records.merge_chunks(Path(cell_dir), [Path(p) for p in chunks])
    files = record_files(Path(cell_dir))
    return {OUTPUTS: files, "rollouts": files[0]}


def cell_records(inputs: dict[str, Any]) -> dict[str, Any]:
    """Return the digest of every current cell's rollouts.json (None: not done yet)."""
    return {name: [file_digest(p) if p.is_file() else None for p in (Path(c) / f"{layout.ROLLOUT_FILE}.json"
                                                                       for c in cells)]
            for name, cells in inputs["cells"].items()}


@task(
    name="rollout-summary",
    task_run_name="rollout summary layer {layer}",
    cache_policy=content_key("steering_core.rollout.report", derived={"cells": cell_records}),
    **RESULTS,
)
def rollout_summary(layer: int, layer_path: str, cells: dict[str, list[str]], note: str | None) -> dict:
    """Write each done pair's table and plots and the layer's summary.md / summary.json."""
    md_path = report.write_layer(Path(layer_path), {name: [Path(c) for c in folders] for name, folders in cells.items()},
                                 note=note)
    get_run_logger().info("rollout summary: %s", md_path)
    return {OUTPUTS: [str(md_path), str(md_path.with_name(layout.SUMMARY_JSON))], "summary": str(md_path)}
