"""Outputs of the evaluation: per pair dose_response.json/.safetensors and PNGs, per layer summary.md/json,
and the comparison of the two pathways (language model vs action expert), pathways.md/json.

`dose_response.json` names the α grid `alphas`, the metric `efficacy`, the control directions `random`
and the reference `swap`; its tensors (every metric, interval and the raw robot actions) are in
`dose_response.safetensors`. Nothing here reads a clock or a random state, so equal inputs give
byte-identical files.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

from steering_core.evaluate.directions import RANDOM_PREFIX
from steering_core.evaluate.metrics import ACTION_GROUPS
from steering_core.reporting.plots import figure, save_png
from steering_core.storage.fileio import atomic_path, read_json, write_json
from steering_core.storage.layout import (
    DOSE_RESPONSE_FILE,
    EFFICACY_PLOT,
    PATHWAYS_FILE,
    SHIFT_PLOT,
    SUMMARY_JSON,
    SUMMARY_MD,
    TRAJECTORY_PLOT,
    stream_layer_dir,
)

logger = logging.getLogger(__name__)

EVAL_FORMAT_VERSION = 1
_PER_DIRECTION = ("efficacy", "efficacy_ci", "cosine", "cosine_ci", "contrast_shift", "contrast_shift_ci", "z")
_AXIS_NAMES = ("x", "y", "z")
ALPHA_UNITS = {
    "lm": "mean instruction-token residual norm at the layer / ||d||; alphas_vector_units: multiples of d",
    "expert": "mean decision-residual norm at the expert layer / ||d||; alphas_vector_units: multiples of d",
}


def _json_floats(tensor: torch.Tensor) -> Any:
    """Return a tensor as nested Python floats, NaN/inf as None (JSON has neither)."""
    values = tensor.double().tolist()
    if isinstance(values, float):
        return values if math.isfinite(values) else None
    return [_json_floats(torch.tensor(v, dtype=torch.float64)) if isinstance(v, list) else
            (v if math.isfinite(v) else None) for v in values]


def best_alpha_index(efficacy: torch.Tensor, zero_index: int) -> int:
    """Return the index of the α ≠ 0 whose efficacy is closest to 1 (the instruction swap); ties keep the first."""
    distance = (efficacy.double() - 1.0).abs().clone()
    distance[zero_index] = math.inf
    return int(torch.argmin(distance))


def pair_record(head: dict[str, Any], names: list[str], alphas: tuple[float, ...], zero_index: int,
                metrics: dict[str, torch.Tensor], vector_scale: torch.Tensor) -> dict[str, Any]:
    """Return the JSON of one pair's dose-response (`head` holds pair, layer, split, settings, frames...)."""
    groups = list(ACTION_GROUPS)
    directions = {}
    for d, name in enumerate(names):
        entry = {key: _json_floats(metrics[key][d]) for key in _PER_DIRECTION}
        entry["alphas_vector_units"] = _json_floats(vector_scale[d])
        entry["shift"] = {g: _json_floats(metrics["shift"][d, :, i]) for i, g in enumerate(groups)}
        entry["shift_ci"] = {g: _json_floats(metrics["shift_ci"][d, :, i]) for i, g in enumerate(groups)}
        best = best_alpha_index(metrics["efficacy"][d], zero_index)
        entry["best"] = {"alpha": alphas[best], "efficacy": entry["efficacy"][best],
                         "efficacy_ci": entry["efficacy_ci"][best], "z": entry["z"][best],
                         "shift": {g: entry["shift"][g][best] for g in groups}}
        directions[name] = entry
    random = [n for n in names if n.startswith(RANDOM_PREFIX)]
    return {
        "format_version": EVAL_FORMAT_VERSION,
        **head,
        "alphas": list(alphas),
        "alpha_units": ALPHA_UNITS[head.get("stream", "lm")],
        "metric": "efficacy",
        "action_groups": groups,
        "directions": directions,
        "random": {"names": random, **{k.removeprefix("random_"): _json_floats(metrics[k])
                                       for k in ("random_mean", "random_std", "random_min", "random_max")}},
        "swap": {"shift": dict(zip(groups, _json_floats(metrics["swap_shift"]), strict=True)),
                 "contrast_shift": _json_floats(metrics["swap_contrast_shift"])},
    }


def write_pair_outputs(folder: Path, record: dict[str, Any], tensors: dict[str, torch.Tensor]) -> None:
    """Write dose_response.json/.safetensors and the three PNGs of one pair into `folder` (already staged)."""
    folder.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in sorted(tensors.items())}, str(folder / f"{DOSE_RESPONSE_FILE}.safetensors"))
    record = {**record, "plots": {"efficacy": EFFICACY_PLOT, "shift": SHIFT_PLOT, "trajectory": TRAJECTORY_PLOT}}
    write_json(folder / f"{DOSE_RESPONSE_FILE}.json", record)
    _plot_efficacy(folder / EFFICACY_PLOT, record)
    _plot_shift(folder / SHIFT_PLOT, record)
    _plot_trajectory(folder / TRAJECTORY_PLOT, record, tensors)


def _named(record: dict[str, Any]) -> list[str]:
    """Return the non-random directions of a record."""
    return [n for n in record["directions"] if not n.startswith(RANDOM_PREFIX)]


def _plot_efficacy(path: Path, record: dict[str, Any]) -> None:
    """Efficacy vs α per direction, intervals as error bars, the random band (min..max) shaded."""
    alphas, random = record["alphas"], record["random"]
    fig = figure((6.4, 4.2))
    ax = fig.add_subplot()
    ax.fill_between(alphas, random["min"], random["max"], color="0.85", label=f"random ({len(random['names'])})")
    ax.plot(alphas, random["mean"], color="0.6", linestyle="--", linewidth=1)
    for name in _named(record):
        entry = record["directions"][name]
        low = [v - ci[0] for v, ci in zip(entry["efficacy"], entry["efficacy_ci"], strict=True)]
        high = [ci[1] - v for v, ci in zip(entry["efficacy"], entry["efficacy_ci"], strict=True)]
        ax.errorbar(alphas, entry["efficacy"], yerr=[low, high], marker="o", markersize=3, capsize=2, label=name)
    ax.axhline(1.0, color="k", linewidth=0.6, linestyle=":")
    ax.set(xlabel="α (× mean residual norm / ‖d‖)", ylabel="efficacy (1 = instruction swap)",
           title=f"{record['pair']}, {_layer_label(record)}")
    ax.legend(fontsize=7)
    save_png(fig, path)


def _plot_shift(path: Path, record: dict[str, Any]) -> None:
    """Mean action shift ‖Δa‖ per action group vs α, one panel per non-random direction."""
    names = _named(record)
    fig = figure((3.2 * len(names), 3.4))
    for i, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), i + 1)
        for group, values in record["directions"][name]["shift"].items():
            ax.plot(record["alphas"], values, marker="o", markersize=3, label=group)
        ax.set(xlabel="α", ylabel="mean ‖Δa‖ over the horizon" if i == 0 else None, title=name)
        ax.title.set_fontsize(8)
    fig.axes[0].legend(fontsize=7)
    save_png(fig, path)


def layer_label(layer: int, stream: str) -> str:
    """Return `layer L` (language model) or `expert layer K` (action expert): task run names, titles, logs."""
    return ("expert " if stream == "expert" else "") + f"layer {layer}"


def _layer_label(record: dict[str, Any]) -> str:
    return layer_label(record["layer"], record.get("stream", "lm"))


def _plot_trajectory(path: Path, record: dict[str, Any], tensors: dict[str, torch.Tensor]) -> None:
    """x, y, z over the horizon of the first negative-task frame, seed 0: unsteered (its own instruction),
    the first direction (residual_direction, decision_mean_difference) at its best α, and with the positive
    task's instruction (the swap)."""
    names, direction = list(record["directions"]), 0
    best = record["alphas"].index(record["directions"][names[0]]["best"]["alpha"])
    zero = record["alphas"].index(0.0)
    f = next(i for i, frame in enumerate(record["frames"]) if frame["side"] == "negative")
    steered, swap = tensors["actions"], tensors["swap_actions"]
    curves = {"α = 0": steered[direction, zero, f, 0], f"{names[0]}, α = {record['alphas'][best]:g}":
              steered[direction, best, f, 0], "positive instruction (swap)": steered[direction, zero, f, 0] + swap[f, 0]}
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


def _add_notes(notes: list[str], record: dict[str, Any]) -> None:
    """Append a record's notes (the settings' note, the in-sample warning) not yet in `notes`."""
    notes += [n for n in (record.get("note"), record.get("in_sample_note")) if n and n not in notes]


def _note_lines(notes: list[str]) -> list[str]:
    """Return the notes as bold markdown lines, then a blank line (nothing without notes)."""
    return [f"**{note}**" for note in notes] + ([""] if notes else [])


def write_layer_summary(layer_path: Path, pair_names: list[str]) -> Path:
    """Write summary.json and summary.md of one layer from its pairs' dose_response.json; return the .md path."""
    rows, notes = [], []
    for pair in pair_names:
        record = read_json(layer_path / pair / f"{DOSE_RESPONSE_FILE}.json")
        _add_notes(notes, record)
        for name in _named(record):
            best = record["directions"][name]["best"]
            rows.append({"pair": pair, "direction": name, **best})
    summary = {"format_version": EVAL_FORMAT_VERSION, "layer": layer_path.name, "notes": notes, "rows": rows}
    write_json(layer_path / SUMMARY_JSON, summary)
    md_path = layer_path / SUMMARY_MD
    with atomic_path(md_path) as tmp:
        tmp.write_text(summary_markdown(summary), encoding="utf-8")
    return md_path


def _fmt(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f}"


def summary_markdown(summary: dict[str, Any]) -> str:
    """Return the summary.md text: notes, then one table row per pair and direction."""
    groups = list(ACTION_GROUPS)
    lines = [f"# Steering evaluation, {summary['layer']}", ""]
    lines += _note_lines(summary["notes"])
    lines += [
        "Best α: the α ≠ 0 whose efficacy is closest to 1 (steering reproduces the instruction swap); z: efficacy "
        "against the random directions' band at that α; shift: mean ‖Δa‖ over the horizon per action group.", "",
        "| pair | direction | best α | efficacy [95% CI] | z vs random | " + " | ".join(groups) + " |",
        "|---|---|---|---|---|" + "---|" * len(groups),
    ]
    for row in summary["rows"]:
        low, high = row["efficacy_ci"]
        lines.append(f"| {row['pair']} | {row['direction']} | {row['alpha']:g} | {_fmt(row['efficacy'])} "
                     f"[{_fmt(low)}, {_fmt(high)}] | {_fmt(row['z'])} | "
                     + " | ".join(_fmt(row["shift"][g]) for g in groups) + " |")
    return "\n".join(lines) + "\n"


def _from_swap(best: dict[str, Any]) -> float:
    """Return how far a `best` entry's efficacy is from 1 (the instruction swap); a missing one is farthest."""
    return math.inf if best["efficacy"] is None else abs(best["efficacy"] - 1.0)


def best_named(record: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """Return the non-random direction whose efficacy at its best α is closest to 1, and its `best` entry."""
    name = min(_named(record), key=lambda n: _from_swap(record["directions"][n]["best"]))
    return name, record["directions"][name]["best"]


def write_pathways(eval_root: Path, layers: list[tuple[int, str]], pair_names: list[str]) -> Path:
    """Write pathways.json and pathways.md: per pair, the best language-model direction against the best
    action-expert one; `layers` are the evaluated (layer, stream). Return the .md path.

    "Best" is the direction (and layer) whose efficacy at its best α is closest to 1, as in the layer summaries.
    """
    rows, notes = [], []
    for pair in pair_names:
        row: dict[str, Any] = {"pair": pair}
        for stream in ("lm", "expert"):
            candidates = []
            for layer, where in layers:
                if where == stream:
                    record = read_json(eval_root / stream_layer_dir(layer, stream) / pair / f"{DOSE_RESPONSE_FILE}.json")
                    _add_notes(notes, record)
                    name, best = best_named(record)
                    candidates.append({"layer": layer, "direction": name, **best})
            row[stream] = min(candidates, key=_from_swap, default=None)
        rows.append(row)
    pathways = {"format_version": EVAL_FORMAT_VERSION, "notes": notes, "rows": rows}
    write_json(eval_root / f"{PATHWAYS_FILE}.json", pathways)
    md_path = eval_root / f"{PATHWAYS_FILE}.md"
    with atomic_path(md_path) as tmp:
        tmp.write_text(pathways_markdown(pathways), encoding="utf-8")
    return md_path


def pathways_markdown(pathways: dict[str, Any]) -> str:
    """Return the pathways.md text: one row per pair, the language model's best direction beside the expert's."""
    lines = ["# Steering pathways: language model vs action expert", ""]
    lines += _note_lines(pathways["notes"])
    lines += [
        "Per pair, the direction (over layers) whose efficacy at its best α is closest to 1 (the instruction "
        "swap), in the language model (SAE and mean-difference directions at the instruction tokens) and in the "
        "action expert (mean difference of the decision rows, at every action token); z: against the random "
        "directions of that layer.", "",
        "| pair | LM direction | LM efficacy [95% CI] | LM z | expert direction | expert efficacy [95% CI] | expert z |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in pathways["rows"]:
        cells = [row["pair"]]
        for stream in ("lm", "expert"):
            best = row[stream]
            if best is None:
                cells += ["–", "–", "–"]
                continue
            low, high = best["efficacy_ci"]
            cells += [f"{best['direction']}, layer {best['layer']}, α = {best['alpha']:g}",
                      f"{_fmt(best['efficacy'])} [{_fmt(low)}, {_fmt(high)}]",
                      _fmt(best["z"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
