"""The parent flow's first task: check every input of the run before any step starts."""

from __future__ import annotations

from prefect import task

from steering_core.preflight import check_run
from tasks.run_configs import run_config


@task(name="preflight", task_run_name="check the run's inputs")
def preflight(config_path: str, capture_device: bool) -> None:
    """Fail with one line per problem (the task's message) if an input of the run is missing or malformed."""
    check_run(run_config(config_path), capture_device=capture_device)
