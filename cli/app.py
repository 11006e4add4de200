"""The `latent-steering` typer application; phase modules register their commands on it."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Sequence
from typing import Any

import typer
from typer.core import TyperGroup

# Options holding one string that lists several values (e.g. `--layers "12 14"`); the seed passes them
# space-separated as separate words, which are joined back into that one value.
JOINED_LIST_OPTIONS = ("--layers",)


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


class SeedSpellingGroup(TyperGroup):
    """Command group that accepts the seed scripts' flag spellings (see `seed_spellings`) for every subcommand."""

    def resolve_command(self, ctx: Any, args: list[str]) -> tuple[str | None, Any, list[str]]:
        name, command, rest = super().resolve_command(ctx, args)
        return name, command, seed_spellings(command, rest) if command is not None else rest


app = typer.Typer(
    cls=SeedSpellingGroup,
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
    except (ValueError, FileNotFoundError, FileExistsError, *extra) as err:
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(1) from None
