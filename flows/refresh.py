"""The scheduled flow `latent-steering-refresh`: re-run the pipeline only when the demo sources changed.

It compares the sha256 of every demo file (a run on an existing LeRobot dataset: the dataset's
content fingerprint) and the run config's fingerprint with the record the pipeline wrote after its
last successful run. Nothing changed: it ends at once, saying so.
Something changed: it runs the pipeline, which is incremental (new episodes are appended and
captured, cached steps whose inputs did not change are reused). As a deployment it starts the
pipeline deployment, whose concurrency limit of 1 keeps it from overlapping a manual run; its
own deployment limit keeps two refreshes from running at once.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, runtime
from prefect.deployments import run_deployment

from flows.pipeline import latent_steering
from steering_core.refresh import SOURCES_RECORD_FILE, diff_sources, read_sources_record, scan_inputs
from steering_core.remote.publish import pulled
from steering_core.storage.mirrors import is_url
from tasks.run_configs import run_config

REFRESH_FLOW = "latent-steering-refresh"


@flow(name=REFRESH_FLOW)
def refresh(config_path: str, rehash: bool = False) -> dict[str, Any]:
    """Run the pipeline if demo files (or the existing dataset, or the config) changed since its last success."""
    logger = get_run_logger()
    config_path = config_path if is_url(config_path) else str(Path(config_path).resolve())
    config = run_config(config_path)
    previous = read_sources_record(pulled(config.output_root / SOURCES_RECORD_FILE))
    current = scan_inputs(config, previous=previous, rehash=rehash)
    changes = diff_sources(previous, current, config_fingerprint=config.fingerprint())
    if not changes:
        checked = f"dataset {current.dataset_root}" if current.dataset_root else f"{len(current.files)} files"
        logger.info("nothing changed since the last successful run (%s checked): %s; nothing to do",
                    checked, changes.describe())
        return {"ran": False, "changes": changes.describe()}
    logger.info("since the last successful run: %s", changes.describe())
    if runtime.deployment.id:
        run = run_deployment(config.orchestration.pipeline_deployment, parameters={"config_path": config_path},
                             poll_interval=config.orchestration.poll_seconds)
        if run.state is None or not run.state.is_completed():
            raise RuntimeError(f"pipeline run {run.name} ended {run.state.name if run.state else 'without a state'}; "
                               "see it in the Prefect UI")
    else:
        latent_steering(config_path)
    return {"ran": True, "changes": changes.describe()}
