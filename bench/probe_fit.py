"""Probe fit: how long `fit_probe` (method `probe`) takes at the residual width of pi0.5, at a fixed C and with C
chosen by cross-validation over whole episodes, on the CPU.

The rows are synthetic residual-like data: a large mean with three massive dimensions, a low-rank power-law
covariance (most of the variance in a few hundred directions), a random offset per episode, and the two concepts
shifted apart along one direction so that they overlap. Both runs fit the same rows in one process; the peak
resident memory is the process's so far (the rows themselves included).

    uv run python -m bench.probe_fit [--rows 100000] [--width 2048] [--episodes 20]
"""

from __future__ import annotations

import argparse

import torch

from bench.common import markdown_table, peak_rss_mib, timed
from steering_core.vectors.methods.probe import fit_probe

# ----------------------------------------------------------------------------- settings

ROWS = 100_000  # both concepts together, half each
WIDTH = 2048  # pi0.5's (PaliGemma's Gemma 2B) residual width
EPISODES = 20  # per concept
RANK = 256  # directions of the low-rank covariance
SHIFT = 0.3  # half the distance between the concepts' means, along a unit direction
FIXED_C = 1.0
FOLDS = 5


def concept_rows(rows: int, width: int, episodes: int, seed: int = 0
                 ) -> tuple[tuple[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]:
    """Return ((rows, episodes) positive, (rows, episodes) negative): float32 rows, int64 episode ids."""
    generator = torch.Generator().manual_seed(seed)
    basis = torch.linalg.qr(torch.randn(width, RANK, generator=generator))[0]
    loadings = basis * (30.0 / torch.arange(1, RANK + 1)).sqrt()
    mean = torch.randn(width, generator=generator) * 2
    mean[:3] += 80
    direction = torch.nn.functional.normalize(torch.randn(width, generator=generator), dim=0)
    per_episode = rows // 2 // episodes
    sides = []
    for sign, first in ((1.0, 0), (-1.0, 1000)):
        offsets = (torch.randn(episodes, RANK, generator=generator) * 0.3) @ loadings.T
        latent = torch.randn(episodes * per_episode, RANK, generator=generator)
        x = latent @ loadings.T + 0.3 * torch.randn(episodes * per_episode, width, generator=generator)
        x += mean + sign * SHIFT * direction + offsets.repeat_interleave(per_episode, 0)
        sides.append((x, torch.arange(first, first + episodes).repeat_interleave(per_episode)))
    return sides[0], sides[1]


def main(argv: list[str] | None = None) -> list[dict]:
    """Time both fits; print and return the table's rows."""
    args = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args.add_argument("--rows", type=int, default=ROWS, help=f"rows of both concepts together (default {ROWS})")
    args.add_argument("--width", type=int, default=WIDTH, help=f"residual width (default {WIDTH})")
    args.add_argument("--episodes", type=int, default=EPISODES, help=f"episodes per concept (default {EPISODES})")
    args = args.parse_args(argv)
    (x_pos, e_pos), (x_neg, e_neg) = concept_rows(args.rows, args.width, args.episodes)
    generated = peak_rss_mib()
    device = torch.device("cpu")
    table = []
    for label, c in ((f"fixed C = {FIXED_C:g}", FIXED_C), (f"cross-validated, {FOLDS} folds", None)):
        fit, seconds = timed(lambda: fit_probe(x_pos, x_neg, e_pos, e_neg, folds=FOLDS, c=c), device)
        table.append({"fit": label, "rows": len(x_pos) + len(x_neg), "width": args.width, "seconds": seconds,
                      "C": fit.c, "iterations": fit.iterations, "converged": fit.converged,
                      "held-out AUC": "-" if fit.heldout_auc is None else f"{fit.heldout_auc:.3f}",
                      "train accuracy": f"{fit.train_accuracy:.3f}", "peak RSS so far (MiB)": peak_rss_mib()})
    print("\n".join(markdown_table(table)), flush=True)
    print(f"torch threads: {torch.get_num_threads()}; {args.episodes} episodes per concept; peak RSS after "
          f"generating the rows, before fitting: {generated:,.0f} MiB", flush=True)
    return table


if __name__ == "__main__":
    main()
