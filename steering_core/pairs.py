"""A concept pair's two sides: `positive` (the pair's first task) and `negative` (its second).

A pair's direction is `positive - negative`, so α > 0 along it pushes toward the positive side.
"""

from __future__ import annotations

from typing import Literal

Side = Literal["positive", "negative"]
SIDES: tuple[Side, Side] = ("positive", "negative")


def other_side(side: str) -> Side:
    """Return the side that is not `side`."""
    return "positive" if side == "negative" else "negative"


def toward_sign(side: str) -> float:
    """Return the sign of α that pushes side `side`'s episodes toward the other side's task."""
    return 1.0 if side == "negative" else -1.0


def same_text(a: str, b: str) -> bool:
    """Return whether two task texts or names are the same, ignoring case and surrounding spaces."""
    return a.strip().casefold() == b.strip().casefold()
