"""A run config's rollouts from this process (the `rollout` command; the flow runs the same jobs as cached Prefect
tasks): its chunks on `rollout.workers` simulation workers, or one after another here when one is enough."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from steering_core.reporting.progress import Progress
from steering_core.rollout import records
from steering_core.rollout.plan import by_cell, config_jobs, write_layer_report
from steering_core.rollout.run import RolloutJob, run_chunk
from steering_core.rollout.workers import run_jobs, simulation

if TYPE_CHECKING:
    from steering_core.capture import CaptureSettings
    from steering_core.config import RunConfig
    from steering_core.rollout.settings import RolloutSettings


def rollout_config(config: RunConfig, targets: list[tuple[str, int]] | None = None,
                   api_key: str | None = None) -> dict[int, Path]:
    """Roll out `targets` (default every (pair, layer) of the config); return layer -> its summary.md. Each cell
    is merged as soon as its chunks are done."""
    settings, model = config.rollout.settings(), config.capture_settings()
    targets = targets or config.rollout_targets()
    jobs = [job for name, layer in targets for job in config_jobs(config, name, layer)]
    cells = by_cell(jobs)
    chunks: dict[Path, dict[int, Path]] = {cell_dir: {} for cell_dir in cells}

    with Progress(sum(len(job.init_states) for job in jobs), "rollouts", "episode") as bar:
        def done(job: RolloutJob, folder: Path) -> None:
            chunks[job.output_dir][job.chunk] = folder
            bar.update(len(job.init_states))
            if len(chunks[job.output_dir]) == len(cells[job.output_dir]):
                records.merge_chunks(job.output_dir, [chunks[job.output_dir][j.chunk] for j in cells[job.output_dir]])

        with simulation(settings, model, config.steering_root, api_key, len(jobs)) as (workers, run_settings, key):
            if workers is None:
                for job in jobs:
                    done(job, run_chunk(job, model, settings, api_key=api_key))
            else:
                run_jobs(workers, chunk_in_worker, jobs, model, run_settings, key, on_done=done)
    summaries = {}
    for layer in sorted({layer for _, layer in targets}):  # every pair rolled out so far at this layer
        summaries[layer] = write_layer_report(config, layer)
    return summaries


def chunk_in_worker(job: RolloutJob, model: CaptureSettings, settings: RolloutSettings, api_key: str | None) -> Path:
    """`run_chunk` as a simulation worker runs it (no progress callback crosses the process)."""
    return run_chunk(job, model, settings, api_key=api_key)
