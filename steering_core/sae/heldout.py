"""The episodes an SAE trained on the run's residuals never sees: the pairs' held-out ones, judged on afterwards."""

from __future__ import annotations

import os
from collections.abc import Sequence

from steering_core.data.split import read_split


def sae_heldout_episodes(run_episodes: Sequence[int], split_paths: Sequence[str | os.PathLike],
                         fraction: float) -> tuple[int, ...]:
    """Return the run's episodes kept out of SAE training.

    The pairs' held-out episodes when their splits hold any (the evaluation's frames must stay unseen); otherwise
    every k-th episode of the run (k = round(1 / fraction)), at least one, so the SAE is still judged on rows it
    was not trained on.
    """
    present = set(run_episodes)
    held = sorted({e for path in split_paths for e in read_split(path).holdout_episodes} & present)
    if held:
        return tuple(held)
    if len(present) < 2:
        raise ValueError(f"the residual run holds {len(present)} episode(s); training an SAE and judging it on "
                         "held-out rows needs at least 2")
    step = max(2, round(1 / fraction))
    return tuple(sorted(present)[::step])
