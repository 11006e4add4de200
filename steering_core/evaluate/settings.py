"""Settings of the steering evaluation (phase 4) and the α grid's units."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, Field

from steering_core.devices import DEVICE_HELP
from steering_core.pi05.steering import check_alpha_grid
from steering_core.storage.schema import StrictModel
from steering_core.vectors.methods import MethodNames

# α in units of R, the mean residual norm of the training rows at the steered positions: α = 1 adds a vector as
# long as a typical residual, whatever the direction's own norm (α_vector = α · R / ‖d‖ multiplies d itself).
DEFAULT_ALPHA_GRID = (-8.0, -4.0, -2.0, -1.0, 0.0, 1.0, 2.0, 4.0, 8.0)
MIN_RANDOM_DIRECTIONS = 8  # the null band needs enough draws for a mean and a spread
# Below this many held-out episodes per task the episode bootstrap has too few distinct resamples (C(2n-1, n):
# 35 at n = 4, 10 at n = 3, 1 at n = 1) for a percentile interval to cover: the summary warns.
MIN_EPISODES_PER_SIDE = 5


MAX_ALPHAS = 256  # α values of a grid


def _grid_with_zero(alphas: tuple[float, ...]) -> tuple[float, ...]:
    """Return the grid sorted and without repeats; refuse one without 0 or with nothing else."""
    if len(alphas) > MAX_ALPHAS:
        raise ValueError(f"alphas: {len(alphas)} values; expected at most {MAX_ALPHAS} (each is a policy entry per "
                         "frame, seed and direction)")
    check_alpha_grid(alphas)
    if 0.0 not in alphas:
        raise ValueError(f"alphas {list(alphas)} must include 0: every shift is measured against the unsteered "
                         "actions at α = 0")
    grid = tuple(sorted(set(alphas)))
    if len(grid) < 2:
        raise ValueError(f"alphas {list(alphas)} need at least one value besides 0")
    return grid


def _each_once(names: tuple[str, ...]) -> tuple[str, ...]:
    """Return `names`; refuse an empty list or a repeated name."""
    if not names or len(set(names)) != len(names):
        raise ValueError(f"{list(names)}: give at least one, each once")
    return names


# field-level validators (not model methods), so that the run config's evaluate section checks them too
AlphaGrid = Annotated[tuple[float, ...], AfterValidator(_grid_with_zero)]


class EvaluateSettings(StrictModel):
    """How each (pair, layer) is evaluated; defaults are the issue's method."""

    holdout_fraction: float = Field(0.2, ge=0, lt=1, description=(
        "Share of each task's episodes held out of slicing for the evaluation (at least one; 0: none)."))
    max_frames: int = Field(32, ge=2, le=10_000, description="Evaluation frames per pair, shared by both tasks.")
    alphas: AlphaGrid = Field(DEFAULT_ALPHA_GRID, description=(
        "α grid in units of the mean residual norm / ||d||; must hold 0 (the unsteered reference)."))
    noise_seeds: int = Field(4, gt=0, le=256, description="Flow-matching noise draws per frame, the same across α.")
    # null: directions drawn from the rows' covariance; each is a policy sweep per frame, so thousands would take days
    random_directions: int = Field(32, ge=MIN_RANDOM_DIRECTIONS, le=4096, description=(
        "Random directions of the null (drawn from the rows' covariance, norm-matched)."))
    permutations: int = Field(8, ge=0, le=10_000, description=(
        "Null: mean differences with episode labels shuffled between the tasks."))
    methods: MethodNames | None = Field(None, description=(
        "Direction methods evaluated (default: every one phase 3 wrote, steering.methods)."))
    modes: Annotated[tuple[Literal["add", "clamp"], ...], AfterValidator(_each_once)] = Field(("add", "clamp"), description=(
        "Strength modes: add (h + α·R·d̂) and clamp (each steered token's projection on d̂ set to m_own + "
        "α·(m_other − m_own), the concepts' mean levels)."))
    num_steps: int = Field(10, gt=0, le=1000, description="Denoising steps of sample_actions.")
    bootstrap: int = Field(1000, gt=0, le=1_000_000, description=(
        "Resamples of the episodes (frames nested) for the 95% intervals."))
    seed: int = Field(0, description="Seed of the random directions, the noise and the bootstrap.")
    batch_size: int = Field(8, gt=0, le=1024, description="Frames per policy call.")
    entries_per_call: int = Field(40, gt=0, le=1024, description=(
        "Steered (direction, α) entries per sweep call (bounds GPU memory)."))
    device: str = Field("auto", description=DEVICE_HELP)
    dtype: str | None = Field(None, description="Compute dtype (default bfloat16 on CUDA, float32 on CPU).")
    compiled: bool | None = Field(None, description=(  # rounding only: not part of the identity
        "Run the policy's denoising step compiled (default: on CUDA only; batches over 16 rows run eagerly)."))
    note: str | None = Field(None, description="Printed at the top of the summary (e.g. \"tiny random model\").")

    @property
    def zero_index(self) -> int:
        """Return the position of α = 0 in the (sorted) grid."""
        return self.alphas.index(0.0)
