"""`latent-steering steer`: phase 3 of the seed pipeline (SAE latent means -> steering vectors)."""

from __future__ import annotations

from pathlib import Path

import typer

from latent_steering_cli.app import app, input_errors
from latent_steering_cli.options import names_flag, settings_options
from steering_core.layout import SUMMARY_MD
from steering_core.vectors.directions import SteeringSettings, compute_steering

NO_SAE = "none"  # --sae value for residual-space directions only


@app.command("steer")
@settings_options(SteeringSettings, parse={"sae": lambda sae: None if sae is None or sae.lower() == NO_SAE else sae},
                  flags={"methods": names_flag("methods", "Direction methods written per pair, comma-separated "
                                               "(steering_core.vectors.methods; default: sae, mean_difference, "
                                               "sae_top_k, probe, the SAE ones only with an SAE).")})
def steer_command(
    save_pairwise_stats: bool = typer.Option(
        True, "--save-pairwise-stats", hidden=True,
        help="The seed's flag, accepted: pairwise_stats.pt/.json are always written (the report reads them).",
    ),
    settings: SteeringSettings = SteeringSettings(pairs_config=Path(".")),
) -> None:
    """Encode concept residuals with the SAE and write latent means, directions, pairwise stats and a report."""
    with input_errors():
        layer_path = compute_steering(settings)
    typer.echo(f"steering vectors in {layer_path}; report: {layer_path / SUMMARY_MD}")
