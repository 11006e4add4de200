"""`latent-steering steer`: phase 3 of the seed pipeline (SAE latent means -> steering vectors)."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.options import device_option
from steering_core.layout import SUMMARY_MD
from steering_core.vectors.directions import PathsRelativeTo, SteeringSettings, compute_steering

_DEFAULTS = SteeringSettings(pairs_config=Path("."))
NO_SAE = "none"  # --sae value for residual-space directions only


@app.command("steer")
def steer_command(
    pairs_config: Path = typer.Option(..., "--pairs-config", help="Pairs JSON, e.g. data/latent_steering/layer12_pairs.json."),
    output_root: Path = typer.Option(_DEFAULTS.output_root, "--output-root", help="Outputs go to <output-root>/layerNN/."),
    layer: int = typer.Option(_DEFAULTS.layer, "--layer", min=0, help="Decoder layer the concept residuals come from."),
    device: str = device_option(_DEFAULTS.device),
    batch_size: int = typer.Option(_DEFAULTS.batch_size, "--batch-size", min=1, help="Rows encoded per SAE batch."),
    sae: str = typer.Option(
        _DEFAULTS.sae, "--sae",
        help=f"SAELens folder, .pt/.safetensors state dict, or release name; '{NO_SAE}': residual-space directions only.",
    ),
    sae_id: str | None = typer.Option(None, "--sae-id", help="SAE within the release (default blocks.<layer>.hook_resid_post)."),
    sae_dir: Path | None = typer.Option(
        None, "--sae-dir", help="Folder holding downloaded release folders, searched before the Hugging Face cache."
    ),
    sae_cfg_from: str | None = typer.Option(
        None, "--sae-cfg-from", help="For a state-dict --sae: folder or release whose cfg.json applies (as the seed did)."
    ),
    include_decoder_bias: bool = typer.Option(
        False, "--include-decoder-bias",
        help="Seed compatibility: residual_direction = decode(delta) = delta @ W_dec + b_dec (default: without b_dec).",
    ),
    top_k: int = typer.Option(_DEFAULTS.top_k, "--top-k", min=1, help="Latents listed per direction in the report."),
    paths_relative_to: PathsRelativeTo = typer.Option(
        _DEFAULTS.paths_relative_to, "--paths-relative-to",
        help="Base of relative concept paths: auto (the current directory when the file exists there, as the seed's "
        "pairs files expect, else the pairs file's folder, as the pipeline writes them), cwd or config.",
    ),
    save_pairwise_stats: bool = typer.Option(
        True, "--save-pairwise-stats", hidden=True,
        help="The seed's flag, accepted: pairwise_stats.pt/.json are always written (the report reads them).",
    ),
) -> None:
    """Encode concept residuals with the SAE and write latent means, directions, pairwise stats and a report."""
    with input_errors():
        settings = SteeringSettings(
            pairs_config=pairs_config,
            output_root=output_root,
            layer=layer,
            sae=None if sae.lower() == NO_SAE else sae,
            sae_id=sae_id,
            sae_dir=sae_dir,
            sae_cfg_from=sae_cfg_from,
            device=device,
            batch_size=batch_size,
            include_decoder_bias=include_decoder_bias,
            top_k=top_k,
            paths_relative_to=paths_relative_to,
        )
        layer_path = compute_steering(settings)
    typer.echo(f"steering vectors in {layer_path}; report: {layer_path / SUMMARY_MD}")
