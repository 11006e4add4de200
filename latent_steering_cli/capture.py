"""`latent-steering capture` and `latent-steering slice`: phase 2 of the seed pipeline."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.options import device_option, model_inputs, model_options
from steering_core.capture import CaptureResult, CaptureSettings, capture
from steering_core.capture.shards import StorageDtype, TokenType
from steering_core.capture.slicing import Reduce, SliceSettings, slice_concepts
from steering_core.config import load_run_config
from steering_core.data.split import read_split
from steering_core.pi05.spec import ModelSpec
from steering_core.storage.overwrites import check_no_overwrite

_CAPTURE_FIELDS = CaptureSettings.model_fields  # defaults live in the settings model only


def layer_list(value: str, flag: str = "--layers") -> tuple[int, ...]:
    """Return the layers of a comma- or space-separated list, e.g. `12` or `6,12`."""
    try:
        layers = tuple(int(part) for part in value.replace(",", " ").split())
    except ValueError:
        raise typer.BadParameter(f"{value!r} is not a list of layer numbers like 12 or 6,12", param_hint=flag) from None
    if not layers:
        raise typer.BadParameter("give at least one layer, e.g. 12", param_hint=flag)
    return layers


@app.command("capture")
@model_options()
def capture_command(
    ctx: typer.Context,
    config: Path | None = typer.Option(
        None, "--config", help="Run config (YAML): capture its dataset with its model and capture settings "
        "into its run folder, exactly as the pipeline does; the other flags are then not allowed."
    ),
    output_dir: Path | None = typer.Option(None, "--output-dir", help="Run folder, e.g. data/residuals/open_close_run."),
    lerobot_root: Path | None = typer.Option(
        None, "--lerobot-root", help="LeRobot dataset folder (v3.0, v2.1 or v2.0; read in place)."
    ),
    repo_id: str | None = typer.Option(None, "--repo-id", help="Dataset repo id (default: the dataset folder name)."),
    layers: str = typer.Option("12", "--layers", help="Decoder layers to capture in one pass, e.g. 12 or 6,12."),
    batch_size: int = typer.Option(
        _CAPTURE_FIELDS["batch_size"].default, "--batch-size", min=1, help="Frames per forward pass."
    ),
    capture_instructions: bool = typer.Option(
        False, "--capture-instructions", help="Keep the task-instruction tokens (the seed's flag)."
    ),
    token_type: TokenType | None = typer.Option(
        None, "--token-type",
        help="instructions (default), prompt (every valid token), last (last prompt token), decision (action "
        "expert residual at the last action token per denoising step; --layers are expert layers) or adarms "
        "(the expert's time conditioning per step).",
    ),
    num_steps: int = typer.Option(
        _CAPTURE_FIELDS["num_steps"].default, "--num-steps", min=1, help="decision/adarms: denoising steps."
    ),
    noise_seed: int = typer.Option(
        _CAPTURE_FIELDS["noise_seed"].default, "--noise-seed", min=0,
        help="decision: seed of each frame's fixed noise (with its global index).",
    ),
    skip_norm_stats: bool = typer.Option(
        False, "--skip-norm-stats", help="Never read norm stats (the libero format needs none)."
    ),
    device: str | None = device_option(None),
    dtype: str | None = typer.Option(
        None, "--dtype", help="Compute dtype (default: openpi's bfloat16 policy on CUDA, float32 on CPU)."
    ),
    storage_dtype: StorageDtype = typer.Option(
        _CAPTURE_FIELDS["storage_dtype"].default, "--storage-dtype", help="Dtype of stored rows (bfloat16/float16 halve the disk)."
    ),
    episodes_per_shard: int = typer.Option(
        _CAPTURE_FIELDS["episodes_per_shard"].default, "--episodes-per-shard", min=1, help="Episodes per shard file."
    ),
    num_workers: int | None = typer.Option(
        _CAPTURE_FIELDS["num_workers"].default, "--num-workers", min=0,
        help="DataLoader processes decoding frames (default: one per usable core less one, at most 8).",
    ),
    video_backend: str | None = typer.Option(
        None, "--video-backend", help="lerobot video decoder for video datasets, e.g. pyav (default: lerobot's)."
    ),
    max_samples_per_layer: int | None = typer.Option(
        None, "--max-samples-per-layer", min=1,
        help="The seed's cap: capture only the first episodes until they hold N frames (whole episode groups).",
    ),
    model: ModelSpec | None = None,
) -> None:
    """Capture pi0.5 residuals of every dataset frame at the given layers into resumable shards.

    Give either --config, or --checkpoint-path, --tokenizer-path, --lerobot-root and --output-dir.
    """
    if config is not None:
        _capture_from_config(ctx, config)
    else:
        fields = {name: ctx.params[name] for name in _CAPTURE_FIELDS if name in ctx.params
                  and name not in ("layers", "token_type")}
        _capture_from_flags(model=model, lerobot_root=lerobot_root, output_dir=output_dir, repo_id=repo_id,
                            layers=layers, capture_instructions=capture_instructions, token_type=token_type,
                            max_samples_per_layer=max_samples_per_layer, **fields)


def _capture_from_flags(
    *, model: ModelSpec | None, lerobot_root: Path | None, output_dir: Path | None, repo_id: str | None, layers: str,
    capture_instructions: bool, token_type: TokenType | None, max_samples_per_layer: int | None, **fields,
) -> None:
    """Run the capture the flags describe; `fields` are the flags named as CaptureSettings fields."""
    missing = [flag for flag, value in (("--checkpoint-path", model), ("--tokenizer-path", model and model.tokenizer),
                                        ("--lerobot-root", lerobot_root), ("--output-dir", output_dir))
               if value is None]
    if missing:
        raise typer.BadParameter(f"{', '.join(missing)} required (or give --config)", param_hint=missing[0])
    if capture_instructions and token_type not in (None, "instructions"):
        raise typer.BadParameter(f"--capture-instructions contradicts --token-type {token_type}; pass one of them",
                                 param_hint="--capture-instructions")
    with input_errors():
        check_no_overwrite({"--output-dir": output_dir}, {"--lerobot-root": lerobot_root, **model_inputs(model)})
        settings = CaptureSettings(**fields, model=model, layers=layer_list(layers),
                                   token_type=token_type or "instructions")
        result = capture(lerobot_root, repo_id or lerobot_root.name, output_dir, settings,
                         max_frames=max_samples_per_layer)
    _echo_result(output_dir, result)


def _capture_from_config(ctx: typer.Context, config: Path) -> None:
    """Run the capture a run config describes; refuse other capture flags, which the config would contradict."""
    given = [param.opts[0] for param in ctx.command.params
             if param.name != "config" and ctx.get_parameter_source(param.name).name != "DEFAULT"]
    if given:
        raise typer.BadParameter(f"{', '.join(given)} cannot be combined with --config: set them in the run config",
                                 param_hint="--config")
    with input_errors():
        run = load_run_config(config)
        result = capture(run.dataset_root, run.repo_id, run.run_dir, run.capture_settings())
    _echo_result(run.run_dir, result)


def _echo_result(run_dir: Path, result: CaptureResult) -> None:
    typer.echo(
        f"{run_dir}: {len(result.written)} shard group(s) written, {len(result.skipped)} already complete, "
        f"{result.frames} frame(s) captured"
    )


@app.command("slice")
def slice_command(
    run_dir: Path = typer.Option(..., "--run-dir", help="Capture run folder (holds metadata.json)."),
    concept_map_path: Path = typer.Option(..., "--concept-map-path", help="Concept map JSON of the same dataset."),
    output_dir: Path = typer.Option(
        ..., "--output-dir", help="Slices folder, e.g. data/residuals/open_vs_close_slices."
    ),
    token_type: TokenType = typer.Option(
        "instructions", "--token-type", help="Token type the run captured."
    ),
    layers: str = typer.Option("12", "--layers", help="Layers to slice, e.g. 12 or 6,12."),
    device: str = typer.Option("cpu", "--device", help="Device for frame means (outputs are saved from CPU)."),
    reduce: Reduce = typer.Option(
        "token", "--reduce", help="One row per captured token, or their mean per frame."
    ),
    max_samples_per_concept: int | None = typer.Option(
        None, "--max-samples-per-concept", min=1, help="Keep at most N rows (or frames), evenly spaced."
    ),
    verify_checksums: bool = typer.Option(
        True, "--verify-checksums/--no-verify-checksums",
        help="Check every shard read against its recorded CRC-32 (sha256 for older runs); a damaged shard stops the slice.",
    ),
    split: Path | None = typer.Option(
        None, "--split", help="Held-out split JSON (manifests/<pair>_split.json): its held-out episodes are not sliced."
    ),
) -> None:
    """Write <output-dir>/layerNN/<concept>.pt (+ .safetensors, index.json) for each concept."""
    with input_errors():
        check_no_overwrite({"--output-dir": output_dir}, {"--run-dir": run_dir, "--concept-map-path": concept_map_path,
                                                          "--split": split})
        settings = SliceSettings(
            holdout_episodes=read_split(split).holdout_episodes if split is not None else (),
            layers=layer_list(layers),
            token_type=token_type,
            reduce=reduce,
            max_samples_per_concept=max_samples_per_concept,
            verify_checksums=verify_checksums,
            device=device,
        )
        written = slice_concepts(run_dir, concept_map_path, output_dir, settings)
    for layer, index in written.items():
        typer.echo(f"layer {layer}: {index}")
