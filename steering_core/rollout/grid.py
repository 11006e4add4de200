"""The rollout grid of one (pair, layer): its cells (side x condition x α) and their chunks of initial states.

Every cell of a pair runs the same initial states with the same seeds, so cells are paired: a difference between
two cells is the steering's, not the draw's. Side `negative` runs the negative task's instruction and pushes
toward the positive task (α > 0 in the direction's own sign); side `positive` is its mirror.
"""

from __future__ import annotations

from dataclasses import dataclass

from steering_core.layout import rollout_cell_dir
from steering_core.pairs import other_side, toward_sign
from steering_core.rollout.settings import RolloutSettings

STEERED, UNSTEERED, SWAP = "steered", "unsteered", "instruction_swap"
RANDOM_PREFIX, WRONG_PREFIX = "random_", "wrong_concept:"


@dataclass(frozen=True)
class Cell:
    """One cell: episodes under `side`'s instruction (the other's with `instruction_swap`), steered by
    `condition` at `alpha_toward` (residual_norm units, toward the other task)."""

    pair: str
    layer: int
    side: str
    condition: str
    alpha_toward: float

    @property
    def alpha(self) -> float:
        """Return the signed α added along the direction (its own sign: + pushes toward the positive concept)."""
        return self.alpha_toward * toward_sign(self.side)

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


def cells(pair: str, layer: int, settings: RolloutSettings, other_pairs: list[str]) -> list[Cell]:
    """Return the cells of (pair, layer): per side α = 0, the instruction swap, then at each push the steered
    direction, the random controls and the wrong concept (the first of `other_pairs`, when there is one)."""
    grid = []
    for side in settings.sides:
        grid.append(Cell(pair, layer, side, UNSTEERED, 0.0))
        if settings.instruction_swap:
            grid.append(Cell(pair, layer, side, SWAP, 0.0))
        for push in settings.pushes:
            conditions = [STEERED] + [f"{RANDOM_PREFIX}{k}" for k in range(settings.random_directions)]
            if settings.wrong_concept and other_pairs:
                conditions.append(f"{WRONG_PREFIX}{other_pairs[0]}")
            grid.extend(Cell(pair, layer, side, condition, push) for condition in conditions)
    return grid


def chunks(settings: RolloutSettings) -> list[tuple[int, ...]]:
    """Return the initial-state indices of each task run of a cell, in order."""
    states, size = settings.init_states, settings.chunk_episodes
    return [states[i:i + size] for i in range(0, len(states), size)]
