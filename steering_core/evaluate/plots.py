"""The PNGs of one pair's dose-response: efficacy vs α (null range shaded), action shifts, one trajectory."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from steering_core.evaluate.directions import is_null
from steering_core.reporting.plots import figure, save_png

_AXIS_NAMES = ("x", "y", "z")


def named(record: dict[str, Any]) -> list[str]:
    """Return the tested (non-null) directions of a record."""
    return [n for n in record["directions"] if not is_null(n)]


def layer_label(layer: int, stream: str) -> str:
    """Return `layer L` (language model) or `expert layer K` (action expert): task run names, titles, logs."""
    return ("expert " if stream == "expert" else "") + f"layer {layer}"


def plot_efficacy(path: Path, record: dict[str, Any]) -> None:
    """Pooled efficacy vs α per method with intervals, each side dashed, one panel per strength mode; the random
    null's 2.5-97.5% shaded in each (the nulls are added, shared by every method and mode)."""
    alphas, null = record["alphas"], record["random"]
    modes = list(dict.fromkeys(record["directions"][name].get("mode", "add") for name in named(record)))
    fig = figure((6.4 * len(modes), 4.2))
    for panel, mode in enumerate(modes):
        ax = fig.add_subplot(1, len(modes), panel + 1)
        ax.fill_between(alphas, null["low"], null["high"], color="0.85",
                        label=f"null: {len(null['names'])} random (added), 2.5-97.5%")
        ax.plot(alphas, null["mean"], color="0.6", linestyle="--", linewidth=1)
        for name in named(record):
            entry = record["directions"][name]
            if entry.get("mode", "add") != mode:
                continue
            # a percentile interval need not contain its estimate (a ratio over resampled episodes): bars stop there
            low = [max(v - ci[0], 0.0) for v, ci in zip(entry["efficacy"], entry["efficacy_ci"], strict=True)]
            high = [max(ci[1] - v, 0.0) for v, ci in zip(entry["efficacy"], entry["efficacy_ci"], strict=True)]
            line = ax.errorbar(alphas, entry["efficacy"], yerr=[low, high], marker="o", markersize=3, capsize=2,
                               label=entry.get("method", name))
            for side, style in (("positive", ":"), ("negative", "--")):
                ax.plot(alphas, entry[f"efficacy_{side}"], linestyle=style, linewidth=0.8,
                        color=line.lines[0].get_color())
        ax.axhline(1.0, color="k", linewidth=0.6, linestyle=":")
        unit = ("α: the level between the own concept's mean projection (0) and the other's (1)" if mode == "clamp"
                else "α (× R, the mean residual norm; vector units: α·R/‖d‖)")
        ax.set(xlabel=unit, ylabel="efficacy (1 = instruction swap, action std units)" if panel == 0 else None,
               title=f"{record['pair']}, {layer_label(record['layer'], record['stream'])}, {mode} "
                     "(dotted: positive-task frames, dashed: negative)")
        ax.title.set_fontsize(8)
        ax.xaxis.label.set_fontsize(8)
        ax.legend(fontsize=7)
    save_png(fig, path)


def plot_shift(path: Path, record: dict[str, Any]) -> None:
    """Mean action shift ‖Δa‖ (action std units) per action group vs α, one panel per tested direction."""
    names = named(record)
    fig = figure((3.2 * len(names), 3.4))
    for i, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), i + 1)
        for group, values in record["directions"][name]["shift"].items():
            ax.plot(record["alphas"], values, marker="o", markersize=3, label=group)
        ax.set(xlabel="α (× R)", ylabel="mean ‖Δa‖ over the horizon (std units)" if i == 0 else None, title=name)
        ax.title.set_fontsize(8)
    fig.axes[0].legend(fontsize=7)
    save_png(fig, path)


def plot_trajectory(path: Path, record: dict[str, Any], tensors: dict[str, torch.Tensor]) -> None:
    """x, y, z over the horizon of the first negative-task frame, seed 0: unsteered (its own instruction),
    the first direction at its best α (toward the positive task), and with the positive task's instruction."""
    names = list(record["directions"])
    best = record["alphas"].index(record["directions"][names[0]]["best"]["alpha"])
    zero = record["alphas"].index(0.0)
    f = next(i for i, frame in enumerate(record["frames"]) if frame["side"] == "negative")
    steered, swap = tensors["actions"], tensors["swap_actions"]
    curves = {"α = 0": steered[0, zero, f, 0], f"{names[0]}, α = {record['alphas'][best]:g}": steered[0, best, f, 0],
              "positive instruction (swap)": steered[0, zero, f, 0] + swap[f, 0]}
    fig = figure((9.0, 3.0))
    for axis, label in enumerate(_AXIS_NAMES):
        ax = fig.add_subplot(1, 3, axis + 1)
        for name, actions in curves.items():
            ax.plot(actions[:, axis].tolist(), marker=".", label=name)
        ax.set(xlabel="action step", ylabel=f"Δ{label}")
    fig.axes[0].legend(fontsize=7)
    frame = record["frames"][f]
    fig.suptitle(f"episode {frame['episode_index']} frame {frame['frame_index']} ({frame['side']} task)", fontsize=9)
    save_png(fig, path)
