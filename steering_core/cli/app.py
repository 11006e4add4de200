"""The `latent-steering` typer application; phase modules register their commands on it."""

from __future__ import annotations

import logging

import typer

app = typer.Typer(
    name="latent-steering",
    help="Concept steering vectors for pi0.5 from LIBERO demos (seed pipeline, productised).",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    """Set up logging for every subcommand."""
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
