"""Base for every settings model: unknown keys are errors, and a model hashes canonically."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from steering_core.fileio import sha256_json


class StrictModel(BaseModel):
    """A pydantic model that forbids unknown keys and round-trips through JSON."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    def fingerprint(self) -> str:
        """Return the sha256 of this model's canonical JSON: part of a step's identity."""
        return sha256_json(self.model_dump(mode="json"))
