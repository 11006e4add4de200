"""The `latent-steering` typer application; phase modules register their commands on it."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

import typer
from pydantic import ValidationError

from cli.lazy import LazyCommands, current_options

app = typer.Typer(
    cls=LazyCommands,
    name="latent-steering",
    help="Concept steering vectors for pi0.5 from LIBERO demos (seed pipeline, productised).",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)

# Libraries that log every HTTP call or server event at INFO: shown only with --verbose.
# (`httpx` alone prints Prefect's csrf-token probe as "422 Unprocessable Entity", which is harmless.)
NOISY_LOGGERS = ("httpx", "httpcore", "urllib3", "uvicorn", "uvicorn.access", "uvicorn.error", "alembic",
                 "aiosqlite", "asyncio", "fsspec", "datasets", "huggingface_hub", "filelock", "matplotlib", "PIL")


class RunNameFormatter(logging.Formatter):
    """Log format that names the Prefect task or flow run a record comes from, e.g. `[slice on_vs_off layer 2]`."""

    def format(self, record: logging.LogRecord) -> str:
        run = getattr(record, "task_run_name", None) or getattr(record, "flow_run_name", None)
        record.run = f" [{run}]" if run else ""
        return super().format(record)


@app.callback()
def main(verbose: bool = typer.Option(
    False, "--verbose", "-v", help="Log debug messages, and the INFO lines of libraries (HTTP calls, server)."
)) -> None:
    """Set up logging for every subcommand."""
    configure_logging(verbose)


def configure_logging(verbose: bool) -> None:
    """Log to stderr with times and run names; library chatter only when `verbose`."""
    handler = logging.StreamHandler()
    handler.setFormatter(RunNameFormatter("%(asctime)s %(levelname)s %(name)s%(run)s: %(message)s", datefmt="%H:%M:%S"))
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[handler])  # no-op under pytest
    for name in NOISY_LOGGERS:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose else logging.WARNING)


def option_problems(err: ValidationError) -> str:
    """Return a settings validation error as one sentence naming the command-line option of each bad field."""
    params = current_options.get()
    problems = []
    for error in err.errors(include_url=False):
        field = str(error["loc"][0]) if error["loc"] else ""
        where = params.get(field, field.replace("_", " ") or err.title)
        message = error["msg"].removeprefix("Value error, ")
        problems.append(f"{where} {error['input']!r}: {message[:1].lower()}{message[1:]}"
                        if error["type"] != "missing" else f"{where}: {message[:1].lower()}{message[1:]}")
    return "; ".join(problems)


@contextlib.contextmanager
def input_errors(*extra: type[Exception]) -> Iterator[None]:
    """Turn the library's bad-input errors into one `error: ...` line and exit code 1, not a traceback.

    Usage errors (unknown flags, unparsable values) stay typer's own, with exit code 2.
    """
    try:
        yield
    except ValidationError as err:  # settings built from the options: name the option, no pydantic dump
        typer.secho(f"error: {option_problems(err)}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1) from None
    except (ValueError, FileNotFoundError, FileExistsError, *extra) as err:
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1) from None
