"""Float options: finite numbers only, for every command (light: no library imported)."""

from __future__ import annotations

import math
from typing import Any

import typer


class FiniteNumber:
    """The parser of every float option: a finite number (never NaN or ±inf, which typer's float takes and every
    range check lets through, since each comparison with NaN is false) within [low, high]."""

    def __init__(self, low: float | None = None, high: float | None = None):
        self.low, self.high = low, high

    def __call__(self, value: Any) -> float:
        number = float(value)
        if not math.isfinite(number) or (self.low is not None and number < self.low) or \
                (self.high is not None and number > self.high):
            raise ValueError(f"{value!r}: expected a finite number{self.bounds()}")
        return number

    def bounds(self) -> str:
        """Return the range in words: ` from 0 to 1`, ` of at least 90`, or nothing."""
        if self.low is not None and self.high is not None:
            return f" from {self.low:g} to {self.high:g}"
        if self.low is not None or self.high is not None:
            return f" of at least {self.low:g}" if self.low is not None else f" of at most {self.high:g}"
        return ""


def number_option(default: float | None, flag: str, *, min: float | None = None, max: float | None = None,
                  help: str) -> Any:
    """Return a float option: a finite number within [min, max] (`FiniteNumber`)."""
    return typer.Option(default, flag, parser=FiniteNumber(min, max), help=help)
