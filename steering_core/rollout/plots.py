"""The PNGs of one pair's rollouts: success rate vs α with Wilson intervals and the controls, and the trajectories
of the joints the goals test (drawer, stove knob) per α. Both read cell records as `records.write_cell` writes them."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from steering_core.pairs import SIDES
from steering_core.reporting.plots import figure, save_png
from steering_core.rollout.records import JOINT_KEY

ALPHA_LABELS = {"add": "α toward the other task (× R, residual_norm units)",
                "clamp": "α toward the other task (clamp: fraction of the way to the other concept's level)"}
Thresholds = Mapping[str, Sequence[tuple[str, float]]]  # joint name -> (goal label, qpos threshold)


def _side_cells(records: Sequence[dict[str, Any]], side: str, *kinds: str) -> list[dict[str, Any]]:
    """Return the side's cells of the given kinds, by α toward the other task."""
    return sorted((r for r in records if r["side"] == side and r["kind"] in kinds), key=lambda r: r["alpha_toward"])


def _errorbar(ax: Any, cells: Sequence[dict[str, Any]], outcome: str, shift: float = 0.0, **style: Any) -> None:
    """Plot the `outcome` success rate of `cells` against α toward (moved by `shift` so that series at one α do
    not hide each other's bars), with Wilson 95% intervals as bars."""
    x = [c["alpha_toward"] + shift for c in cells]
    success = [c["success"][outcome] for c in cells]
    rates = [s["rate"] for s in success]
    bars = [[r - s["low"] for r, s in zip(rates, success, strict=True)],
            [s["high"] - r for r, s in zip(rates, success, strict=True)]]
    ax.errorbar(x, rates, yerr=bars, capsize=2, markersize=4, **style)


def _random_band(ax: Any, cells: Sequence[dict[str, Any]]) -> None:
    """Shade min..max of the random controls' toward-task success rates at each α."""
    by_alpha: dict[float, list[float]] = {}
    for cell in cells:
        by_alpha.setdefault(cell["alpha_toward"], []).append(cell["success"]["toward"]["rate"])
    x = sorted(by_alpha)
    count = len({c["condition"] for c in cells})
    ax.fill_between(x, [min(by_alpha[a]) for a in x], [max(by_alpha[a]) for a in x], facecolor="0.85",
                    edgecolor="0.6", label=f"random ({count} directions): toward, min-max", zorder=0)


def _panels(records: Sequence[dict[str, Any]]) -> list[tuple[str, str]]:
    """Return the (steered condition, side) of each panel: one row per method x mode, one column per side."""
    sides = [s for s in SIDES if any(r["side"] == s for r in records)]
    conditions = list(dict.fromkeys(r["condition"] for r in records if r["kind"] == "steered")) or [None]
    return [(condition, side) for condition in conditions for side in sides]


def plot_success(path: Path, records: Sequence[dict[str, Any]]) -> None:
    """Success rate vs α toward the other task, one panel per steered direction (method x mode, rows) and side
    (columns): the direction's toward-task and instructed-task success with Wilson 95% intervals, the random
    controls' band (shared by every direction), the wrong concept's marks (in its method's add panel), and α = 0
    (unsteered) and the instruction swap (ceiling) as horizontal lines."""
    panels = _panels(records)
    columns = len({side for _, side in panels})
    rows = len(panels) // columns
    fig = figure((5.5 * columns, 4.6 * rows))
    alphas = [r["alpha_toward"] for r in records]
    dodge = 0.012 * ((max(alphas) - min(alphas)) or 1.0)
    for i, (condition, side) in enumerate(panels):
        ax = fig.add_subplot(rows, columns, i + 1, sharey=fig.axes[0] if i else None)
        steered = [r for r in _side_cells(records, side, "steered") if r["condition"] == condition]
        mode = steered[0]["mode"] if steered else "add"
        if randoms := _side_cells(records, side, "random"):
            _random_band(ax, randoms)
        wrong = [c for c in _side_cells(records, side, "wrong_concept")
                 if steered and c["method"] == steered[0]["method"] and mode == "add"]
        for name in sorted({c["condition"] for c in wrong}):
            _errorbar(ax, [c for c in wrong if c["condition"] == name], "toward", -dodge, marker="x",
                      linestyle="none", color="C3", label=f"{name}: toward")
        for kind, outcome, color, style in (("unsteered", "toward", "C0", ":"), ("unsteered", "instructed", "C1", ":"),
                                            ("instruction_swap", "toward", "C2", "--")):
            for cell in _side_cells(records, side, kind):
                name = "α = 0" if kind == "unsteered" else "instruction swap (ceiling)"
                ax.axhline(cell["success"][outcome]["rate"], color=color, linestyle=style, linewidth=1,
                           label=f"{name}: {outcome} {cell['success'][outcome]['k']}/{cell['success'][outcome]['n']}")
        if steered:  # from α = 0: the direction at zero strength
            curve = _side_cells(records, side, "unsteered") + steered
            _errorbar(ax, curve, "toward", marker="o", color="C0", label=f"{condition}: toward-task success")
            _errorbar(ax, curve, "instructed", dodge, marker="s", color="C1", linestyle="--",
                      label=f"{condition}: instructed-task success")
        first = next(r for r in records if r["side"] == side)
        task = f"{first['instructed']['instruction']!r} → {first['toward']['instruction']!r}"
        ax.set(xlabel=ALPHA_LABELS[mode], ylabel="success rate (Wilson 95%)" if i % columns == 0 else None,
               ylim=(-0.03, 1.03), title=f"{condition or 'no steered cells'}, {side} side: {task}")
        ax.title.set_fontsize(8)
        ax.xaxis.label.set_fontsize(8)
        ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=2)
    pair = records[0]
    fig.suptitle(f"{pair['pair']}, layer {pair['layer']}: {pair['success']['toward']['n']} episodes per cell",
                 fontsize=9)
    save_png(fig, path)


def held_after_end(values: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Return (E, T + 1) joint positions with each episode's last value held after its end (NaN padding
    replaced): an episode that ended at a goal stays at the goal rather than leaving the median."""
    out = values.copy()
    for i, steps in enumerate(lengths):
        out[i, steps + 1:] = values[i, steps]
    return out


def plot_joints(path: Path, cells: Sequence[tuple[dict[str, Any], dict[str, np.ndarray]]],
                thresholds: Thresholds | None = None) -> None:
    """Each goal-tested joint's position per policy step, one panel per (steered direction, side, joint): one line
    per α toward the other task (the direction's and α = 0; median over episodes with the 25-75% band), the
    instruction swap dotted, and the goals' thresholds dashed."""
    from matplotlib import colormaps

    joints = sorted({name for record, _ in cells for name in record["joints"]})
    if not joints:
        raise ValueError(f"{cells[0][0]['pair']}: the cells record no goal-tested joints; nothing to plot")
    panels = _panels([record for record, _ in cells])
    fig = figure((4.6 * len(joints), 3.4 * len(panels)))
    largest = max((abs(r["alpha_toward"]) for r, _ in cells), default=0.0) or 1.0
    for row, (condition, side) in enumerate(panels):
        lines = sorted(((r, a) for r, a in cells if r["side"] == side and (
            r["kind"] in ("unsteered", "instruction_swap") or r["condition"] == condition)),
                       key=lambda item: (item[0]["kind"] == "instruction_swap", item[0]["alpha_toward"]))
        for col, joint in enumerate(joints):
            ax = fig.add_subplot(len(panels), len(joints), row * len(joints) + col + 1)
            for record, arrays in lines:
                if JOINT_KEY + joint not in arrays:
                    continue
                values = held_after_end(arrays[JOINT_KEY + joint], arrays["lengths"])
                low, median, high = np.percentile(values, [25, 50, 75], axis=0)
                swap = record["kind"] == "instruction_swap"
                color = "k" if swap else colormaps["viridis"](0.9 * abs(record["alpha_toward"]) / largest)
                label = "instruction swap" if swap else f"α = {record['alpha_toward']:+g}"
                steps = np.arange(len(median))
                ax.plot(steps, median, color=color, linestyle=":" if swap else "-", linewidth=1.2, label=label)
                ax.fill_between(steps, low, high, color=color, alpha=0.15, linewidth=0)
            for goal, value in (thresholds or {}).get(joint, ()):
                ax.axhline(value, color="C3", linestyle="--", linewidth=0.8)
                ax.annotate(goal, (1.0, value), xycoords=("axes fraction", "data"), fontsize=7, color="C3",
                            ha="right", va="bottom")
            task = f": {lines[0][0]['instructed']['instruction']!r}" if lines else ""
            ax.set(xlabel="policy step", ylabel=f"{joint} qpos" if col == 0 else None,
                   title=f"{condition or 'no steered cells'}, {side} side{task}")
            ax.title.set_fontsize(8)
            if col == 0:
                ax.legend(fontsize=6)
    fig.suptitle(f"{cells[0][0]['pair']}, layer {cells[0][0]['layer']}: median over episodes, 25-75% shaded "
                 "(an ended episode holds its last value)", fontsize=9)
    save_png(fig, path)
