"""The rollout grid of one (pair, layer): its cells (side x condition x α, `cells.Cell`) and their chunks of
initial states.

Every cell of a pair runs the same initial states with the same seeds, so cells are paired: a difference between
two cells is the steering's, not the draw's. Side `negative` runs the negative task's instruction and pushes
toward the positive task (α > 0 in the direction's own sign); side `positive` is its mirror.
"""

from __future__ import annotations

from steering_core.rollout.cells import RANDOM_PREFIX, SWAP, UNSTEERED, Cell, steered_condition, wrong_condition
from steering_core.rollout.settings import RolloutSettings


def steered_conditions(settings: RolloutSettings) -> list[str]:
    """Return the steered conditions, one per method x mode, methods first: `sae`, `sae+clamp`, `probe`, ..."""
    return [steered_condition(method, mode) for method in settings.methods for mode in settings.modes]


def cells(pair: str, layer: int, settings: RolloutSettings, other_pairs: list[str]) -> list[Cell]:
    """Return the cells of (pair, layer): per side α = 0, the instruction swap, then at each push one steered cell
    per method x mode, the random controls (add mode, shared by every method) and the wrong concept (the first of
    `other_pairs`, when there is one, steered by the first method in add mode)."""
    grid = []
    for side in settings.sides:
        grid.append(Cell(pair, layer, side, UNSTEERED, 0.0))
        if settings.instruction_swap:
            grid.append(Cell(pair, layer, side, SWAP, 0.0))
        for push in settings.pushes:
            conditions = steered_conditions(settings) + [f"{RANDOM_PREFIX}{k}" for k in range(settings.random_directions)]
            if settings.wrong_concept and other_pairs:
                conditions.append(wrong_condition(other_pairs[0], settings.methods[0]))
            grid.extend(Cell.pushed(pair, layer, side, condition, push) for condition in conditions)
    return grid


def chunks(settings: RolloutSettings) -> list[tuple[int, ...]]:
    """Return the initial-state indices of each task run of a cell, in order."""
    states, size = settings.init_states, settings.chunk_episodes
    return [states[i:i + size] for i in range(0, len(states), size)]
