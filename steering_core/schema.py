"""Base for every settings model (unknown keys are errors, canonical hash) and the validated JSON reader."""

from __future__ import annotations

import os
from typing import TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from steering_core.fileio import read_json, sha256_json


class StrictModel(BaseModel):
    """A pydantic model that forbids unknown keys and round-trips through JSON."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    def fingerprint(self) -> str:
        """Return the sha256 of this model's canonical JSON: part of a step's identity."""
        return sha256_json(self.model_dump(mode="json"))


M = TypeVar("M", bound=BaseModel)


def validation_problems(err: ValidationError) -> str:
    """Return one line per problem of a pydantic error, each as `key.path: message`."""
    return "\n  ".join(f"{'.'.join(map(str, e['loc'])) or '(top level)'}: {e['msg']}" for e in err.errors())


def read_model(
    path: str | os.PathLike, model: type[M], *, what: str, fix: str = "", format_version: int | None = None
) -> M:
    """Return `model` validated from the JSON file at `path`.

    A wrong `format_version` (when one is expected) or invalid content raises one ValueError that
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
        raise ValueError(f"{path}: not a valid {what}{fix}:\n  {validation_problems(err)}") from None
