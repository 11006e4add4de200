"""`latent-steering split` and `latent-steering evaluate`: phase 4, does each vector steer the policy?"""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.capture import layer_list
from steering_core.capture import CaptureSettings
from steering_core.config import load_run_config
from steering_core.data.contrast import read_manifest
from steering_core.data.split import split_episodes, write_split
from steering_core.evaluate import EvaluateSettings
from steering_core.evaluate.report import write_layer_summary, write_pathways
from steering_core.evaluate.run import (
    EvaluateJob,
    check_decision_run,
    check_model,
    evaluate_job,
    expert_job,
    pair_job,
    run_config_job,
    slice_decision_run,
)
from steering_core.pi05 import Pi05Arch
from steering_core.sae.vectors import PathsRelativeTo, SteeringSettings, load_steering_sae, read_pairs_config
from steering_core.storage.fileio import read_json
from steering_core.storage.layout import STEERING_EVAL_ROOT, STEERING_ROOT, SUMMARY_MD

_DEFAULTS = EvaluateSettings()
NO_SAE = "none"


@app.command("split")
def split_command(
    manifest: Path = typer.Option(..., "--manifest", help="Contrast manifest, e.g. data/manifests/open_vs_close.json."),
    output: Path = typer.Option(..., "--output", help="Split JSON, e.g. data/manifests/open_vs_close_split.json."),
    holdout_fraction: float = typer.Option(
        _DEFAULTS.holdout_fraction, "--holdout-fraction", min=0.0, max=0.99,
        help="Share of each task's episodes held out of slicing for the evaluation (at least one; 0: none).",
    ),
) -> None:
    """Split each task's episodes into training (sliced) and held-out (evaluated) ones; pass it to `slice --split`."""
    with input_errors():
        split = split_episodes(read_manifest(manifest), holdout_fraction, where=str(manifest))
        write_split(split, output)
    for task, sides in split.tasks.items():
        typer.echo(f"{task}: train {list(sides.train)}, held out {list(sides.holdout)}")


def _floats(value: str) -> tuple[float, ...]:
    try:
        return tuple(float(part) for part in value.replace(",", " ").split())
    except ValueError:
        raise typer.BadParameter(f"{value!r} is not a list of numbers like -4,-2,0,2,4", param_hint="--alphas") from None


@app.command("evaluate")
def evaluate_command(
    config: Path | None = typer.Option(
        None, "--config", help="Run config (YAML): evaluate its pairs and layers with its model, SAE and evaluate "
        "settings (the flags below then override the evaluate section; path flags are not allowed)."),
    pairs_config: Path | None = typer.Option(None, "--pairs-config", help="Pairs JSON, e.g. data/latent_steering/layer12_pairs.json."),
    layer: int | None = typer.Option(None, "--layer", min=0, help="Decoder layer of the vectors (--config: one of its layers)."),
    pair: list[str] = typer.Option([], "--pair", help="Evaluate only this pair (repeatable; default all)."),
    data_root: Path = typer.Option(Path("data"), "--data-root", help="The seed's data/ folder: manifests/<pair>.json, "
                                   "<pair>_concept_map.json and <pair>_split.json."),
    steering_root: Path | None = typer.Option(None, "--steering-root", help=f"Phase 3 outputs (default <data-root>/{STEERING_ROOT})."),
    output_root: Path | None = typer.Option(None, "--output-root", help=f"Outputs (default <data-root>/{STEERING_EVAL_ROOT})."),
    lerobot_root: Path | None = typer.Option(None, "--lerobot-root", help="LeRobot dataset the frames come from."),
    repo_id: str | None = typer.Option(None, "--repo-id", help="Dataset repo id (default: the dataset folder name)."),
    checkpoint_path: Path | None = typer.Option(None, "--checkpoint-path", help="openpi PyTorch pi0.5 checkpoint folder."),
    tokenizer_path: Path | None = typer.Option(None, "--tokenizer-path", help="PaliGemma SentencePiece model."),
    norm_stats: Path | None = typer.Option(None, "--norm-stats", help="norm_stats.json (default: the checkpoint's assets)."),
    arch_file: Path | None = typer.Option(None, "--arch-file", help="JSON of Pi05Arch fields, for a non-standard (tiny) checkpoint."),
    decision_run: Path | None = typer.Option(
        None, "--decision-run", help="Residual run of `capture --token-type decision` (the action expert's rows, same "
        "checkpoint): also evaluate each pair's expert direction at --expert-layers (sliced here, held-out episodes "
        "left out, into <data-root>/residuals/<pair>_decision_slices)."),
    expert_layers: str | None = typer.Option(
        None, "--expert-layers", help="Action-expert layers to evaluate, e.g. 9 or 3,9 (with --decision-run, or "
        "--config: some of its evaluate.expert_layers)."),
    sae: str = typer.Option("gemma-2b-it-res-jb", "--sae", help=f"SAE of the layer (for the top-k direction); '{NO_SAE}': none."),
    sae_id: str | None = typer.Option(None, "--sae-id", help="SAE within the release (default blocks.<layer>.hook_resid_post)."),
    sae_dir: Path | None = typer.Option(None, "--sae-dir", help="Folder holding downloaded SAE release folders."),
    paths_relative_to: PathsRelativeTo = typer.Option("cwd", "--paths-relative-to",
                                                      help="Resolve the pairs config's slice paths against cwd or its folder."),
    alphas: str | None = typer.Option(None, "--alphas", help="α grid in units of the mean residual norm / ||d||, with 0 "
                                      f"(default {','.join(f'{a:g}' for a in _DEFAULTS.alphas)})."),
    max_frames: int | None = typer.Option(None, "--max-frames", min=2, help=f"Frames per pair (default {_DEFAULTS.max_frames})."),
    noise_seeds: int | None = typer.Option(None, "--noise-seeds", min=1, help=f"Noise draws per frame (default {_DEFAULTS.noise_seeds})."),
    random_directions: int | None = typer.Option(None, "--random-directions", min=8, help="Random directions in the null band (default 8)."),
    top_k: int | None = typer.Option(None, "--top-k", min=1, help=f"SAE latents of the top-k direction (default {_DEFAULTS.top_k})."),
    batch_size: int | None = typer.Option(None, "--batch-size", min=1, help="Frames per policy call."),
    device: str | None = typer.Option(None, "--device", help="auto (CUDA when available), cuda, cuda:1 or cpu."),
    dtype: str | None = typer.Option(None, "--dtype", help="Compute dtype (default bfloat16 on CUDA, float32 on CPU)."),
) -> None:
    """Dose-response of each pair's steering vectors on held-out frames: efficacy vs α, against random directions.

    Give --config, or --pairs-config, --layer, --lerobot-root, --checkpoint-path and --tokenizer-path
    (the split comes from `latent-steering split`, used by `slice --split`). The action expert: add
    --decision-run and --expert-layers (--layer and --pairs-config may then be left out: --pair names the
    pairs); with --config, its evaluate.expert_layers are evaluated too (--layer or --expert-layers alone
    select one pathway).
    """
    overrides = {name: value for name, value in (
        ("alphas", _floats(alphas) if alphas else None), ("max_frames", max_frames), ("noise_seeds", noise_seeds),
        ("random_directions", random_directions), ("top_k", top_k), ("batch_size", batch_size), ("device", device),
        ("dtype", dtype)) if value is not None}
    expert = layer_list(expert_layers, "--expert-layers") if expert_layers is not None else None
    with input_errors():
        if config is not None:
            step_flags = [flag for flag, value in (("--pairs-config", pairs_config), ("--lerobot-root", lerobot_root),
                                                   ("--checkpoint-path", checkpoint_path), ("--tokenizer-path", tokenizer_path),
                                                   ("--steering-root", steering_root), ("--output-root", output_root),
                                                   ("--decision-run", decision_run))
                          if value is not None]
            if step_flags:
                raise typer.BadParameter(f"{', '.join(step_flags)} cannot be combined with --config", param_hint="--config")
            run = load_run_config(config)
            if stray := sorted(set(expert or ()) - set(run.expert_layers)):
                raise typer.BadParameter(f"{stray}: the run config's evaluate.expert_layers are "
                                         f"{list(run.expert_layers)}", param_hint="--expert-layers")
            layers = [layer] if layer is not None else [] if expert is not None else list(run.layers)
            expert = expert if expert is not None else [] if layer is not None else run.expert_layers
            names = pair or [p.name for p in run.pairs]
            settings = EvaluateSettings(**(run.evaluate_settings().model_dump() | overrides))
            jobs = [(run_config_job(run, name, lay), run.steering_settings(lay)) for lay in layers for name in names]
            jobs += [(run_config_job(run, name, lay, "expert"), None) for lay in expert for name in names]
            model = run.capture_settings()
        else:
            needed = ((("--pairs-config", pairs_config), ("--layer", layer)) if layer is not None or decision_run is None
                      else (("--pair or --pairs-config", pair or pairs_config),))
            missing = [flag for flag, value in (*needed, ("--lerobot-root", lerobot_root),
                                                ("--checkpoint-path", checkpoint_path),
                                                ("--tokenizer-path", tokenizer_path),
                                                *((("--expert-layers", expert),) if decision_run is not None else ()))
                       if value is None]
            if missing:
                raise typer.BadParameter(f"{', '.join(missing)} required (or give --config)", param_hint=missing[0])
            if expert is not None and decision_run is None:
                raise typer.BadParameter("needs --decision-run (a `capture --token-type decision` run)",
                                         param_hint="--expert-layers")
            settings = EvaluateSettings(**overrides)
            model = CaptureSettings(checkpoint_path=checkpoint_path, tokenizer_path=tokenizer_path,
                                    layers=(layer,) if layer is not None else expert, norm_stats_path=norm_stats,
                                    arch=Pi05Arch.model_validate(read_json(arch_file)) if arch_file else Pi05Arch())
            names = pair or [p.name for p in read_pairs_config(pairs_config).pairs]
            places = dict(data_root=data_root, dataset_root=lerobot_root, repo_id=repo_id or lerobot_root.name,
                          output_root=output_root or data_root / STEERING_EVAL_ROOT)
            jobs = []
            if layer is not None:
                steering = SteeringSettings(pairs_config=pairs_config, layer=layer, device=settings.device,
                                            sae=None if sae.lower() == NO_SAE else sae, sae_id=sae_id, sae_dir=sae_dir)
                base_dir = Path.cwd() if paths_relative_to == "cwd" else pairs_config.parent
                jobs += [(pair_job(pairs_config, name, layer, base_dir=base_dir,
                                   steering_root=steering_root or data_root / STEERING_ROOT, **places), steering)
                         for name in names]
            if decision_run is not None:
                for lay in expert:
                    check_model(model, lay, "expert")
                check_decision_run(decision_run, expert, model, settings.num_steps)  # before anything is written
                slices = {name: slice_decision_run(decision_run, name, expert, data_root=data_root) for name in names}
                jobs += [(expert_job(name, lay, slices_root=slices[name], **places), None)
                         for lay in expert for name in names]
        _run(jobs, model, settings)


def _run(jobs: list[tuple[EvaluateJob, SteeringSettings | None]], model: CaptureSettings,
         settings: EvaluateSettings) -> None:
    """Evaluate every job (one policy for all), then write each layer's summary (and, with both pathways,
    the pathways table)."""
    layers: dict[Path, list[str]] = {}
    for job, steering in jobs:
        folder = evaluate_job(job, model, settings, load_steering_sae(steering) if steering is not None else None)
        typer.echo(f"{job.pair} {job.label}: {folder}")
        layers.setdefault(folder.parent, []).append(job.pair)
    for layer_path, names in layers.items():
        typer.echo(f"summary: {write_layer_summary(layer_path, names)}")
    if not jobs:
        typer.echo(f"nothing to evaluate; see {SUMMARY_MD} files under the output root")
    elif any(job.stream == "expert" for job, _ in jobs):
        evaluated = list(dict.fromkeys((job.layer, job.stream) for job, _ in jobs))
        names = list(dict.fromkeys(job.pair for job, _ in jobs))
        typer.echo(f"pathways: {write_pathways(jobs[0][0].output_dir.parent.parent, evaluated, names)}")
