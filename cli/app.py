"""The `latent-steering` typer application; phase modules register their commands on it."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

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


@contextlib.contextmanager
def input_errors(*extra: type[Exception]) -> Iterator[None]:
    """Turn the library's bad-input errors into one `error: ...` line and exit code 1, not a traceback.

    Usage errors (unknown flags, unparsable values) stay typer's own, with exit code 2.
    """
    try:
        yield
    except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError,
            *extra) as err:
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1) from None
