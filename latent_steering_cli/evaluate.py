"""`latent-steering split` and `latent-steering evaluate`: phase 4, does each vector steer the policy?"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.capture import layer_list
from latent_steering_cli.numbers import number_option
from latent_steering_cli.options import Flag, model_inputs, model_options, names_flag, settings_options
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
from steering_core.pi05.robot_side import DEFAULT_HORIZON
from steering_core.pi05.spec import ModelSpec
from steering_core.storage.overwrites import check_no_overwrite
from steering_core.vectors.directions import PathsRelativeTo, SteeringSettings, read_pairs_config
from steering_core.workload import evaluation_problems

_DEFAULTS = EvaluateSettings()
_STEERING_FIELDS = SteeringSettings.model_fields  # --paths-relative-to: the steer step's default and help


@app.command("split")
def split_command(
    manifest: Path = typer.Option(..., "--manifest", help="Contrast manifest, e.g. data/manifests/open_vs_close.json."),
    output: Path = typer.Option(..., "--output", help="Split JSON, e.g. data/manifests/open_vs_close_split.json."),
    holdout_fraction: float = number_option(
        _DEFAULTS.holdout_fraction, "--holdout-fraction", min=0.0, max=0.99,
        help="Share of each task's episodes held out of slicing for the evaluation (at least one; 0: none).",
    ),
) -> None:
    """Split each task's episodes into training (sliced) and held-out (evaluated) ones; pass it to `slice --split`."""
    with input_errors():
        check_no_overwrite({"--output": output}, {"--manifest": manifest})
        split = split_episodes(read_manifest(manifest), holdout_fraction, where=str(manifest))
        write_split(split, output)
    for task, sides in split.tasks.items():
        typer.echo(f"{task}: train {list(sides.train)}, held out {list(sides.holdout)}")


def _parse_floats(value: str) -> tuple[float, ...]:
    try:
        return tuple(float(part) for part in value.replace(",", " ").split())
    except ValueError:
        raise typer.BadParameter(f"{value!r} is not a list of numbers like -4,-2,0,2,4", param_hint="--alphas") from None


# EvaluateSettings' options where a field's own flag or type does not fit the command line
EVALUATE_FLAGS = {
    "alphas": Flag("--alphas", str | None, _parse_floats, "α grid in units of the mean residual norm / ||d||, with 0 "
                   f"(default {','.join(f'{a:g}' for a in _DEFAULTS.alphas)})."),
    "compiled": Flag("--compiled/--eager", bool | None),
    "methods": names_flag("methods", "Direction methods to evaluate, comma-separated (default: every one phase 3 "
                          "wrote)."),
    "modes": names_flag("modes", "Strength modes, comma-separated: add, clamp (default both)."),
}


@app.command("evaluate")
@model_options()
@settings_options(EvaluateSettings, "overrides", flags=EVALUATE_FLAGS, skip=("holdout_fraction",), optional=True)
def evaluate_command(
    ctx: typer.Context,
    config: Path | None = typer.Option(
        None, "--config", help="Run config (YAML): evaluate its pairs and layers with its model, SAE and evaluate "
        "settings (the evaluation flags then override the evaluate section; model and path flags are not allowed)."),
    pairs_config: Path | None = typer.Option(None, "--pairs-config", help="Pairs JSON, e.g. data/latent_steering/layer12_pairs.json."),
    layer: int | None = typer.Option(None, "--layer", min=0, help="Decoder layer of the vectors (--config: one of its layers)."),
    pair: list[str] = typer.Option([], "--pair", help="Evaluate only this pair (repeatable; default all)."),
    data_root: Path = typer.Option(Path("data"), "--data-root", help="The seed's data/ folder: manifests/<pair>.json, "
                                   "<pair>_concept_map.json and <pair>_split.json."),
    steering_root: Path | None = typer.Option(None, "--steering-root", help=f"Phase 3 outputs (default <data-root>/{STEERING_ROOT})."),
    output_root: Path | None = typer.Option(None, "--output-root", help=f"Outputs (default <data-root>/{STEERING_EVAL_ROOT})."),
    lerobot_root: Path | None = typer.Option(None, "--lerobot-root", help="LeRobot dataset the frames come from."),
    repo_id: str | None = typer.Option(None, "--repo-id", help="Dataset repo id (default: the dataset folder name)."),
    decision_run: Path | None = typer.Option(
        None, "--decision-run", help="Residual run of `capture --token-type decision` (the action expert's rows, same "
        "checkpoint): also evaluate each pair's expert direction at --expert-layers (sliced here, held-out episodes "
        "left out, into <data-root>/residuals/<pair>_decision_slices)."),
    expert_layers: str | None = typer.Option(
        None, "--expert-layers", help="Action-expert layers to evaluate, e.g. 9 or 3,9 (with --decision-run, or "
        "--config: some of its evaluate.expert_layers)."),
    paths_relative_to: PathsRelativeTo = typer.Option(
        _STEERING_FIELDS["paths_relative_to"].default, "--paths-relative-to",
        help=_STEERING_FIELDS["paths_relative_to"].description),
    model: ModelSpec | None = None,
    overrides: EvaluateSettings | None = None,
) -> None:
    """Dose-response of each pair's steering vectors on held-out frames: efficacy vs α, against random directions.

    Give --config, or --pairs-config, --layer, --lerobot-root, --checkpoint-path and --tokenizer-path
    (the split comes from `latent-steering split`, used by `slice --split`). The action expert: add
    --decision-run and --expert-layers (--layer and --pairs-config may then be left out: --pair names the
    pairs); with --config, its evaluate.expert_layers are evaluated too (--layer or --expert-layers alone
    select one pathway).
    """
    own = {name: ctx.params[name] for name in EvaluateOptions.__dataclass_fields__ if name in ctx.params}
    options = EvaluateOptions(**own, model=model, model_flags=_given_model_flags(ctx))
    expert = layer_list(expert_layers, "--expert-layers") if expert_layers is not None else None
    given = {} if overrides is None else overrides.model_dump(include=overrides.model_fields_set)
    with input_errors():
        plan = _config_plan if config is not None else _flags_plan
        _run(*plan(options, expert, given))


@dataclass(frozen=True)
class EvaluateOptions:
    """What `latent-steering evaluate` evaluates and where: its own options (the model's and the evaluation settings'
    come from `ModelSpec` and `EvaluateSettings`)."""

    config: Path | None
    pairs_config: Path | None
    layer: int | None
    pair: list[str]
    data_root: Path
    steering_root: Path | None
    output_root: Path | None
    lerobot_root: Path | None
    repo_id: str | None
    decision_run: Path | None
    paths_relative_to: PathsRelativeTo
    model: ModelSpec | None = None
    model_flags: tuple[str, ...] = ()  # the model options given (refused beside --config)


def _given_model_flags(ctx: typer.Context) -> tuple[str, ...]:
    """Return the flags of the ModelSpec options given on the command line."""
    return tuple(param.opts[0] for param in ctx.command.params
                 if param.name in ModelSpec.model_fields and ctx.get_parameter_source(param.name).name != "DEFAULT")


Plan = tuple[list[EvaluateJob], CaptureSettings, EvaluateSettings]


def _config_plan(options: EvaluateOptions, expert: list[int] | None, overrides: dict) -> Plan:
    """Return the jobs of a run config: its pairs (or --pair) at its layers and expert layers (or --layer,
    --expert-layers), with its model and evaluate settings."""
    path_flags = {"--pairs-config": options.pairs_config, "--lerobot-root": options.lerobot_root,
                  "--steering-root": options.steering_root, "--output-root": options.output_root,
                  "--decision-run": options.decision_run}
    if given := [flag for flag, value in path_flags.items() if value is not None] + list(options.model_flags):
        raise typer.BadParameter(f"{', '.join(given)} cannot be combined with --config", param_hint="--config")
    run = load_run_config(options.config)
    if stray := sorted(set(expert or ()) - set(run.expert_layers)):
        raise typer.BadParameter(f"{stray}: the run config's evaluate.expert_layers are {list(run.expert_layers)}",
                                 param_hint="--expert-layers")
    layer = options.layer
    layers = [layer] if layer is not None else [] if expert is not None else list(run.layers)
    expert = expert if expert is not None else [] if layer is not None else run.expert_layers
    names = options.pair or [p.name for p in run.pairs]
    jobs = [run_config_job(run, name, lay) for lay in layers for name in names]
    jobs += [run_config_job(run, name, lay, "expert") for lay in expert for name in names]
    settings = EvaluateSettings(**(run.evaluate_settings().model_dump() | overrides))
    _check_work(settings, run.model.action_horizon or DEFAULT_HORIZON)
    return jobs, run.capture_settings(), settings


def _flags_plan(options: EvaluateOptions, expert: list[int] | None, overrides: dict) -> Plan:
    """Return the jobs the path flags describe: a pairs config's pairs at --layer, and/or the expert directions
    of a --decision-run at --expert-layers."""
    _require_flags(options, expert)
    settings = EvaluateSettings(**overrides)
    _check_work(settings, options.model.action_horizon or DEFAULT_HORIZON)
    layer, data_root, lerobot_root = options.layer, options.data_root, options.lerobot_root
    model = CaptureSettings(model=options.model, layers=(layer,) if layer is not None else expert)
    names = [check_name(name, "--pair") for name in options.pair] or [
        p.name for p in read_pairs_config(options.pairs_config).pairs]
    places = dict(data_root=data_root, dataset_root=lerobot_root, repo_id=options.repo_id or lerobot_root.name,
                  output_root=options.output_root or data_root / STEERING_EVAL_ROOT)
    check_no_overwrite({"--output-root": places["output_root"]}, {
        "--pairs-config": options.pairs_config, "--steering-root": options.steering_root or data_root / STEERING_ROOT,
        "--lerobot-root": lerobot_root, "--decision-run": options.decision_run, **model_inputs(options.model)})
    jobs = _layer_jobs(options, names, places) if layer is not None else []
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
    needed = {"--lerobot-root": options.lerobot_root, "--checkpoint-path": options.model,
              "--tokenizer-path": options.model and options.model.tokenizer}
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


def _layer_jobs(options: EvaluateOptions, names: list[str], places: dict) -> list[EvaluateJob]:
    """Return the language-model jobs of each named pair of --pairs-config at --layer."""
    steering_root = options.steering_root or options.data_root / STEERING_ROOT
    return [pair_job(options.pairs_config, name, options.layer, relative_to=options.paths_relative_to,
                     steering_root=steering_root, **places) for name in names]


def _expert_jobs(decision_run: Path, expert: list[int], names: list[str], places: dict, model: CaptureSettings,
                 settings: EvaluateSettings) -> list:
    """Return the expert jobs of each named pair: its decision slices cut here (held-out episodes left out)."""
    for layer in expert:
        check_model(model, layer, "expert")
    check_decision_run(decision_run, expert, model, settings.num_steps)  # before anything is written
    slices = {name: slice_decision_run(decision_run, name, expert, data_root=places["data_root"]) for name in names}
    return [expert_job(name, layer, slices_root=slices[name], **places) for layer in expert for name in names]


def _run(jobs: list[EvaluateJob], model: CaptureSettings, settings: EvaluateSettings) -> None:
    """Evaluate every job (one policy for all), then write each layer's summary (and, with both pathways,
    the pathways table)."""
    layers: dict[Path, list[str]] = {}
    for job in jobs:
        folder = evaluate_job(job, model, settings)
        typer.echo(f"{job.pair} {job.label}: {folder}")
        layers.setdefault(folder.parent, []).append(job.pair)
    for layer_path, names in layers.items():
        typer.echo(f"summary: {write_layer_summary(layer_path, names)}")
    if not jobs:
        typer.echo(f"nothing to evaluate; see {SUMMARY_MD} files under the output root")
    elif any(job.stream == "expert" for job in jobs):
        evaluated = list(dict.fromkeys((job.layer, job.stream) for job in jobs))
        names = list(dict.fromkeys(job.pair for job in jobs))
        typer.echo(f"pathways: {write_pathways(jobs[0].output_dir.parent.parent, evaluated, names)}")
