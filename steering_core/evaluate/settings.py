"""Settings of the steering evaluation (phase 4) and the α grid's units."""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import AfterValidator, Field

from steering_core.storage.schema import StrictModel

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
    if not all(math.isfinite(a) for a in alphas):
        raise ValueError(f"alphas {list(alphas)} must be finite numbers")
    if 0.0 not in alphas:
        raise ValueError(f"alphas {list(alphas)} must include 0: every shift is measured against the unsteered "
                         "actions at α = 0")
    grid = tuple(sorted(set(alphas)))
    if len(grid) < 2:
        raise ValueError(f"alphas {list(alphas)} need at least one value besides 0")
    return grid


# a field-level validator (not a model method), so that the run config's evaluate section checks it too
AlphaGrid = Annotated[tuple[float, ...], AfterValidator(_grid_with_zero)]


class EvaluateSettings(StrictModel):
    """How each (pair, layer) is evaluated; defaults are the issue's method."""

    holdout_fraction: float = Field(0.2, ge=0, lt=1)  # episodes per task held out of slicing (at least one)
    max_frames: int = Field(32, ge=2, le=10_000)  # evaluation frames per pair, shared by both tasks
    alphas: AlphaGrid = DEFAULT_ALPHA_GRID       # must hold 0 (the unsteered reference)
    noise_seeds: int = Field(4, gt=0, le=256)  # flow-matching noise draws per frame, the same across α
    # null: directions drawn from the rows' covariance; each is a policy sweep per frame, so thousands would take days
    random_directions: int = Field(32, ge=MIN_RANDOM_DIRECTIONS, le=4096)
    permutations: int = Field(8, ge=0, le=10_000)  # null: mean differences with episode labels shuffled between tasks
    top_k: int = Field(20, gt=0, le=4096)    # SAE latents kept for the top-k direction
    num_steps: int = Field(10, gt=0, le=1000)  # denoising steps of sample_actions
    bootstrap: int = Field(1000, gt=0, le=1_000_000)  # resamples of the episodes (frames nested) for 95% intervals
    seed: int = 0                              # random directions, noise and bootstrap
    batch_size: int = Field(8, gt=0, le=1024)  # frames per policy sweep call (capture's bound)
    entries_per_call: int = Field(40, gt=0, le=1024)  # steered (direction, α) entries per sweep call (bounds GPU memory)
    device: str = "auto"
    dtype: str | None = None                   # None: bfloat16 on CUDA, float32 on CPU (as openpi)
    compiled: bool | None = None               # the compiled denoising step (None: on CUDA); rounding only: no identity
    note: str | None = None                    # printed at the top of the summary (e.g. "tiny random model")

    @property
    def zero_index(self) -> int:
        """Return the position of α = 0 in the (sorted) grid."""
        return self.alphas.index(0.0)
