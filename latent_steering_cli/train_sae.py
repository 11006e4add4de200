"""`latent-steering train-sae`: an SAE trained on one layer of a residual run (SAELens's trainer), in SAELens's format."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from steering_core.sae.training.rows import RowSource
from steering_core.sae.training.settings import Architecture, Normalization, TrainSettings
from steering_core.sae.training.trainer import train_sae

_DEFAULTS = TrainSettings()


@app.command("train-sae")
def train_sae_command(
    run_dir: Path = typer.Option(..., "--run-dir", help="Residual run folder written by `capture` (data/residuals/<run>)."),
    layer: int = typer.Option(..., "--layer", min=0, help="Decoder layer whose rows the SAE learns."),
    output_dir: Path = typer.Option(..., "--output-dir", help="The SAE folder: cfg.json + sae_weights.safetensors."),
    exclude_episodes: list[int] = typer.Option(
        [], "--exclude-episode", help="Episode kept out of training (repeat the option), e.g. the held-out ones."),
    architecture: Architecture = typer.Option(_DEFAULTS.architecture, "--architecture", help="SAELens architecture."),
    d_sae: int = typer.Option(_DEFAULTS.d_sae, "--d-sae", help="Latent count."),
    k: int = typer.Option(_DEFAULTS.k, "--k", help="Active latents per row (topk, batchtopk)."),
    sparsity_coefficient: float = typer.Option(_DEFAULTS.sparsity_coefficient, "--sparsity-coefficient",
                                               help="L0 (jumprelu) or L1 (standard) loss coefficient."),
    lr: float = typer.Option(_DEFAULTS.lr, "--lr", help="Adam learning rate."),
    batch_size: int = typer.Option(_DEFAULTS.batch_size, "--batch-size", help="Rows per training step."),
    training_rows: int = typer.Option(_DEFAULTS.training_rows, "--training-rows",
                                      help="Rows seen in all (the run's rows repeat in new orders when fewer)."),
    normalize: Normalization = typer.Option(_DEFAULTS.normalize, "--normalize",
                                            help="Input normalisation, folded into the weights at the end."),
    norm_estimate_batches: int = typer.Option(_DEFAULTS.norm_estimate_batches, "--norm-estimate-batches",
                                              help="Batches that estimate the normalisation factor."),
    buffer_rows: int = typer.Option(_DEFAULTS.buffer_rows, "--buffer-rows",
                                    help="Rows held in the shuffle buffer (bounds memory whatever the run's size)."),
    seed: int = typer.Option(_DEFAULTS.seed, "--seed", help="Initialisation and shuffling seed."),
    checkpoints: int = typer.Option(_DEFAULTS.checkpoints, "--checkpoints",
                                    help="Checkpoints during training; a rerun resumes from the latest."),
    dead_feature_window: int = typer.Option(_DEFAULTS.dead_feature_window, "--dead-feature-window",
                                            help="Steps without firing before a latent counts as dead."),
    feature_sampling_window: int = typer.Option(_DEFAULTS.feature_sampling_window, "--feature-sampling-window",
                                                help="Steps over which firing frequency is counted."),
    device: str = typer.Option(_DEFAULTS.device, "--device", help="auto (CUDA when available), cuda, cuda:1 or cpu."),
) -> None:
    """Train an SAE on a layer's captured residuals (resumable) and save it in SAELens's format."""
    with input_errors():
        settings = TrainSettings(architecture=architecture, d_sae=d_sae, k=k, sparsity_coefficient=sparsity_coefficient,
                                 lr=lr, batch_size=batch_size, training_rows=training_rows, normalize=normalize,
                                 norm_estimate_batches=norm_estimate_batches, buffer_rows=buffer_rows, seed=seed,
                                 checkpoints=checkpoints, dead_feature_window=dead_feature_window,
                                 feature_sampling_window=feature_sampling_window, device=device)
        source = RowSource(run_dir, layer, exclude=exclude_episodes)
        folder = train_sae(source, output_dir, settings, layer=layer)
    typer.echo(f"SAE of layer {layer} trained on {source.rows} rows: {folder}")
