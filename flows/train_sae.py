"""The SAE training flow `latent-steering-train-sae`: SAEs trained on the run's own residuals, on the `gpu` pool.

For every layer with `sae.<layer>.train`, after capture and before the SAE phase: train the SAE on the layer's
rows with the held-out episodes left out (`steering_core.sae.training.heldout`), then judge it on those episodes against
the borrowed SAE named beside `train`. With a server, the parent starts one deployment run per layer not cached
yet; without one, it calls this flow in-process.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.children import run_phase
from steering_core.capture import shards
from steering_core.config import RunConfig
from steering_core.data.dataset import read_meta
from steering_core.data.split import read_split
from steering_core.layout import layer_dir
from steering_core.remote.publish import pulled
from steering_core.sae.training.heldout import sae_heldout_episodes
from steering_core.sae_quality.feature_run import FeatureJob
from steering_core.sae_quality.judge_run import JudgedPair, JudgeJob
from tasks import sae_train
from tasks.results import TaskSet
from tasks.run_configs import run_config

TRAIN_FLOW = "latent-steering-train-sae"


def heldout_episodes(config: RunConfig, layer: int) -> list[int]:
    """Return the episodes the layer's SAE is not trained on (and is judged on)."""
    captured = set(shards.read_run_metadata(pulled(config.run_dir / shards.METADATA_FILE).parent).episodes)
    task_episodes: dict[str, list[int]] = {}
    for episode in read_meta(pulled(config.dataset_root)).episodes:
        if episode.episode_index in captured:
            task_episodes.setdefault(episode.task, []).append(episode.episode_index)
    splits = [read_split(pulled(config.split_path(pair))) for pair in config.pairs]
    return list(sae_heldout_episodes(task_episodes, splits, config.sae_for(layer).train.heldout_fraction))


def train_arguments(config: RunConfig, layer: int) -> tuple:
    """Return the arguments of `train_layer_sae` for one layer."""
    return (layer, str(config.run_dir), str(config.trained_sae_dir(layer)), config.train_settings(layer),
            heldout_episodes(config, layer))


def judge_arguments(config: RunConfig, layer: int) -> tuple:
    """Return the arguments of `judge_trained_sae` for one layer: its held-out rows, and the first pair's held-out
    frames for the action change (none at the last layer, whose output no action reads)."""
    train, pair = config.sae_for(layer).train, config.pairs[0]
    judged = None if layer == config.model.arch.depth - 1 else JudgedPair(
        name=pair.name, manifest=config.manifest_path(pair), concept_map=config.concept_map_path(pair))
    job = JudgeJob(layer=layer, run_dir=config.run_dir, trained=config.trained_sae_dir(layer),
                   heldout_episodes=tuple(heldout_episodes(config, layer)), output_dir=config.sae_layer_path(layer),
                   pair=judged, dataset_root=config.dataset_root, repo_id=config.repo_id, frames=train.judge_frames,
                   device=train.device)
    borrowed = config.steering_settings(layer, borrowed=True)
    return job, config.capture_settings(), borrowed if borrowed.sae is not None else None


@flow(name=TRAIN_FLOW)
def train_sae_flow(config_path: str, targets: list[list[int]] | None = None) -> dict:
    """Train (and judge) the SAE of every `targets` layer (default every trained layer), one after another."""
    config = run_config(config_path)
    tasks, folders = TaskSet(config.output_root, sae_train), {}
    for (layer,) in targets or [[layer] for layer in config.trained_layers]:
        folders[layer_dir(layer)] = tasks.train_layer_sae(*train_arguments(config, layer))["sae"]
        tasks.judge_trained_sae(*judge_arguments(config, layer))
    return {"saes": folders}


def run_training(config: RunConfig, config_path: str | Path) -> dict[str, str]:
    """Train every trained layer's SAE on the `gpu` pool or in-process; return layer folder name -> SAE folder."""
    layers = config.trained_layers
    if not layers:
        return {}
    tasks = TaskSet(config.output_root, sae_train)
    run_phase(config, config_path, "SAE training", deployment=config.orchestration.train_deployment,
              phase_flow=train_sae_flow, targets=[[layer] for layer in layers],
              name_of=lambda target: f"train SAE {layer_dir(target[0])}",
              cached=lambda target: (tasks.is_cached("train_layer_sae", *train_arguments(config, *target))
                                     and tasks.is_cached("judge_trained_sae", *judge_arguments(config, *target))))
    return {layer_dir(layer): str(config.trained_sae_dir(layer)) for layer in layers}


def feature_job(config: RunConfig, layer: int) -> FeatureJob:
    """Return the feature page job of one trained layer (after the SAE phase: it reads the pairs' directions)."""
    train, capture = config.sae_for(layer).train, config.capture_settings()
    return FeatureJob(layer=layer, run_dir=config.run_dir, sae=config.trained_sae_dir(layer),
                      output_dir=config.sae_layer_path(layer), steering_layer=config.layer_path(layer),
                      dataset_root=config.dataset_root, repo_id=config.repo_id, tokenizer=capture.model.tokenizer,
                      pair_top_k=config.steering.top_k, examples=train.feature_examples, device=train.device,
                      video_backend=capture.video_backend)


def feature_pages(config: RunConfig) -> dict[str, str]:
    """Write every trained layer's feature page and Neuronpedia export (CPU); return layer folder name -> page."""
    feature_page = TaskSet(config.output_root, sae_train).feature_page
    futures = {layer_dir(layer): feature_page.submit(feature_job(config, layer)) for layer in config.trained_layers}
    return {name: future.result()["page"] for name, future in futures.items()}
