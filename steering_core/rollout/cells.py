"""A rollout cell: one (side, condition, α) of a (pair, layer), the unit the closed loop measures.

`side` names the task whose scene, initial states and instruction the episodes start from. `condition` is one of:

- `<method>` (e.g. `sae`, `probe`): the pair's direction of that registered method (`steering_core.vectors.methods`)
  added at α (add mode); `<method>+clamp`: the same direction in clamp mode, each steered token's projection set
  to a level between the two concepts' mean levels (kind "steered");
- `random_<k>`: a random direction norm-matched to the catalog's default direction, add mode (kind "random");
- `wrong_concept:<pair>/<method>`: another pair's direction of that method at the same α, add mode;
- `instruction_swap`: the other task's instruction, no steering (the ceiling); `unsteered`: α = 0.

`alpha` is the signed push along the direction: α·toward_sign(side), so `alpha_toward` (α on the negative side,
−α on the positive side) is the push toward the other task, in residual_norm units (× R, the evaluation's unit)
in add mode, and in clamp mode the fraction of the way from this side's concept level to the other's
(`run.steering_entries` turns it into the request's absolute level).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from steering_core.layout import rollout_cell_dir
from steering_core.pairs import SIDES, other_side, toward_sign
from steering_core.pi05.steering import MODES
from steering_core.vectors.methods import METHODS

STEERED, UNSTEERED, SWAP = "steered", "unsteered", "instruction_swap"
RANDOM_PREFIX, WRONG_PREFIX = "random_", "wrong_concept:"
KINDS = (STEERED, "random", "wrong_concept", SWAP, UNSTEERED)
_RANDOM = re.compile(r"random_\d+")
_WRONG = re.compile(r"wrong_concept:(?P<pair>[^/]+)/(?P<method>[^/]+)")


def steered_condition(method: str, mode: str = "add") -> str:
    """Return the condition of `method`'s direction in `mode`: `sae`, `probe+clamp`."""
    return method if mode == "add" else f"{method}+{mode}"


def steered_parts(condition: str) -> tuple[str, str]:
    """Return (method, mode) of a steered condition: `probe+clamp` -> ("probe", "clamp"), `sae` -> ("sae", "add")."""
    method, _, mode = condition.partition("+")
    return method, mode or "add"


def wrong_condition(pair: str, method: str) -> str:
    """Return the condition steering with another pair's `method` direction: `wrong_concept:on_vs_off/sae`."""
    return f"{WRONG_PREFIX}{pair}/{method}"


def condition_kind(condition: str) -> str:
    """Return the kind of a condition (one of KINDS): `random_3` -> random, `wrong_concept:a_vs_b/sae` ->
    wrong_concept, `sae` and `probe+clamp` -> steered."""
    if condition in (SWAP, UNSTEERED):
        return condition
    if _RANDOM.fullmatch(condition):
        return "random"
    return "wrong_concept" if condition.startswith(WRONG_PREFIX) else STEERED


def _condition_problem(condition: str) -> str | None:
    """Return why `condition` is not one of the module docstring's, or None."""
    kind = condition_kind(condition)
    if kind == "wrong_concept":
        match = _WRONG.fullmatch(condition)
        method = match.group("method") if match else None
    elif kind == STEERED:
        method, mode = steered_parts(condition)
        method = method if condition == steered_condition(method, mode) and mode in MODES else None
    else:
        return None
    if method in METHODS:
        return None
    return (f"condition {condition!r} is not <method>, <method>+clamp, random_<k>, wrong_concept:<pair>/<method>, "
            f"instruction_swap or unsteered (registered methods: {sorted(METHODS)})")


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
        if problem := _condition_problem(self.condition):
            problems.append(problem)
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
        return _WRONG.fullmatch(self.condition).group("pair") if self.kind == "wrong_concept" else self.pair

    @property
    def method(self) -> str | None:
        """Return the method whose direction steers this cell (None: unsteered, or a random control)."""
        if self.kind == "wrong_concept":
            return _WRONG.fullmatch(self.condition).group("method")
        return steered_parts(self.condition)[0] if self.kind == STEERED else None

    @property
    def mode(self) -> str | None:
        """Return how the direction steers: "add" or "clamp" (None: unsteered)."""
        if self.steering_pair is None:
            return None
        return steered_parts(self.condition)[1] if self.kind == STEERED else "add"

    @property
    def direction(self) -> str | None:
        """Return the catalog direction name (`sae`, `random_3`, ...) steering this cell, or None."""
        return self.condition if self.kind == "random" else self.method

    @property
    def prompt_side(self) -> str:
        """Return the side whose instruction the policy reads."""
        return other_side(self.side) if self.condition == SWAP else self.side

    @property
    def name(self) -> str:
        """Return the cell's folder name, e.g. `negative_sae_a+2`, `positive_probe+clamp_a-0.5`."""
        return rollout_cell_dir(self.side, self.condition, self.alpha)
