"""The command list, and each command's module imported only when the command runs.

A command module imports what its commands need (torch, lerobot, Prefect: 5-15 s); `latent-steering
--help` and the light commands (`filter`, `manifest`, ...) must not pay for the others. So the command
list is written out here: to add a command, define it with `@app.command("name")` in a module of this
package and add its line to `COMMANDS` (`tests/test_cli.py` checks the two agree, summary included).
"""

from __future__ import annotations

import contextvars
import importlib
from dataclasses import dataclass
from typing import Any

import typer.main
from typer.core import TyperCommand, TyperGroup

# parameter name -> its first flag (`image_size` -> `--image-size`) of the command being run, for error messages
current_options: contextvars.ContextVar[dict[str, str]] = contextvars.ContextVar("current_options")


@dataclass(frozen=True)
class CommandSource:
    """Where a command is defined, and the summary `--help` lists for it (its docstring's first line)."""

    name: str
    module: str
    help: str


def _commands(*rows: tuple[str, str, str]) -> dict[str, CommandSource]:
    return {name: CommandSource(name, f"latent_steering_cli.{module}", summary) for name, module, summary in rows}


# every command, in `--help` order: (name, module in latent_steering_cli, its docstring's first line)
COMMANDS = _commands(
    ("filter", "prepare", "Select demo files by task text or file-name glob into a folder with selection.json."),
    ("convert", "prepare", "Convert LIBERO demos into a LeRobot dataset (openpi's physical-intelligence/libero schema)."),
    ("make-demos", "prepare", "Write synthetic LIBERO demos for two concept pairs (drawer open/close, stove on/off)."),
    ("manifest", "contrast",
     "Find the state axis two tasks move along in opposite directions and each demo's window on it."),
    ("concept-map", "contrast", "Map every manifest segment to its global dataset indices, grouped by concept."),
    ("split", "evaluate",
     "Split each task's episodes into training (sliced) and held-out (evaluated) ones; pass it to `slice --split`."),
    ("capture", "capture", "Capture pi0.5 residuals of every dataset frame at the given layers into resumable shards."),
    ("slice", "capture", "Write <output-dir>/layerNN/<concept>.pt (+ .safetensors, index.json) for each concept."),
    ("train-sae", "train_sae",
     "Train an SAE on a layer's captured residuals (resumable) and save it in SAELens's format."),
    ("steer", "steer",
     "Encode concept residuals with the SAE and write latent means, directions, pairwise stats and a report."),
    ("evaluate", "evaluate",
     "Dose-response of each pair's steering vectors on held-out frames: efficacy vs α, against random directions."),
    ("rollout", "rollout",
     "Run the steered policy in the LIBERO simulator per pair, layer, α and control; write rollouts/layerNN/."),
    ("serve", "serve", "Serve steered pi0.5 over openpi's websocket protocol until Ctrl-C or SIGTERM."),
    ("run", "run", "Run the whole pipeline (the `latent-steering` flow) in this process."),
    ("demo", "run",
     "Generate demos for two concept pairs, a tiny pi0.5, tokenizer and SAEs; run the whole flow; summarise."),
    ("deploy", "run",
     "Create the `gpu` and `cpu` work pools and the `gpu` concurrency limit, then deploy every flow."),
)


class LazyCommands(TyperGroup):
    """A typer group whose commands are imported on first use; help listings use their docstrings only."""

    def list_commands(self, ctx: Any) -> list[str]:
        return [*COMMANDS, *(name for name in self.commands if name not in COMMANDS)]

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        """Return the command, or a stand-in carrying its help when its module is not imported yet."""
        if cmd_name in self.commands or cmd_name not in COMMANDS:
            return self.commands.get(cmd_name)
        return TyperCommand(cmd_name, help=COMMANDS[cmd_name].help)

    def resolve_command(self, ctx: Any, args: list[str]) -> tuple[str | None, Any, list[str]]:
        """Import the named command's module before its options are parsed; note its flags for error messages."""
        if args and args[0] in COMMANDS and args[0] not in self.commands:
            self.commands[args[0]] = load_command(args[0])
        name, command, rest = super().resolve_command(ctx, args)
        if command is not None:
            current_options.set({p.name: p.opts[0] for p in command.params if getattr(p, "opts", None)})
        return name, command, rest


def load_command(name: str) -> Any:
    """Import the module defining `name` and return its (typer's) click command."""
    app = importlib.import_module(COMMANDS[name].module).app  # the shared app it registered on
    info = next(info for info in app.registered_commands
                if (info.name or info.callback.__name__.replace("_", "-")) == name)
    return typer.main.get_command_from_info(
        info, pretty_exceptions_short=app.pretty_exceptions_short, rich_markup_mode=app.rich_markup_mode
    )
