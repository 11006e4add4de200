"""Base for every settings model (unknown keys and converted scalars are errors, canonical hash) and the validated
JSON reader."""

from __future__ import annotations

import os
import reprlib
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, GetCoreSchemaHandler, ValidationError
from pydantic_core import CoreSchema

from steering_core.storage.fileio import read_json, sha256_json
from steering_core.storage.mirrors import portable

# Scalars taken only as themselves: "1" or 1.0 is no int, 1 or "yes" no bool, "1.5" or true no float (an int is a
# float). Containers, paths and literals keep pydantic's conversions: YAML and JSON give lists for tuples, strings
# for paths, and strings for mapping keys (a dict[int, ...] written as JSON comes back keyed by "12").
STRICT_SCALARS = ("int", "bool", "float", "str")
SHORT = reprlib.Repr(maxstring=80, maxother=80, maxlist=4, maxtuple=4, maxdict=4, maxlevel=2)  # a found value in a line
_TYPE_ERRORS = ("int_type", "bool_type", "float_type", "string_type")  # a scalar of another type


def _strict_scalars(schema: Any) -> None:
    """Mark every int, bool, float and str of a pydantic core schema strict, except mapping keys, and every float
    finite (NaN and ±inf refused: a setting or a record holds real numbers), in place."""
    if isinstance(schema, dict):
        if schema.get("type") in STRICT_SCALARS:
            schema["strict"] = True
        if schema.get("type") == "float":
            schema["allow_inf_nan"] = False
        for key, value in schema.items():
            if key != "keys_schema":
                _strict_scalars(value)
    elif isinstance(schema, list):
        for item in schema:
            _strict_scalars(item)


class StrictModel(BaseModel):
    """A pydantic model that forbids unknown keys, takes scalars only of their own type and numbers only finite, and
    round-trips through JSON."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @classmethod
    def __get_pydantic_core_schema__(cls, source: type[BaseModel], handler: GetCoreSchemaHandler) -> CoreSchema:
        schema = handler(source)
        _strict_scalars(schema)
        return schema

    def fingerprint(self) -> str:
        """Return the sha256 of this model's canonical JSON: part of a step's identity."""
        return sha256_json(portable(self.model_dump(mode="json")))  # paths in mirrors count by their URLs


M = TypeVar("M", bound=BaseModel)


def error_message(error: Mapping[str, Any], *, value: bool = True) -> str:
    """Return a pydantic error's message, with what was found (the value and its type, or the type alone) when it
    was a scalar of another type."""
    if error["type"] not in _TYPE_ERRORS:
        return error["msg"]
    kind = type(error["input"]).__name__
    return f"{error['msg']}, found {SHORT.repr(error['input'])} ({kind})" if value else f"{error['msg']}, found a {kind}"


def validation_problems(err: ValidationError) -> str:
    """Return every problem of a pydantic error on one line, each as `key.path: message`, `; `-separated.

    Problems that differ only in list positions (the same field of every shard of a run, say) share one
    line, the positions given as ranges: `shards.<0-39>.crc32 (40 entries): ...`.
    """
    groups: dict[tuple[tuple[Any, ...], str], list[tuple[int, ...]]] = {}
    for problem in err.errors():
        shape = tuple(None if isinstance(part, int) else part for part in problem["loc"])
        groups.setdefault((shape, error_message(problem, value=False)), []).append(
            tuple(part for part in problem["loc"] if isinstance(part, int)))
    lines = []
    for (shape, message), positions in groups.items():
        columns = iter(zip(*positions))
        parts = [str(part) if part is not None else _positions(sorted(set(next(columns))), len(positions))
                 for part in shape]
        count = f" ({len(positions)} entries)" if len(positions) > 1 else ""
        lines.append(f"{'.'.join(parts) or '(top level)'}{count}: {message}")
    return "; ".join(lines)


def _positions(values: list[int], entries: int) -> str:
    """Return one list position as it is (one entry), or as `<ranges>` (several)."""
    return str(values[0]) if entries == 1 else f"<{describe_ranges(values)}>"


def describe_ranges(values: Sequence[int]) -> str:
    """Return sorted integers as compact ranges, e.g. `0-3, 7, 9-10`."""
    if not values:
        return "none"
    spans, start, prev = [], values[0], values[0]
    for value in list(values[1:]) + [None]:
        if value is not None and value == prev + 1:
            prev = value
            continue
        spans.append(f"{start}" if start == prev else f"{start}-{prev}")
        if value is not None:
            start = prev = value
    return ", ".join(spans)


def read_model(
    path: str | os.PathLike, model: type[M], *, what: str, fix: str = "", format_version: int | None = None
) -> M:
    """Return `model` validated from the JSON file at `path`.

    A wrong `format_version` (when one is expected) or invalid content raises one ValueError, one line, that
    names the file, says what it should be (`what`), lists every problem by key, and ends with `fix`.
    """
    payload = read_json(path)
    fix = f"; {fix}" if fix else ""
    if format_version is not None:
        found = payload.get("format_version") if isinstance(payload, dict) else None
        if found != format_version:
            raise ValueError(f"{path}: `format_version` is {found!r}, expected {format_version}{fix}")
    try:
        return model.model_validate(payload)
    except ValidationError as err:
        raise ValueError(f"{path}: not a valid {what}: {validation_problems(err)}{fix}") from None
