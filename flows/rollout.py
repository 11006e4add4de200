"""The rollout flow `latent-steering-rollout`: closed-loop LIBERO episodes of (pair, layer, side)s, on the `sim` pool.

With a server, the parent flow starts one deployment run per (pair, layer, side), so several machines of the pool
share the grid; without one, it calls this flow in-process. Either way a flow run spreads its chunks over
`rollout.workers` simulation processes on its machine (Prefect's thread task runner feeds them, one thread per
worker), all reaching one policy: the one loaded once and served from this process (`rollout.policy: local`) or a
`latent-steering serve` on a GPU machine. Every chunk of a cell is a cached task: a re-run after a crash runs only
the chunks not yet written.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow
from prefect.artifacts import create_markdown_artifact
from prefect.futures import as_completed
from prefect.task_runners import ThreadPoolTaskRunner

from flows.children import run_phase
from steering_core.config import RunConfig
from steering_core.layout import SUMMARY_JSON, SUMMARY_MD, layer_dir
from steering_core.remote.publish import pulled
from steering_core.reporting.progress import Progress
from steering_core.rollout.plan import by_cell, config_jobs, layer_cells
from steering_core.rollout.run import RolloutJob
from steering_core.rollout.workers import simulation, stop_on_interrupt
from steering_core.serve.auth import read_api_key
from steering_core.storage.fileio import read_json
from tasks import rollout as rollout_tasks
from tasks.artifacts import ProgressArtifact, artifact_key, ui_markdown
from tasks.results import TaskSet, is_cached
from tasks.run_configs import run_config

ROLLOUT_FLOW = "latent-steering-rollout"


def rollout_targets(config: RunConfig) -> list[tuple[str, int, str]]:
    """Return every (pair, layer, side) the run rolls out."""
    return [(name, layer, side) for name, layer in config.rollout_targets() for side in config.rollout.sides]


@flow(name=ROLLOUT_FLOW)
def rollout_flow(config_path: str, targets: list[tuple[str, int, str]] | None = None) -> dict:
    """Roll out `targets` (default every (pair, layer, side)), one task per chunk on `rollout.workers` simulation
    workers (one policy shared by them), then merge each cell."""
    config = run_config(config_path)
    pulled(config.output_root)  # on a bucket root: what the jobs are planned from (directions, splits, dataset)
    settings, model = config.rollout.settings(), config.capture_settings()
    api_key = read_api_key(settings.api_key_file)
    tasks = TaskSet(config.output_root, rollout_tasks)
    jobs = [job for name, layer, side in targets or rollout_targets(config)
            for job in config_jobs(config, name, layer, (side,))]
    todo = [job for job in jobs if not is_cached(rollout_tasks.rollout_chunk, config.output_root, job, model,
                                                 settings, api_key)]
    chunks: dict[tuple[Path, int], str] = {}
    with simulation(settings, model, config.steering_root, api_key, len(todo)) as (workers, run_settings, key), \
            ThreadPoolTaskRunner(max_workers=workers.count if workers else 1) as runner, \
            stop_on_interrupt(workers), flow_progress(config.name, todo) as progress:
        futures = {runner.submit(tasks.rollout_chunk, {"job": job, "model": model, "settings": run_settings,
                                                       "api_key": key, "workers": workers}): job for job in jobs}
        for future in as_completed(futures):
            job = futures[future]
            chunks[job.output_dir, job.chunk] = future.result()["chunk"]
            if job in todo:
                progress.update(len(job.init_states))
    cells = []
    for cell_dir, cell_jobs in by_cell(jobs).items():
        label = f"{cell_jobs[0].cell.pair} layer {cell_jobs[0].cell.layer} {cell_dir.name}"
        cells.append(tasks.rollout_cell(str(cell_dir), [chunks[cell_dir, job.chunk] for job in cell_jobs],
                                        label)["rollouts"])
    return {"cells": cells}


def flow_progress(run_name: str, todo: list[RolloutJob]) -> Progress:
    """Return the phase's progress over the episodes of the chunks not cached: in the terminal or log, and as a
    Prefect progress artifact with the rate and the time left."""
    artifact = ProgressArtifact(artifact_key(run_name, "rollout-progress"), "episodes", f"rollout {run_name}")
    bar = Progress(sum(len(job.init_states) for job in todo), "rollouts", "episode",
                   callback=lambda done, total: artifact(done, total, bar.describe()))
    return bar


def ui_rollouts(layer_path: Path) -> str:
    """Return a layer's rollout summary for the Prefect UI: its plots inline, then where the files and videos are."""
    summary = read_json(pulled(layer_path / SUMMARY_JSON))
    plots = [f"{pair['pair']}/{file}" for pair in summary["pairs"] for file in pair["plots"].values()]
    videos = [f"{pair['pair']}/{file}" for pair in summary["pairs"] for file in pair["videos"].values()]
    return ui_markdown(layer_path, plots, [SUMMARY_MD, SUMMARY_JSON, *videos])


def run_rollouts(config: RunConfig, config_path: str | Path) -> dict[str, str]:
    """Roll out every (pair, layer, side) on the `sim` pool or in-process, then write and publish each layer's
    summary; return layer folder name -> its summary.md."""
    pulled(config.output_root)  # on a bucket root: outputs of steps cached here but computed on other machines
    targets = rollout_targets(config)
    run_phase(config, config_path, "rollout", deployment=config.orchestration.rollout_deployment,
              phase_flow=rollout_flow, targets=targets,
              name_of=lambda target: f"rollout {target[0]} {layer_dir(target[1])} {target[2]}")
    tasks = TaskSet(config.output_root, rollout_tasks)
    summaries = {}
    for layer in sorted({layer for _, layer, _ in targets}):
        layer_path = config.rollout_layer_path(layer)
        cells = {name: [str(c) for c in folders] for name, folders in layer_cells(config, layer).items()}
        result = tasks.rollout_summary(layer, str(layer_path), cells, config.rollout.note)
        summaries[layer_dir(layer)] = result["summary"]
        create_markdown_artifact(ui_rollouts(layer_path), key=artifact_key(config.name, "rollouts", layer_dir(layer)),
                                 description=f"Closed-loop rollouts, {layer_dir(layer)} ({layer_path})")
    return summaries
