"""Options defined once: those shared by several commands, and a command's options made from a settings model.

`settings_options(Model)` gives a command one option per field of `Model` (`--field-name`, the field's default,
its description as help) and hands them on as one validated `Model`, so a setting is written once, in the model.
"""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from typing import Any

import typer
from pydantic import BaseModel

from latent_steering_cli.app import input_errors
from steering_core.devices import DEVICE_HELP


def device_option(default: str | None = "auto", help: str = DEVICE_HELP) -> Any:
    """Return the `--device` option (default `auto`, or None where the run's own setting decides)."""
    return typer.Option(default, "--device", help=help)


def flag(name: str) -> str:
    """Return the option flag of a settings field, e.g. `d_sae` -> `--d-sae`."""
    return "--" + name.replace("_", "-")


def settings_options(model: type[BaseModel], parameter: str = "settings",
                     parse: dict[str, Callable[[Any], Any]] | None = None) -> Callable[[Callable], Callable]:
    """Decorate a command whose parameter `parameter` is a `model`: it takes one option per field of `model` instead
    (after its own parameters) and receives them as one `model`, validated (a bad value is an `error:` line).
    `parse` maps a field to what turns its option's value into the field's (e.g. `none` -> None)."""
    hints = typing.get_type_hints(model)
    fields = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=hints[name],
                                default=typer.Option(... if field.is_required() else field.default, flag(name),
                                                     help=field.description))
              for name, field in model.model_fields.items()]

    def decorate(command: Callable) -> Callable:
        command_hints = typing.get_type_hints(command)
        own = [p.replace(annotation=command_hints[p.name]) for p in inspect.signature(command).parameters.values()
               if p.name != parameter]

        @functools.wraps(command)
        def run(**options: Any) -> Any:
            values = {name: (parse or {}).get(name, lambda value: value)(options.pop(name)) for name in model.model_fields}
            with input_errors():
                settings = model(**values)
            return command(**options, **{parameter: settings})

        del run.__wrapped__  # typer reads the signature below, not the command's
        run.__signature__ = inspect.Signature([*own, *fields])
        run.__annotations__ = {p.name: p.annotation for p in [*own, *fields]}
        return run

    return decorate
