"""The `latent-steering` typer application; phase modules register their commands on it."""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, get_args

import typer
from pydantic import ValidationError
from typer.core import TyperGroup

from latent_steering_cli.interrupts import held_back, interruptible
from latent_steering_cli.lazy import LazyCommands, current_options
from steering_core.storage.mirrors import is_url, portable
from steering_core.storage.os_limits import machine_error_line

# Options holding one string that lists several values (e.g. `--layers "12 14"`); the seed passes them
# space-separated as separate words, which are joined back into that one value.
JOINED_LIST_OPTIONS = ("--layers",)
_MOUNTED = "latent_steering.mounted"  # context key: the mirror paths of URL options, as they were before the command


def seed_spellings(command: Any, args: Sequence[str]) -> list[str]:
    """Return `args` with the seed's spellings rewritten to this command's: `--repo_id` -> `--repo-id`, and
    space-separated list values (`--layers 12 14`, `--task-a-episodes 3 4`) -> one value / repeated options.

    Only names the command knows are rewritten; a lone `--` ends the rewriting.
    """
    # typer ships its own click, so options are recognised by their type name, not their class
    options = {name: param for param in command.params if param.param_type_name == "option"
               for name in (*param.opts, *param.secondary_opts)}
    out: list[str] = []
    open_list: str | None = None  # the list option whose value(s) were just read
    awaiting: Any = None  # the option whose value is the next word
    for position, word in enumerate(args):
        if word == "--":
            return out + list(args[position:])
        if awaiting is not None:
            out.append(word)
            name = out[-2]
            open_list = name if awaiting.multiple or name in JOINED_LIST_OPTIONS else None
            awaiting = None
            continue
        if word.startswith("-"):
            name, equals, value = word.partition("=")
            if name not in options and name.replace("_", "-") in options:
                name = name.replace("_", "-")
            out.append(name + equals + value)
            param = options.get(name)
            awaiting = param if param is not None and not param.is_flag and not equals else None
            open_list = None
        elif open_list is not None:  # another value of a space-separated list
            if open_list in JOINED_LIST_OPTIONS:
                out[-1] = f"{out[-1]} {word}"
            else:
                out += [open_list, word]
        else:
            out.append(word)
    return out


def path_options(command: Any) -> set[str]:
    """Return the flags of `command`'s options that take a path (or a list or optional of one)."""
    return {name for param in command.params if _holds_path(getattr(param, "type_descriptor", None))
            for name in param.opts}


def _holds_path(descriptor: Any) -> bool:
    """Return whether an option's type annotation is a Path (or a list or optional of one)."""
    def paths_in(annotation: Any) -> bool:
        return annotation is Path or any(paths_in(arg) for arg in get_args(annotation))
    return descriptor is not None and paths_in(descriptor.annotation)


class SeedSpellingGroup(TyperGroup):
    """Command group that accepts the seed scripts' flag spellings (see `seed_spellings`) for every subcommand,
    and URLs (`s3://...`, `gs://...`) for its path options (`latent_steering_cli.storage`): mounted and pulled
    before the command, what it changed there published after it."""

    def resolve_command(self, ctx: Any, args: list[str]) -> tuple[str | None, Any, list[str]]:
        name, command, rest = super().resolve_command(ctx, args)
        if command is None:
            return name, command, rest
        rest = seed_spellings(command, rest)
        if any(is_url(word.partition("=")[2] or word) for word in rest):
            from latent_steering_cli.storage import mount_urls, snapshot

            with input_errors(OSError):
                rest, mounted = mount_urls(path_options(command), rest)
            ctx.meta[_MOUNTED] = snapshot(mounted)
        return name, command, rest

    def invoke(self, ctx: Any) -> Any:
        with interruptible(lambda: f"latent-steering {ctx.invoked_subcommand}"), machine_errors():
            result = super().invoke(ctx)
        if ctx.meta.get(_MOUNTED):
            from latent_steering_cli.storage import publish_changed

            with input_errors(OSError):
                publish_changed(ctx.meta[_MOUNTED])
        return result


class Commands(SeedSpellingGroup, LazyCommands):
    """The command group: commands imported on first use (`latent_steering_cli.lazy`), the seed's flag spellings accepted."""


app = typer.Typer(
    cls=Commands,
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
    """Set up logging for every subcommand; a write over the file-size limit raises (EFBIG), not kills."""
    configure_logging(verbose)
    ignore_file_size_signal()


def ignore_file_size_signal() -> None:
    """Ignore SIGXFSZ, so a write past `ulimit -f` fails with OSError EFBIG (`machine_errors` says it in one line)
    rather than killing the process with a core dump; child processes inherit it."""
    if hasattr(signal, "SIGXFSZ") and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)


def configure_logging(verbose: bool) -> None:
    """Log to stderr with times and run names; library chatter only when `verbose`."""
    handler = logging.StreamHandler()
    handler.setFormatter(RunNameFormatter("%(asctime)s %(levelname)s %(name)s%(run)s: %(message)s", datefmt="%H:%M:%S"))
    handler.addFilter(held_back)  # quiet once interrupted (`interrupts`)
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, handlers=[handler])  # no-op under pytest
    for name in NOISY_LOGGERS:
        logging.getLogger(name).setLevel(logging.DEBUG if verbose else logging.WARNING)


def option_problems(err: ValidationError) -> str:
    """Return a settings validation error as one sentence naming the command-line option of each bad field."""
    params = current_options.get({})
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
    except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError,
            *extra) as err:
        line = machine_error_line(err) or str(err)  # a permission refused: what to do
        typer.secho(f"error: {portable(line)}", fg=typer.colors.RED, err=True)  # mirror paths as their URLs
        raise typer.Exit(1) from None


@contextlib.contextmanager
def machine_errors() -> Iterator[None]:
    """Turn an error of the machine (full disk, name too long, memory, nesting: `machine_error_line`) met anywhere in a
    command into one `error: ...` line and exit code 1; any other error propagates."""
    try:
        yield
    except (OSError, MemoryError, RecursionError) as err:
        line = machine_error_line(err)
        if line is None:
            raise
        typer.secho(f"error: {portable(line)}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1) from None
