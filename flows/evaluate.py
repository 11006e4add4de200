"""The evaluation flow `latent-steering-evaluate`: steering dose-responses of (pair, layer)s, on the `gpu` pool.

With a server, the parent flow starts one deployment run per (pair, layer), so several GPU workers
share the work; without one, it calls this flow in-process and the pairs run one after another on
the local device (one policy load for all). Every pair is a cached task: unchanged vectors, frames
and settings give `Cached`, a refreshed vector re-evaluates only its pair.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact
from prefect.deployments import run_deployment

from flows.capture import capture_mode, wait_for_runs
from steering_core.config import RunConfig, load_run_config
from steering_core.evaluate.run import run_config_job
from steering_core.layout import layer_dir
from tasks import evaluate as evaluate_tasks
from tasks.artifacts import artifact_key
from tasks.cache import rooted

EVALUATE_FLOW = "latent-steering-evaluate"


def evaluation_targets(config: RunConfig) -> list[tuple[str, int]]:
    """Return every (pair, layer) of the run, layer by layer."""
    return [(pair.name, layer) for layer in config.layers for pair in config.pairs]


@flow(name=EVALUATE_FLOW)
def evaluate_flow(config_path: str, targets: list[tuple[str, int]] | None = None) -> dict:
    """Evaluate the steering vectors of `targets` (default every pair and layer), one task each."""
    config = load_run_config(config_path)
    settings = config.evaluate_settings()
    task = rooted(evaluate_tasks.evaluate_pair, config.output_root)
    done = []
    for name, layer in targets or evaluation_targets(config):  # one after another: they share this device
        job = run_config_job(config, name, layer)
        done.append(task(job, config.capture_settings(), config.steering_settings(layer), settings)["folder"])
    return {"folders": done}


def run_evaluation(config: RunConfig, config_path: str | Path) -> dict[int, str]:
    """Evaluate every (pair, layer) on the `gpu` pool or in-process, then write and publish each layer's summary.

    Returns layer -> its summary.md.
    """
    logger = get_run_logger()
    targets = evaluation_targets(config)
    if capture_mode(config) == "deployment":
        started = [run_deployment(config.orchestration.evaluate_deployment,
                                  parameters={"config_path": str(config_path), "targets": [[name, layer]]},
                                  flow_run_name=f"evaluate {name} {layer_dir(layer)}", timeout=0)
                   for name, layer in targets]
        logger.info("started %d evaluation run(s); waiting", len(started))
        failed = [run.name for run in wait_for_runs(started, config.orchestration.poll_seconds)
                  if run.state is None or not run.state.is_completed()]
        if failed:
            raise RuntimeError(f"evaluation run(s) did not complete: {', '.join(failed)}; see them in the Prefect UI")
    else:
        evaluate_flow(str(config_path), targets)
    summaries = {}
    for layer in config.layers:
        layer_path = config.eval_layer_path(layer)
        result = rooted(evaluate_tasks.evaluation_summary, config.output_root)(
            layer, str(layer_path), [pair.name for pair in config.pairs])
        summaries[layer] = result["summary"]
        create_markdown_artifact(Path(result["summary"]).read_text(encoding="utf-8"),
                                 key=artifact_key(config.name, "evaluation", layer_dir(layer)),
                                 description=f"Steering evaluation, {layer_dir(layer)} ({layer_path})")
    return summaries
