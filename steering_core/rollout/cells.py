"""A rollout cell: one (side, condition, α) of a (pair, layer), the unit the closed loop measures.

`side` names the task whose scene, initial states and instruction the episodes start from; `condition` is
"steered" (the pair's direction), "random_<k>" (a norm-matched random direction), "wrong_concept:<pair>" (another
pair's direction at the same α), "instruction_swap" (the other task's instruction, no steering: the ceiling) or
"unsteered" (α = 0). `alpha` is the signed α added along the direction, in residual_norm units (× R, the
evaluation's unit); `alpha_toward` = α on the negative side and −α on the positive side is the push toward the
other task.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from steering_core.layout import rollout_cell_dir
from steering_core.pairs import SIDES, other_side, toward_sign

STEERED, UNSTEERED, SWAP = "steered", "unsteered", "instruction_swap"
RANDOM_PREFIX, WRONG_PREFIX = "random_", "wrong_concept:"
KINDS = ("steered", "random", "wrong_concept", "instruction_swap", "unsteered")
_CONDITION = re.compile(r"steered|random_\d+|wrong_concept:.+|instruction_swap|unsteered")


def condition_kind(condition: str) -> str:
    """Return the kind of a condition (one of KINDS): `random_3` -> random, `wrong_concept:a_vs_b` -> wrong_concept."""
    return condition.partition(":")[0] if ":" in condition else re.sub(r"_\d+$", "", condition)


@dataclass(frozen=True)
class Cell:
    """One cell (see the module docstring); ValueError naming every problem when its fields do not fit."""

    pair: str
    layer: int
    side: str
    condition: str
    alpha: float

    def __post_init__(self) -> None:
        problems = []
        if self.side not in SIDES:
            problems.append(f"side {self.side!r} is not one of {list(SIDES)}")
        if not _CONDITION.fullmatch(self.condition):
            problems.append(f"condition {self.condition!r} is not steered, random_<k>, wrong_concept:<pair>, "
                            "instruction_swap or unsteered")
        if not math.isfinite(self.alpha) or (self.condition in (UNSTEERED, SWAP) and self.alpha):
            problems.append(f"alpha {self.alpha!r} must be finite, and 0 for the unsteered and instruction_swap cells")
        if problems:
            raise ValueError(f"rollout cell {self.pair} layer {self.layer}: " + "; ".join(problems))
        object.__setattr__(self, "alpha", float(self.alpha) + 0.0)  # + 0.0: no -0

    @classmethod
    def pushed(cls, pair: str, layer: int, side: str, condition: str, push: float) -> Cell:
        """Return the cell of `side` whose steering pushes its episodes `push` toward the other task."""
        return cls(pair, layer, side, condition, push * toward_sign(side))

    @property
    def alpha_toward(self) -> float:
        """Return α as a push toward the other task: α on the negative side, −α on the positive side."""
        return self.alpha * toward_sign(self.side) + 0.0

    @property
    def kind(self) -> str:
        """Return the condition's kind (one of KINDS)."""
        return condition_kind(self.condition)

    @property
    def steering_pair(self) -> str | None:
        """Return the pair whose vector steers this cell (None: unsteered)."""
        if self.condition in (UNSTEERED, SWAP):
            return None
        return self.condition.removeprefix(WRONG_PREFIX) if self.condition.startswith(WRONG_PREFIX) else self.pair

    def direction(self, kind: str) -> str | None:
        """Return the catalog direction name (`residual`, `random_3`, ...) steering this cell, or None."""
        if self.steering_pair is None:
            return None
        return self.condition if self.condition.startswith(RANDOM_PREFIX) else kind

    @property
    def prompt_side(self) -> str:
        """Return the side whose instruction the policy reads."""
        return other_side(self.side) if self.condition == SWAP else self.side

    @property
    def name(self) -> str:
        """Return the cell's folder name, e.g. `negative_steered_a+2` or `positive_random_1_a-4`."""
        return rollout_cell_dir(self.side, self.condition, self.alpha)
