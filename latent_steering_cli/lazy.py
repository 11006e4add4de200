"""Commands found without importing them: each `latent_steering_cli/<module>.py` is imported only when its command runs.

A command module imports what its commands need (torch, lerobot, Prefect: 5-15 s); `latent-steering
--help` and the light commands (`filter`, `manifest`, ...) must not pay for the others. The command
list and each command's help line are read from the modules' source (`@app.command("name")` and the
function's docstring) with `ast`, which takes milliseconds.
"""

from __future__ import annotations

import ast
import contextvars
import functools
import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import typer.main
from typer.core import TyperCommand, TyperGroup

CLI_DIR = Path(__file__).resolve().parent
_NOT_COMMANDS = {"__init__", "app", "lazy"}
# parameter name -> its first flag (`image_size` -> `--image-size`) of the command being run, for error messages
current_options: contextvars.ContextVar[dict[str, str]] = contextvars.ContextVar("current_options")


@dataclass(frozen=True)
class CommandSource:
    """Where a command is defined and its docstring, as read from the source."""

    name: str
    module: str
    help: str


@functools.cache
def command_sources() -> dict[str, CommandSource]:
    """Return command name -> its module and docstring, for every `@app.command` in latent_steering_cli/*.py, in file order."""
    found: dict[str, CommandSource] = {}
    for path in sorted(CLI_DIR.glob("*.py")):
        if path.stem in _NOT_COMMANDS:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in tree.body:
            if not isinstance(node, ast.FunctionDef):
                continue
            for decorator in node.decorator_list:
                name = _command_name(decorator, node.name)
                if name is not None:
                    found[name] = CommandSource(name, f"latent_steering_cli.{path.stem}", ast.get_docstring(node) or "")
    return found


def _command_name(decorator: ast.expr, function: str) -> str | None:
    """Return the command name of an `@app.command(...)` decorator, or None for any other decorator."""
    if not (isinstance(decorator, ast.Call) and isinstance(decorator.func, ast.Attribute)
            and decorator.func.attr == "command" and isinstance(decorator.func.value, ast.Name)
            and decorator.func.value.id == "app"):
        return None
    if decorator.args and isinstance(decorator.args[0], ast.Constant):
        return str(decorator.args[0].value)
    return function.replace("_", "-")  # typer's default name


class LazyCommands(TyperGroup):
    """A typer group whose commands are imported on first use; help listings use their docstrings only."""

    def list_commands(self, ctx: Any) -> list[str]:
        return [*command_sources(), *(name for name in self.commands if name not in command_sources())]

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        """Return the command, or a stand-in carrying its help when its module is not imported yet."""
        if cmd_name in self.commands or cmd_name not in command_sources():
            return self.commands.get(cmd_name)
        return TyperCommand(cmd_name, help=command_sources()[cmd_name].help)

    def resolve_command(self, ctx: Any, args: list[str]) -> tuple[str | None, Any, list[str]]:
        """Import the named command's module before its options are parsed; note its flags for error messages."""
        if args and args[0] in command_sources() and args[0] not in self.commands:
            self.commands[args[0]] = load_command(args[0])
        name, command, rest = super().resolve_command(ctx, args)
        if command is not None:
            current_options.set({p.name: p.opts[0] for p in command.params if getattr(p, "opts", None)})
        return name, command, rest


def load_command(name: str) -> Any:
    """Import the module defining `name` and return its (typer's) click command."""
    from latent_steering_cli.app import app

    importlib.import_module(command_sources()[name].module)
    info = next(info for info in app.registered_commands
                if (info.name or info.callback.__name__.replace("_", "-")) == name)
    return typer.main.get_command_from_info(
        info, pretty_exceptions_short=app.pretty_exceptions_short, rich_markup_mode=app.rich_markup_mode
    )
