"""Base for every settings model (unknown keys are errors, canonical hash) and the validated JSON reader."""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from steering_core.storage.fileio import read_json, sha256_json
from steering_core.storage.mirrors import portable


class StrictModel(BaseModel):
    """A pydantic model that forbids unknown keys and round-trips through JSON."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    def fingerprint(self) -> str:
        """Return the sha256 of this model's canonical JSON: part of a step's identity."""
        return sha256_json(portable(self.model_dump(mode="json")))  # paths in mirrors count by their URLs


M = TypeVar("M", bound=BaseModel)


def validation_problems(err: ValidationError) -> str:
    """Return every problem of a pydantic error on one line, each as `key.path: message`, `; `-separated.

    Problems that differ only in list positions (the same field of every shard of a run, say) share one
    line, the positions given as ranges: `shards.<0-39>.crc32 (40 entries): ...`.
    """
    groups: dict[tuple[tuple[Any, ...], str], list[tuple[int, ...]]] = {}
    for problem in err.errors():
        shape = tuple(None if isinstance(part, int) else part for part in problem["loc"])
        groups.setdefault((shape, problem["msg"]), []).append(
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
