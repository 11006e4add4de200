"""The parent flow `latent-steering`: the recipe's phases over every concept pair and layer, after a preflight.

0. Preflight: every input checked (sources or the existing dataset, checkpoint, tokenizer, SAEs,
   output folders, devices).
1. Data (CPU): filter demo files, convert them to one LeRobot dataset (or, with
   `dataset.existing`, read an existing dataset in place), then a contrast manifest
   and a concept map per pair.
2. Capture (GPU): the `latent-steering-capture` flow, as deployment runs on the `gpu` pool or
   in-process (`flows.capture.run_capture`), then the run metadata; with `evaluate.expert_layers`,
   each capture run also writes the action expert's `decision` rows (`residuals/<name>_decision`).
   Then, for layers with `sae.<layer>.train`, the `latent-steering-train-sae` flow (GPU) trains their SAE
   on these residuals and judges it against the borrowed one (`flows.train_sae`); those layers steer through it.
3. Steering vectors (CPU), fanned out over every (pair, layer): slice residuals by concept (held-out episodes left out),
   SAE statistics per concept, directions per pair; then per layer the pairwise statistics, the
   report and its artifacts. The decision rows are sliced per (pair, expert layer) the same way.
4. Evaluation (GPU): the `latent-steering-evaluate` flow, one run per (pair, layer) of the language
   model and of the expert on the `gpu` pool or in-process (`flows.evaluate.run_evaluation`), then
   each layer's evaluation summary and, with expert layers, the pathways table.
5. Rollouts (CPU simulator; `rollout` section): the `latent-steering-rollout` flow, one run per (pair, layer,
   side) on the `sim` pool or in-process (`flows.rollout.run_rollouts`): closed-loop LIBERO episodes per
   steering dose and control, then each layer's rollout summary.

Every task is cached on the content of its inputs (`tasks.cache_keys`): a re-run on unchanged inputs
reads every result from the cache, and a new demo file recomputes only what depends on it. After a
successful run the demo sources (or the existing dataset's fingerprint) are recorded for the
scheduled refresh (`flows.refresh`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger
from prefect.futures import PrefectFuture
from prefect.settings import get_current_settings
from prefect.task_runners import ThreadPoolTaskRunner

from flows.capture import run_capture
from flows.children import orchestration_mode
from flows.evaluate import run_evaluation
from flows.rollout import run_rollouts
from flows.train_sae import feature_pages, run_training
from steering_core.config import RunConfig, share_run_config
from steering_core.data.dataset_checks import check_dataset
from steering_core.pairs import SIDES
from steering_core.refresh import SOURCES_RECORD_FILE, read_sources_record, scan_inputs, write_sources_record
from steering_core.remote.publish import publish, pulled
from steering_core.storage.mirrors import is_url, localize, portable
from tasks import capture as capture_tasks
from tasks import data, report, sae
from tasks.artifacts import publish_layer_report
from tasks.preflight import preflight
from tasks.results import TaskSet
from tasks.run_configs import run_config, sharing

PIPELINE_FLOW = "latent-steering"
# CPU tasks running at once (PREFECT_TASKS_RUNNER_THREAD_POOL_MAX_WORKERS overrides): each SAE task
# holds its own copy of the SAE (256 MiB for Gemma-2B's 16k latents), so the pool must stay bounded.
CPU_TASKS = get_current_settings().tasks.runner.thread_pool_max_workers or 4


@flow(name=PIPELINE_FLOW, task_runner=ThreadPoolTaskRunner(max_workers=CPU_TASKS))
def latent_steering(config_path: str) -> dict[str, Any]:
    """Run the whole pipeline described by a run config (YAML); return where its outputs are."""
    config_path = config_path if is_url(config_path) else str(Path(config_path).resolve())
    config = run_config(config_path)  # parsed once: what the CLI shared, else read here
    with sharing(config, config_path):  # the in-process flows and tasks of this run read this parse
        preflight(config_path, capture_device=orchestration_mode(config) == "local")  # minutes before the GPU hours
        shared_path = share_run_config(config) or config_path  # on a bucket root, workers elsewhere read it there
        with sharing(config, shared_path):
            return run_phases(config, shared_path)


def run_phases(config: RunConfig, config_path: str) -> dict[str, Any]:
    """Run every phase of a checked run config (`config_path` names it for child runs); return the outputs."""
    logger = get_run_logger()
    record_path = config.output_root / SOURCES_RECORD_FILE
    sources = scan_inputs(config, previous=read_sources_record(pulled(record_path)))

    tasks = TaskSet(config.output_root, data, capture_tasks, sae, report)
    task_texts = prepare_data(config, tasks)
    holdouts = holdout_splits(config, tasks)
    mode = run_capture(config, config_path)  # with evaluate.expert_layers, the decision rows too
    logger.info("capture ran %s", "on the gpu work pool" if mode == "deployment" else "in this process")
    expert_slices = decision_slices(config, tasks, holdouts)  # submitted: sliced on this machine while training runs
    trained = run_training(config, config_path)  # the layers whose SAE is trained on these residuals
    reports = steering_vectors(config, tasks, task_texts, holdouts)
    for future in expert_slices:
        future.result()

    features = feature_pages(config)  # of the trained SAEs: their latents in the pairs' directions
    for layer_path in reports.values():
        publish_layer_report(pulled(layer_path), config.name)
    evaluations = run_evaluation(config, config_path) if config.evaluate is not None else {}
    rollouts = run_rollouts(config, config_path) if config.rollout is not None else {}
    publish(write_sources_record(record_path, sources.with_config(config.fingerprint())))
    logger.info("done: reports in %s", ", ".join(str(Path(p) / "summary.md") for p in reports.values()))
    return portable({"output_root": str(config.output_root), "run_dir": str(config.run_dir), "capture": mode,
            "reports": {str(layer): path for layer, path in reports.items()}, "trained_saes": trained,
            "feature_pages": features,
            "evaluations": evaluations, "rollouts": rollouts})  # on a bucket root: URLs


def prepare_data(config: RunConfig, tasks: TaskSet) -> dict[str, tuple[str, str]]:
    """Run phase 1; return pair -> (positive, negative) task texts as the dataset spells them."""
    dataset_root, repo_id = str(config.dataset_root), config.repo_id
    if config.sources is not None:
        tasks.filter_demos([str(f) for f in config.sources.folders], str(config.filtered_dir), config.filter_settings())
        tasks.convert_dataset(str(config.filtered_dir), dataset_root, config.convert_settings())
    else:  # read in place: checked here, never written
        meta = check_dataset(dataset_root)
        get_run_logger().info("reading the existing LeRobot %s dataset %s in place (%d episodes)",
                              meta.version, dataset_root, len(meta.episodes))
    manifests: dict[str, PrefectFuture] = {}
    maps: dict[str, PrefectFuture] = {}
    for pair in config.pairs:
        manifests[pair.name] = tasks.build_manifest.submit(
            pair.name, dataset_root, pair.positive, pair.negative, pair.manifest, repo_id,
            str(config.manifest_path(pair)))
        maps[pair.name] = tasks.map_concepts.submit(
            pair.name, str(config.manifest_path(pair)), dataset_root, repo_id, pair.rename,
            str(config.concept_map_path(pair)), wait_for=[manifests[pair.name]])
    for future in maps.values():
        future.result()
    return {name: tuple(future.result()["tasks"]) for name, future in manifests.items()}


def holdout_splits(config: RunConfig, tasks: TaskSet) -> dict[str, tuple[int, ...]]:
    """Write each pair's held-out split (manifests/<pair>_split.json); return pair -> held-out episodes."""
    return {pair.name: tuple(tasks.split_episodes(pair.name, str(config.manifest_path(pair)), config.holdout_fraction,
                                        str(config.split_path(pair)))["holdout_episodes"])
            for pair in config.pairs}


def decision_slices(config: RunConfig, tasks: TaskSet, holdouts: dict[str, tuple[int, ...]]) -> list[PrefectFuture]:
    """Submit the slicing of the `decision` rows per (pair, expert layer), held-out episodes left out."""
    return [
        tasks.slice_layer.with_options(task_run_name=f"slice {pair.name} expert layer {layer}").submit(
            pair.name, layer, str(config.decision_run_dir), str(config.concept_map_path(pair)),
            str(config.decision_slices_dir(pair)), config.slice_settings(layer, holdouts[pair.name], "expert"))
        for layer in config.expert_layers for pair in config.pairs
    ]


def steering_vectors(
    config: RunConfig, tasks: TaskSet, task_texts: dict[str, tuple[str, str]], holdouts: dict[str, tuple[int, ...]]
) -> dict[int, str]:
    """Run the SAE phase over every (pair, layer), held-out episodes left out; return layer -> its output folder."""
    run_dir = str(config.run_dir)
    slices = {
        (pair.name, layer): tasks.slice_layer.submit(
            pair.name, layer, run_dir, str(config.concept_map_path(pair)), str(config.slices_dir(pair)),
            config.slice_settings(layer, holdouts[pair.name]))
        for layer in config.layers for pair in config.pairs
    }
    stats: dict[tuple[str, int, str], PrefectFuture] = {}
    specs = {}
    for layer in config.layers:
        concepts = {pair.name: localize(slices[pair.name, layer].result()["concepts"]) for pair in config.pairs}
        pairs_config = config.pairs_config(layer, task_texts, concepts)
        path = config.pairs_config_path(layer)
        tasks.write_pairs_config(layer, pairs_config, str(path))
        settings = config.steering_settings(layer)
        for spec in pairs_config.pairs:
            specs[spec.name, layer] = spec
            for side in SIDES:
                label, concept_path = getattr(spec, f"{side}_label"), getattr(spec, f"{side}_path")
                stats[spec.name, layer, side] = tasks.encode_concept.submit(
                    spec.name, side, layer, label, str(path.parent / concept_path), settings)
    directions = {
        key: tasks.pair_directions.submit(
            spec, key[1], stats[(*key, "positive")].result()["stats"], stats[(*key, "negative")].result()["stats"],
            config.steering_settings(key[1]))
        for key, spec in specs.items()
    }
    reports = {}
    for layer in config.layers:
        layer_path, names = str(config.layer_path(layer)), [pair.name for pair in config.pairs]
        for name in names:
            directions[name, layer].result()
        tasks.pairwise_stats(layer, layer_path, names)
        trained = str(config.sae_layer_path(layer)) if layer in config.trained_layers else None
        tasks.write_report(layer, layer_path, names, config.steering.top_k, trained)
        reports[layer] = layer_path
    return reports
