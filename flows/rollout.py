"""The rollout flow `latent-steering-rollout`: closed-loop LIBERO episodes of (pair, layer, side)s, on the `sim` pool.

With a server, the parent flow starts one deployment run per (pair, layer, side), so several CPU simulation
workers share the grid (each reaching the policy in-process or through a `latent-steering serve` on a GPU
machine: `rollout.policy`); without one, it calls this flow in-process. Every chunk of a cell is a cached task:
a re-run after a crash resumes at the first chunk not yet written.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow
from prefect.artifacts import create_markdown_artifact

from flows.children import run_phase
from steering_core.config import RunConfig
from steering_core.layout import SUMMARY_JSON, SUMMARY_MD, layer_dir
from steering_core.remote.publish import pulled
from steering_core.rollout.plan import by_cell, config_jobs, layer_cells
from steering_core.serve.auth import read_api_key
from steering_core.storage.fileio import read_json
from tasks import rollout as rollout_tasks
from tasks.artifacts import artifact_key, ui_markdown
from tasks.results import TaskSet
from tasks.run_configs import run_config

ROLLOUT_FLOW = "latent-steering-rollout"


def rollout_targets(config: RunConfig) -> list[tuple[str, int, str]]:
    """Return every (pair, layer, side) the run rolls out."""
    return [(name, layer, side) for name, layer in config.rollout_targets() for side in config.rollout.sides]


@flow(name=ROLLOUT_FLOW)
def rollout_flow(config_path: str, targets: list[tuple[str, int, str]] | None = None) -> dict:
    """Roll out `targets` (default every (pair, layer, side)), one task per chunk, then merge each cell."""
    config = run_config(config_path)
    pulled(config.output_root)  # on a bucket root: what the jobs are planned from (directions, splits, dataset)
    settings, model = config.rollout.settings(), config.capture_settings()
    api_key = read_api_key(settings.api_key_file)
    tasks = TaskSet(config.output_root, rollout_tasks)
    cells = []
    for name, layer, side in targets or rollout_targets(config):  # one after another: one simulator per worker
        for cell_dir, jobs in by_cell(config_jobs(config, name, layer, (side,))).items():
            chunks = [tasks.rollout_chunk(job, model, settings, api_key)["chunk"] for job in jobs]
            label = f"{name} layer {layer} {cell_dir.name}"
            cells.append(tasks.rollout_cell(str(cell_dir), chunks, label)["rollouts"])
    return {"cells": cells}


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
