"""A run config's rollouts in this process, one chunk after another (the `rollout` command; the flow runs the
same jobs as cached Prefect tasks)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from steering_core.reporting.progress import Progress
from steering_core.rollout import records
from steering_core.rollout.plan import by_cell, config_jobs, write_layer_report
from steering_core.rollout.run import run_chunk

if TYPE_CHECKING:
    from steering_core.config import RunConfig


def rollout_config(config: RunConfig, targets: list[tuple[str, int]] | None = None,
                   api_key: str | None = None) -> dict[int, Path]:
    """Roll out `targets` (default every (pair, layer) of the config); return layer -> its summary.md."""
    settings, model = config.rollout.settings(), config.capture_settings()
    targets = targets or config.rollout_targets()
    jobs = [job for name, layer in targets for job in config_jobs(config, name, layer)]
    with Progress(sum(len(job.init_states) for job in jobs), "rollouts", "episode") as bar:
        for cell_dir, cell_jobs in by_cell(jobs).items():
            chunks = []
            for job in cell_jobs:
                chunks.append(run_chunk(job, model, settings, api_key=api_key))
                bar.update(len(job.init_states))
            records.merge_chunks(cell_dir, chunks)
    summaries = {}
    for layer in sorted({layer for _, layer in targets}):  # every pair rolled out so far at this layer
        summaries[layer] = write_layer_report(config, layer)
    return summaries
