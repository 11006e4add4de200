"""Options defined once: those shared by several commands, and a command's options made from a settings model.

`settings_options(Model)` gives a command one option per field of `Model` (`--field-name`, the field's default,
its description as help) and hands them on as one validated `Model`, so a setting is written once, in the model;
`model_options()` does so for the pi0.5 model (`ModelSpec`), the same flags in every command that loads it.
"""

from __future__ import annotations

import functools
import inspect
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import typer
from pydantic import BaseModel

from latent_steering_cli.app import input_errors
from latent_steering_cli.numbers import FiniteNumber
from steering_core.devices import DEVICE_HELP
from steering_core.pi05.arch import read_arch
from steering_core.pi05.spec import ModelSpec


def _is_float(annotation: Any) -> bool:
    """Return whether an option's annotation is `float` or `float | None`."""
    return annotation is float or (isinstance(annotation, types.UnionType) and float in typing.get_args(annotation))


def device_option(default: str | None = "auto", help: str = DEVICE_HELP) -> Any:
    """Return the `--device` option (default `auto`, or None where the run's own setting decides)."""
    return typer.Option(default, "--device", help=help)


def flag(name: str) -> str:
    """Return the option flag of a settings field, e.g. `d_sae` -> `--d-sae`."""
    return "--" + name.replace("_", "-")


@dataclass(frozen=True)
class Flag:
    """How one settings field appears on the command line where its own name or type does not fit."""

    name: str                                    # the flag, e.g. --checkpoint-path for ModelSpec.checkpoint
    annotation: Any = None                       # the option's type when the field's is not one (a JSON file)
    parse: Callable[[Any], Any] | None = None    # the option's value -> the field's
    help: str | None = None                      # default: the field's description


def names(value: str | None) -> tuple[str, ...] | None:
    """Return a comma-separated option (`sae,probe`) as a tuple of names (None when not given)."""
    return None if value is None else tuple(part.strip() for part in value.split(",") if part.strip())


def names_flag(field: str, help_text: str) -> Flag:
    """Return the flag of a tuple-of-names field, given comma-separated on the command line."""
    return Flag(flag(field), str | None, names, help_text)


# ModelSpec's options, as every model command spells them; `--device` and `--dtype` stay the commands' own
MODEL_FLAGS = {
    "checkpoint": Flag("--checkpoint-path"),
    "tokenizer": Flag("--tokenizer-path"),
    "arch": Flag("--arch-file", Path | None, read_arch,
                 "JSON of Pi05Arch fields, for a checkpoint of non-standard (e.g. tiny) size."),
}
MODEL_SKIP = ("device", "dtype")


def settings_options(model: type[BaseModel], parameter: str = "settings",
                     parse: dict[str, Callable[[Any], Any]] | None = None, *, flags: dict[str, Flag] | None = None,
                     skip: tuple[str, ...] = (), optional: bool = False) -> Callable[[Callable], Callable]:
    """Decorate a command whose parameter `parameter` is a `model`: it takes one option per field of `model` instead
    (after its own parameters) and receives them as one `model`, validated (a bad value is an `error:` line).

    `parse` maps a field to what turns its option's value into the field's (e.g. `none` -> None); `flags` gives a
    field another flag, type or parse (`Flag`); `skip` leaves fields out (their defaults apply). With `optional`, every
    option defaults to None and the command receives None when none was given (it may take the model from elsewhere,
    e.g. a run config)."""
    hints = typing.get_type_hints(model)
    flags = flags or {}
    names = [name for name in model.model_fields if name not in skip]

    # None given for these means "not given": the field's default applies (an option of another type than its field
    # cannot show the field's default)
    unset_if_none = set(names) if optional else {name for name in names if name in flags and flags[name].annotation}

    def option(name: str) -> inspect.Parameter:
        field, given = model.model_fields[name], flags.get(name, Flag(flag(name)))
        default = None if name in unset_if_none else ... if field.is_required() else field.default
        annotation = given.annotation or (hints[name] | None if optional else hints[name])
        numeric = {"parser": FiniteNumber()} if _is_float(annotation) and not given.parse else {}
        return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=annotation,
                                 default=typer.Option(default, given.name, help=given.help or field.description,
                                                      **numeric))

    fields = [option(name) for name in names]
    parsers = {name: given.parse for name, given in flags.items() if given.parse} | (parse or {})

    def decorate(command: Callable) -> Callable:
        command_hints = typing.get_type_hints(command)
        own = [p.replace(annotation=command_hints[p.name]) for p in inspect.signature(command).parameters.values()
               if p.name != parameter]

        @functools.wraps(command)
        def run(**options: Any) -> Any:
            values = {name: options.pop(name) for name in names}
            if optional and all(value is None for value in values.values()):
                return command(**options, **{parameter: None})
            if missing := [flags.get(name, Flag(flag(name))).name for name in names
                           if model.model_fields[name].is_required() and values[name] is None]:
                raise typer.BadParameter(f"{', '.join(missing)} required", param_hint=missing[0])
            with input_errors():
                settings = model(**{name: parsers.get(name, lambda value: value)(value) for name, value in values.items()
                                    if not (value is None and name in unset_if_none)})
            return command(**options, **{parameter: settings})

        del run.__wrapped__  # typer reads the signature below, not the command's
        run.__signature__ = inspect.Signature([*own, *fields])
        run.__annotations__ = {p.name: p.annotation for p in [*own, *fields]}
        return run

    return decorate


def model_inputs(model: ModelSpec | None) -> dict[str, Path | None]:
    """Return the files the model options name, by their flags (the inputs an output must keep apart from)."""
    if model is None:
        return {}
    return {MODEL_FLAGS["checkpoint"].name: model.checkpoint, MODEL_FLAGS["tokenizer"].name: model.tokenizer,
            flag("norm_stats"): model.norm_stats}


def model_options(parameter: str = "model") -> Callable[[Callable], Callable]:
    """Decorate a command that takes the pi0.5 model: ModelSpec's options (`MODEL_FLAGS`), all optional, handed on
    as one `ModelSpec` (None when none was given)."""
    return settings_options(ModelSpec, parameter, flags=MODEL_FLAGS, skip=MODEL_SKIP, optional=True)
