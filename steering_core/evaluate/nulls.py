"""The null directions every tested direction is ranked against, built from the pair's training slices.

- `random_NN`: x = Xᵀz / √(n − 1), z ~ N(0, I_n), X the training rows centred on their own task's mean: a
  Gaussian draw with the rows' within-task covariance (the residual space's anisotropy), never forming the
  (width, width) matrix. The two tasks' mean difference is left out, so a draw is ordinary variation, not
  the contrast.
- `permuted_NN`: the mean difference with the training episodes' task labels shuffled (as many "positive"
  episodes as the positive task has), from the slices' per-row `episode_index`. It keeps its size relative to
  the real mean difference: a shuffle that mixes the tasks shrinks the difference, and steering pushes it
  that much less at the same α (`push`), so a real concept beats its shuffles even when every shuffle points
  the same way (as when the rows vary only between the tasks).

Steering adds α · R · push · d/‖d‖ (push 1 but for the permuted null), so a random direction's norm does not
change its push; each null is stored with the reference direction's norm times its push, so that α in vector
units reads the same.
"""

from __future__ import annotations

from pathlib import Path

import torch

from steering_core.evaluate.directions import PERMUTED, RANDOM
from steering_core.vectors.slice_rows import read_slice_episodes, read_slice_rows


def covariance_directions(groups: list[torch.Tensor], norm: float, count: int, seed: int) -> list[torch.Tensor]:
    """Return `count` (width,) float32 draws from the pooled within-group covariance of `groups` (rows, width),
    each scaled to `norm`; isotropic draws when no row differs from its group's mean (a zero covariance)."""
    centred = torch.cat([g.double() - g.double().mean(0) for g in groups])
    generator = torch.Generator().manual_seed(seed)
    if not bool(centred.any()):  # no row varies within its task: there is no anisotropy to match
        draws = torch.randn(count, centred.shape[1], generator=generator, dtype=torch.float64)
    else:
        z = torch.randn(count, centred.shape[0], generator=generator, dtype=torch.float64)
        draws = z @ centred / max(centred.shape[0] - 1, 1) ** 0.5
    return [(v * (norm / v.norm())).float() for v in draws]


def permuted_directions(rows: list[torch.Tensor], episodes: list[torch.Tensor], norm: float, count: int,
                        seed: int) -> list[torch.Tensor]:
    """Return `count` mean differences (positive − negative) with the episodes' labels shuffled, each scaled by
    norm / ‖real mean difference‖ (so a shuffle half as large as the real difference has norm `norm` / 2).

    `rows`/`episodes` are the (positive, negative) slices' rows and per-row episode indices; a shuffle keeps
    the number of positive episodes. Rows are pooled per pseudo-task, as the real mean difference pools them.
    """
    all_rows = torch.cat([r.double() for r in rows])
    labels = torch.cat(episodes)
    ids, inverse = torch.unique(labels, return_inverse=True)
    sums = torch.zeros(len(ids), all_rows.shape[1], dtype=torch.float64).index_add_(0, inverse, all_rows)
    counts = torch.bincount(inverse, minlength=len(ids)).double()
    positives = len(torch.unique(episodes[0]))
    real = rows[0].double().mean(0) - rows[1].double().mean(0)
    scale = norm / float(real.norm()) if real.any() else 0.0
    generator = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(count):
        chosen = torch.zeros(len(ids), dtype=torch.bool)
        chosen[torch.randperm(len(ids), generator=generator)[:positives]] = True
        d = sums[chosen].sum(0) / counts[chosen].sum() - sums[~chosen].sum(0) / counts[~chosen].sum()
        out.append((d * scale).float())
    return out


def null_directions(slices: tuple[Path, Path], norm: float, *, random_count: int, permutations: int,
                    seed: int) -> tuple[dict[str, torch.Tensor], str | None]:
    """Return the null directions of a pair's training slices and a note when the permutation null is skipped.

    The permutation null needs each slice's `episode_index` column and at least two episodes in all.
    """
    rows = [read_slice_rows(path) for path in slices]
    nulls = {RANDOM.format(index=i): v for i, v in enumerate(covariance_directions(rows, norm, random_count, seed))}
    if permutations == 0:
        return nulls, None
    episodes = [read_slice_episodes(path) for path in slices]
    if any(e is None for e in episodes):
        return nulls, (f"no permutation null: {', '.join(str(p) for p, e in zip(slices, episodes, strict=True) if e is None)}"
                       " has no `episode_index` column (cut the slices with `latent-steering slice`)")
    if len(torch.unique(torch.cat(episodes))) < 2:
        return nulls, "no permutation null: the training slices hold fewer than two episodes"
    permuted = permuted_directions(rows, episodes, norm, permutations, seed + 1)
    return nulls | {PERMUTED.format(index=i): v for i, v in enumerate(permuted) if v.norm() > 0}, None
