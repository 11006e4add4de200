"""`latent-steering train-sae`: an SAE trained on one layer of a residual run (SAELens's trainer), in SAELens's format."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.options import settings_options
from steering_core.sae.training.rows import RowSource
from steering_core.sae.training.settings import TrainSettings
from steering_core.sae.training.trainer import train_sae
from steering_core.storage.overwrites import check_no_overwrite


@app.command("train-sae")
@settings_options(TrainSettings)
def train_sae_command(
    run_dir: Path = typer.Option(..., "--run-dir", help="Residual run folder written by `capture` (data/residuals/<run>)."),
    layer: int = typer.Option(..., "--layer", min=0, help="Decoder layer whose rows the SAE learns."),
    output_dir: Path = typer.Option(..., "--output-dir", help="The SAE folder: cfg.json + sae_weights.safetensors."),
    exclude_episodes: list[int] = typer.Option(
        [], "--exclude-episode", help="Episode kept out of training (repeat the option), e.g. the held-out ones."),
    settings: TrainSettings = TrainSettings(),
) -> None:
    """Train an SAE on a layer's captured residuals (resumable) and save it in SAELens's format."""
    with input_errors():
        check_no_overwrite({"--output-dir": output_dir}, {"--run-dir": run_dir})
        source = RowSource(run_dir, layer, exclude=exclude_episodes)
        folder = train_sae(source, output_dir, settings, layer=layer)
    typer.echo(f"SAE of layer {layer} trained on {source.rows} rows: {folder}")
