"""The closed-loop grid for M direction methods in one or both modes: cells and episodes, and modelled time.

The cells come from the rollout settings themselves (`steering_core.rollout.grid.cells`), at the scale of the study
of section 16: one (pair, layer), both sides, 50 episodes per cell, α toward the other task 0, 1, 2 and 4, 4 random
directions, the wrong concept and the instruction swap: 40 cells and 2,000 episodes with one method in add mode.
Each method x mode adds one cell per push and side; α = 0, the swap, the random directions and the wrong concept
are shared. The time is section 16's model (`bench.serve_throughput.grid_model`) on one machine with one GPU and
16 simulator cores: GPU calls of 16 rows (the first H200 run's peak and batch-1 latency, or a GPU check JSON's)
plus simulator steps at section 12's per-core rates, added without overlap (an upper bound). Nothing is measured.

    uv run python -m bench.rollout_grid [--gpu-check gpu_check.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from bench.common import markdown_table
from bench.serve_throughput import gpu_inputs, grid_model

STUDY = {"episodes": 50, "alphas": (0.0, 1.0, 2.0, 4.0), "random_directions": 4}  # section 16's grid
METHOD_COUNTS = (1, 2, 3, 4)
MODE_SETS = (("add",), ("add", "clamp"))


def grid_size(methods: tuple[str, ...], modes: tuple[str, ...], **settings: Any) -> tuple[int, int]:
    """Return (cells, episodes) of one (pair, layer)'s grid with `methods` x `modes` (the study's other settings
    unless given), a second pair rolled out beside it (the wrong concept)."""
    from steering_core.rollout.grid import cells
    from steering_core.rollout.settings import RolloutSettings

    rollout = RolloutSettings(**(STUDY | settings), methods=methods, modes=modes)
    count = len(cells("pair", 12, rollout, other_pairs=["other"]))
    return count, count * rollout.episodes


def method_grid(gpu: dict[str, Any]) -> list[dict[str, Any]]:
    """Return one row per method count and mode set: cells, episodes, and the modelled GPU, simulator and total
    minutes (`grid_model`)."""
    from steering_core.vectors.methods import METHODS

    names = tuple(name for name, entry in METHODS.items() if not entry.needs_file)  # any registered names will do
    rows = []
    for count in METHOD_COUNTS:
        for modes in MODE_SETS:
            cells, episodes = grid_size(names[:count], modes)
            model = {row["quantity"].split(" (")[0]: row["value"] for row in grid_model(gpu, episodes)}
            rows.append({"methods": count, "modes": " + ".join(modes), "cells": cells, "episodes": episodes,
                         "GPU min": model["GPU minutes"], "simulator min": model["simulator minutes"],
                         "total min (no overlap)": model["study minutes"]})
    return rows


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    """Print the table (markdown) and the GPU figures' source; return its rows."""
    args = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args.add_argument("--gpu-check", type=Path, default=None, help="A bench.gpu_check JSON for the GPU figures.")
    gpu = gpu_inputs(args.parse_args(argv).gpu_check)
    rows = method_grid(gpu)
    print("\n".join(markdown_table(rows)))
    print(f"\nGPU figures: {gpu['source']} ({gpu['peak_tflops']:g} TFLOP/s peak, {gpu['batch1_ms']:g} ms batch 1)")
    return rows


if __name__ == "__main__":
    main()
