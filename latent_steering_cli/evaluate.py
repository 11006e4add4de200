"""`latent-steering split` and `latent-steering evaluate`: phase 4, does each vector steer the policy?"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.capture import layer_list
from latent_steering_cli.options import device_option
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
from steering_core.layout import STEERING_EVAL_ROOT, STEERING_ROOT, SUMMARY_MD, check_name
from steering_core.pi05.arch import read_arch
from steering_core.pi05.robot_side import DEFAULT_HORIZON
from steering_core.pi05.spec import ModelSpec
from steering_core.vectors.directions import PathsRelativeTo, SteeringSettings, load_steering_sae, read_pairs_config
from steering_core.workload import evaluation_problems

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


def _parse_floats(value: str) -> tuple[float, ...]:
    try:
        return tuple(float(part) for part in value.replace(",", " ").split())
    except ValueError:
        raise typer.BadParameter(f"{value!r} is not a list of numbers like -4,-2,0,2,4", param_hint="--alphas") from None


@app.command("evaluate")
def evaluate_command(
    ctx: typer.Context,
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
    random_directions: int | None = typer.Option(None, "--random-directions", min=8, help=f"Random directions of the null (default {_DEFAULTS.random_directions})."),
    top_k: int | None = typer.Option(None, "--top-k", min=1, help=f"SAE latents of the top-k direction (default {_DEFAULTS.top_k})."),
    batch_size: int | None = typer.Option(None, "--batch-size", min=1, help="Frames per policy call."),
    device: str | None = device_option(None),
    dtype: str | None = typer.Option(None, "--dtype", help="Compute dtype (default bfloat16 on CUDA, float32 on CPU)."),
    compiled: bool | None = typer.Option(None, "--compiled/--eager", help="Run the policy's denoising step compiled "
                                         "(default: on CUDA only; batches over 16 rows run eagerly)."),
) -> None:
    """Dose-response of each pair's steering vectors on held-out frames: efficacy vs α, against random directions.

    Give --config, or --pairs-config, --layer, --lerobot-root, --checkpoint-path and --tokenizer-path
    (the split comes from `latent-steering split`, used by `slice --split`). The action expert: add
    --decision-run and --expert-layers (--layer and --pairs-config may then be left out: --pair names the
    pairs); with --config, its evaluate.expert_layers are evaluated too (--layer or --expert-layers alone
    select one pathway).
    """
    options = EvaluateOptions(**ctx.params)
    expert = layer_list(expert_layers, "--expert-layers") if expert_layers is not None else None
    with input_errors():
        plan = _config_plan if config is not None else _flags_plan
        _run(*plan(options, expert, _setting_overrides(options)))


@dataclass(frozen=True)
class EvaluateOptions:
    """The options of `latent-steering evaluate`, as given (None: not given)."""

    config: Path | None
    pairs_config: Path | None
    layer: int | None
    pair: list[str]
    data_root: Path
    steering_root: Path | None
    output_root: Path | None
    lerobot_root: Path | None
    repo_id: str | None
    checkpoint_path: Path | None
    tokenizer_path: Path | None
    norm_stats: Path | None
    arch_file: Path | None
    decision_run: Path | None
    expert_layers: str | None
    sae: str
    sae_id: str | None
    sae_dir: Path | None
    paths_relative_to: PathsRelativeTo
    alphas: str | None
    max_frames: int | None
    noise_seeds: int | None
    random_directions: int | None
    top_k: int | None
    batch_size: int | None
    device: str | None
    dtype: str | None
    compiled: bool | None


Plan = tuple[list[tuple[EvaluateJob, SteeringSettings | None]], CaptureSettings, EvaluateSettings]


def _setting_overrides(options: EvaluateOptions) -> dict:
    """Return the evaluation settings the options give: each given option named as an EvaluateSettings field (the
    rest keep the run config's or the defaults)."""
    overrides = {name: value for name, value in asdict(options).items()
                 if name in EvaluateSettings.model_fields and value is not None}
    return overrides | ({"alphas": _parse_floats(options.alphas)} if options.alphas else {})


def _config_plan(options: EvaluateOptions, expert: list[int] | None, overrides: dict) -> Plan:
    """Return the jobs of a run config: its pairs (or --pair) at its layers and expert layers (or --layer,
    --expert-layers), with its model and evaluate settings."""
    path_flags = {"--pairs-config": options.pairs_config, "--lerobot-root": options.lerobot_root,
                  "--checkpoint-path": options.checkpoint_path, "--tokenizer-path": options.tokenizer_path,
                  "--steering-root": options.steering_root, "--output-root": options.output_root,
                  "--decision-run": options.decision_run}
    if given := [flag for flag, value in path_flags.items() if value is not None]:
        raise typer.BadParameter(f"{', '.join(given)} cannot be combined with --config", param_hint="--config")
    run = load_run_config(options.config)
    if stray := sorted(set(expert or ()) - set(run.expert_layers)):
        raise typer.BadParameter(f"{stray}: the run config's evaluate.expert_layers are {list(run.expert_layers)}",
                                 param_hint="--expert-layers")
    layer = options.layer
    layers = [layer] if layer is not None else [] if expert is not None else list(run.layers)
    expert = expert if expert is not None else [] if layer is not None else run.expert_layers
    names = options.pair or [p.name for p in run.pairs]
    jobs = [(run_config_job(run, name, lay), run.steering_settings(lay)) for lay in layers for name in names]
    jobs += [(run_config_job(run, name, lay, "expert"), None) for lay in expert for name in names]
    settings = EvaluateSettings(**(run.evaluate_settings().model_dump() | overrides))
    _check_work(settings, run.model.action_horizon or DEFAULT_HORIZON)
    return jobs, run.capture_settings(), settings


def _flags_plan(options: EvaluateOptions, expert: list[int] | None, overrides: dict) -> Plan:
    """Return the jobs the path flags describe: a pairs config's pairs at --layer, and/or the expert directions
    of a --decision-run at --expert-layers."""
    _require_flags(options, expert)
    settings = EvaluateSettings(**overrides)
    _check_work(settings, DEFAULT_HORIZON)
    layer, data_root, lerobot_root = options.layer, options.data_root, options.lerobot_root
    model = CaptureSettings(
        model=ModelSpec(checkpoint=options.checkpoint_path, tokenizer=options.tokenizer_path,
                        norm_stats=options.norm_stats, arch=read_arch(options.arch_file)),
        layers=(layer,) if layer is not None else expert,
    )
    names = [check_name(name, "--pair") for name in options.pair] or [
        p.name for p in read_pairs_config(options.pairs_config).pairs]
    places = dict(data_root=data_root, dataset_root=lerobot_root, repo_id=options.repo_id or lerobot_root.name,
                  output_root=options.output_root or data_root / STEERING_EVAL_ROOT)
    jobs = _layer_jobs(options, names, places, settings) if layer is not None else []
    if options.decision_run is not None:
        jobs += _expert_jobs(options.decision_run, expert, names, places, model, settings)
    return jobs, model, settings


def _check_work(settings: EvaluateSettings, action_horizon: int) -> None:
    """Refuse settings whose estimated work per (pair, layer) is over its limit (`steering_core.workload`)."""
    if problems := evaluation_problems(settings, action_horizon):
        raise ValueError("; ".join(problems))


def _require_flags(options: EvaluateOptions, expert: list[int] | None) -> None:
    """Refuse a flag set that names no complete job (--config missing)."""
    decision_run = options.decision_run
    needed = {"--lerobot-root": options.lerobot_root, "--checkpoint-path": options.checkpoint_path,
              "--tokenizer-path": options.tokenizer_path}
    if options.layer is not None or decision_run is None:
        needed = {"--pairs-config": options.pairs_config, "--layer": options.layer} | needed
    missing = [flag for flag, value in needed.items() if value is None]
    if decision_run is not None and options.layer is None and not (options.pair or options.pairs_config):
        missing.insert(0, "--pair or --pairs-config")
    if decision_run is not None and expert is None:
        missing.append("--expert-layers")
    if missing:
        raise typer.BadParameter(f"{', '.join(missing)} required (or give --config)", param_hint=missing[0])
    if expert is not None and decision_run is None:
        raise typer.BadParameter("needs --decision-run (a `capture --token-type decision` run)",
                                 param_hint="--expert-layers")


def _layer_jobs(options: EvaluateOptions, names: list[str], places: dict, settings: EvaluateSettings) -> list:
    """Return the language-model jobs of each named pair of --pairs-config at --layer."""
    sae, pairs_config, data_root = options.sae, options.pairs_config, options.data_root
    steering = SteeringSettings(pairs_config=pairs_config, layer=options.layer, device=settings.device,
                                sae=None if sae.lower() == NO_SAE else sae, sae_id=options.sae_id,
                                sae_dir=options.sae_dir)
    base_dir = Path.cwd() if options.paths_relative_to == "cwd" else pairs_config.parent
    steering_root = options.steering_root or data_root / STEERING_ROOT
    return [(pair_job(pairs_config, name, options.layer, base_dir=base_dir, steering_root=steering_root, **places),
             steering) for name in names]


def _expert_jobs(decision_run: Path, expert: list[int], names: list[str], places: dict, model: CaptureSettings,
                 settings: EvaluateSettings) -> list:
    """Return the expert jobs of each named pair: its decision slices cut here (held-out episodes left out)."""
    for layer in expert:
        check_model(model, layer, "expert")
    check_decision_run(decision_run, expert, model, settings.num_steps)  # before anything is written
    slices = {name: slice_decision_run(decision_run, name, expert, data_root=places["data_root"]) for name in names}
    return [(expert_job(name, layer, slices_root=slices[name], **places), None) for layer in expert for name in names]


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
