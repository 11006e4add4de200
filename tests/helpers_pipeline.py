"""The seed's steps one by one through the CLI, on a run config's inputs: the pipeline without Prefect."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.config import RunConfig
from steering_core.layout import layer_dir


def run_cli_steps(config: RunConfig, out: Path) -> None:
    """Run filter, convert, manifest, concept-map, capture, split, slice, steer and evaluate into `out` (the seed's layout).

    The evaluation runs at the last layer only (with the run config's evaluate settings; none without them);
    with evaluate.expert_layers, a `capture --token-type decision` run is evaluated with `--decision-run`.
    """
    repo = config.dataset.repo_id
    dataset, run_dir = out / "libero_lerobot" / repo, out / "residuals" / "demo"
    arch_file = out / "arch.json"
    out.mkdir(parents=True, exist_ok=True)
    arch_file.write_text(config.model.arch.model_dump_json())
    layers = ",".join(map(str, config.layers))
    tasks = [text for pair in config.pairs for text in (pair.positive, pair.negative)]
    steps = [
        ["filter", "--input-dir", str(config.sources.folders[0]), "--output-dir", str(out / "filtered"),
         *[arg for task in tasks for arg in ("--task", task)]],
        ["convert", "--input-dir", str(out / "filtered"), "--repo-id", repo, "--output-dir", str(dataset),
         "--image-size", str(config.dataset.image_size)],
    ]
    for pair in config.pairs:
        manifest = out / "manifests" / f"{pair.name}.json"
        concept_map = out / "manifests" / f"{pair.name}_concept_map.json"
        steps += [
            ["manifest", "--lerobot-root", str(dataset), "--task-a-text", pair.positive, "--task-b-text",
             pair.negative, "--output", str(manifest), "--repo-id", repo],
            ["concept-map", "--manifest-path", str(manifest), "--output-path", str(concept_map),
             "--lerobot-root", str(dataset), "--repo-id", repo],
        ]
    steps.append(["capture", "--checkpoint-path", str(config.model.checkpoint), "--tokenizer-path",
                  str(config.model.tokenizer), "--lerobot-root", str(dataset), "--repo-id", repo, "--output-dir",
                  str(run_dir), "--layers", layers, "--batch-size", str(config.capture.batch_size), "--device", "cpu",
                  "--num-workers", "0", "--arch-file", str(arch_file)])
    fraction = config.evaluate.holdout_fraction if config.evaluate is not None else 0.0
    steps += [["split", "--manifest", str(out / "manifests" / f"{p.name}.json"), "--output",
               str(out / "manifests" / f"{p.name}_split.json"), "--holdout-fraction", str(fraction)]
              for p in config.pairs]
    steps += [["slice", "--run-dir", str(run_dir), "--concept-map-path",
               str(out / "manifests" / f"{p.name}_concept_map.json"), "--output-dir",
               str(out / "residuals" / f"{p.name}_slices"), "--layers", layers,
               "--split", str(out / "manifests" / f"{p.name}_split.json")] for p in config.pairs]
    runner = CliRunner()
    for step in steps:
        result = runner.invoke(app, step)
        assert result.exit_code == 0, (step[0], result.output, result.exception)
    saes = {layer: str(config.sae[layer].path) for layer in config.layers}
    for layer in config.trained_layers:  # `train-sae` with the held-out episodes the flow leaves out
        saes[layer] = str(out / "saes" / "demo" / layer_dir(layer) / "sae")
        result = runner.invoke(app, ["train-sae", "--run-dir", str(run_dir), "--layer", str(layer), "--output-dir",
                                     saes[layer], *train_options(config, layer, dataset, out)])
        assert result.exit_code == 0, (result.output, result.exception)
    for layer in config.layers:
        pairs = {"pairs": [{
            "name": p.name,
            "positive_label": p.positive, "negative_label": p.negative,
            "positive_path": str(out / "residuals" / f"{p.name}_slices" / layer_dir(layer) / f"{p.positive}.pt"),
            "negative_path": str(out / "residuals" / f"{p.name}_slices" / layer_dir(layer) / f"{p.negative}.pt"),
        } for p in config.pairs]}
        pairs_file = out / f"layer{layer}_pairs.json"
        pairs_file.write_text(json.dumps(pairs))
        result = runner.invoke(app, [
            "steer", "--pairs-config", str(pairs_file), "--output-root", str(out / "latent_steering"),
            "--layer", str(layer), "--device", "cpu", "--batch-size", str(config.steering.batch_size),
            "--sae", saes[layer], "--top-k", str(config.steering.top_k)])
        assert result.exit_code == 0, (result.output, result.exception)
    evaluate = config.evaluate
    if evaluate is None:
        return
    layer = config.layers[-1]
    common = ["--data-root", str(out), "--lerobot-root", str(dataset), "--repo-id", repo,
              "--checkpoint-path", str(config.model.checkpoint), "--tokenizer-path", str(config.model.tokenizer),
              "--arch-file", str(arch_file), "--max-frames", str(evaluate.max_frames),
              "--noise-seeds", str(evaluate.noise_seeds), "--batch-size", str(evaluate.batch_size), "--device", "cpu"]
    result = runner.invoke(app, [
        "evaluate", "--pairs-config", str(out / f"layer{layer}_pairs.json"), "--layer", str(layer), *common])
    assert result.exit_code == 0, (result.output, result.exception)
    if not evaluate.expert_layers:
        return
    expert = ",".join(map(str, evaluate.expert_layers))
    decision = out / "residuals" / "demo_decision"
    for step in (
        ["capture", "--checkpoint-path", str(config.model.checkpoint), "--tokenizer-path", str(config.model.tokenizer),
         "--lerobot-root", str(dataset), "--repo-id", repo, "--output-dir", str(decision), "--layers", expert,
         "--token-type", "decision", "--num-steps", str(config.capture.num_steps), "--batch-size",
         str(config.capture.batch_size), "--device", "cpu", "--num-workers", "0", "--arch-file", str(arch_file)],
        # the expert pathway alone: pairs by name, no --layer and no pairs config
        ["evaluate", "--decision-run", str(decision), "--expert-layers", expert,
         *[arg for p in config.pairs for arg in ("--pair", p.name)], *common],
    ):
        result = runner.invoke(app, step)
        assert result.exit_code == 0, (step[0], result.output, result.exception)


def train_options(config: RunConfig, layer: int, dataset: Path, out: Path) -> list[str]:
    """Return `train-sae`'s options for the layer's training settings and the episodes the flow holds out."""
    from steering_core.data.dataset import read_meta
    from steering_core.data.split import read_split
    from steering_core.sae.training.heldout import sae_heldout_episodes

    settings = config.train_settings(layer)
    options = [arg for name, value in settings.model_dump().items()
               for arg in ("--" + name.replace("_", "-"), str(value))]
    task_episodes: dict[str, list[int]] = {}
    for episode in read_meta(dataset).episodes:
        task_episodes.setdefault(episode.task, []).append(episode.episode_index)
    splits = [read_split(out / "manifests" / f"{pair.name}_split.json") for pair in config.pairs]
    held = sae_heldout_episodes(task_episodes, splits, config.sae[layer].train.heldout_fraction)
    return options + [arg for episode in held for arg in ("--exclude-episode", str(episode))]
