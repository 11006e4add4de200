"""The evaluation flow `latent-steering-evaluate`: steering dose-responses of (pair, layer)s, on the `gpu` pool.

With a server, the parent flow starts one deployment run per (pair, layer), so several GPU workers
share the work; without one, it calls this flow in-process and the pairs run one after another on
the local device (one policy load for all). Every pair is a cached task: unchanged vectors, frames
and settings give `Cached`, a refreshed vector re-evaluates only its pair.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow
from prefect.artifacts import create_markdown_artifact

from flows.children import run_phase
from steering_core.config import RunConfig
from steering_core.evaluate.report import layer_label
from steering_core.evaluate.run import run_config_job
from steering_core.layout import PATHWAYS_FILE, stream_layer_dir
from steering_core.remote.publish import pulled
from steering_core.storage.mirrors import localize
from tasks import evaluate as evaluate_tasks
from tasks.artifacts import artifact_key
from tasks.results import TaskSet
from tasks.run_configs import run_config

EVALUATE_FLOW = "latent-steering-evaluate"


def evaluation_targets(config: RunConfig) -> list[tuple[str, int, str]]:
    """Return every (pair, layer, stream) of the run, layer by layer: the language model's, then the expert's."""
    return [(pair.name, layer, stream) for layer, stream in config.eval_layers() for pair in config.pairs]


@flow(name=EVALUATE_FLOW)
def evaluate_flow(config_path: str, targets: list[tuple[str, int, str]] | None = None) -> dict:
    """Evaluate the steering vectors of `targets` (default every pair, layer and stream), one task each."""
    config = run_config(config_path)
    pulled(config.output_root)  # on a bucket root: what the jobs are planned from (pairs configs, slices, dataset)
    tasks = TaskSet(config.output_root, evaluate_tasks)
    done = []
    for target in targets or evaluation_targets(config):  # one after another: they share this device
        done.append(tasks.evaluate_pair(*evaluation_arguments(config, *target))["folder"])
    return {"folders": done}


def evaluation_arguments(config: RunConfig, name: str, layer: int, stream: str) -> tuple:
    """Return the arguments of `evaluate_pair` for one (pair, layer, stream)."""
    return run_config_job(config, name, layer, stream), config.capture_settings(), config.evaluate_settings()


def run_evaluation(config: RunConfig, config_path: str | Path) -> dict[str, str]:
    """Evaluate every (pair, layer, stream) on the `gpu` pool or in-process, then write and publish each layer's
    summary and, with expert layers, the pathways table.

    Returns layer folder name (`layer02`, `expert_layer01`, `pathways`) -> its summary.md.
    """
    pulled(config.output_root)  # on a bucket root: outputs of steps cached here but computed on other machines
    tasks = TaskSet(config.output_root, evaluate_tasks)
    run_phase(config, config_path, "evaluation", deployment=config.orchestration.evaluate_deployment,
              phase_flow=evaluate_flow, targets=evaluation_targets(config),
              name_of=lambda target: f"evaluate {target[0]} {stream_layer_dir(*target[1:])}",
              cached=lambda target: tasks.is_cached("evaluate_pair", *evaluation_arguments(config, *target)))
    summaries = {}
    names = [pair.name for pair in config.pairs]
    for layer, stream in config.eval_layers():
        layer_path, folder = config.eval_layer_path(layer, stream), stream_layer_dir(layer, stream)
        result = tasks.evaluation_summary(layer_label(layer, stream), str(layer_path), names)
        summaries[folder] = result["summary"]
        create_markdown_artifact(evaluate_tasks.ui_summary(layer_path),
                                 key=artifact_key(config.name, "evaluation", folder),
                                 description=f"Steering evaluation, {folder} ({layer_path})")
    if config.expert_layers:
        result = tasks.evaluation_pathways(str(config.eval_root), config.eval_layers(), names)
        summaries[PATHWAYS_FILE] = result["pathways"]
        create_markdown_artifact(pulled(localize(result["pathways"])).read_text(encoding="utf-8"),
                                 key=artifact_key(config.name, "evaluation", PATHWAYS_FILE),
                                 description=f"Steering pathways, language model vs action expert ({config.eval_root})")
    return summaries
