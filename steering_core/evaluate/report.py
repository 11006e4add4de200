"""Outputs of the evaluation: per pair dose_response.json/.safetensors and PNGs, per layer summary.md/json,
and the comparison of the two pathways (language model vs action expert), pathways.md/json.

`dose_response.json` names the α grid `alphas` (in units of R) and `alpha_units`, the metric `efficacy`
(pooled, and per side: `efficacy_positive`, `efficacy_negative`; action std units, `efficacy_raw` in robot
units), the null directions `random` (and `permuted`), their p-values per direction (`p_random`, `p_permuted`),
the cross-fitting `selection` halves and the reference `swap`; its tensors (every metric, interval and the
raw robot actions) are in `dose_response.safetensors`. Nothing here reads a clock or a random state, so
equal inputs give byte-identical files.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

from steering_core.evaluate.directions import entry_name, entry_parts, is_null
from steering_core.evaluate.metrics import ACTION_GROUPS, holm, paired_difference
from steering_core.evaluate.plots import layer_label, named, plot_efficacy, plot_shift, plot_trajectory
from steering_core.evaluate.settings import MIN_EPISODES_PER_SIDE
from steering_core.layout import (
    DOSE_RESPONSE_FILE,
    EFFICACY_PLOT,
    PATHWAYS_FILE,
    SHIFT_PLOT,
    SUMMARY_JSON,
    SUMMARY_MD,
    TRAJECTORY_PLOT,
    stream_layer_dir,
)
from steering_core.storage.fileio import read_json, write_json, write_text

__all__ = ["layer_label", "pair_record", "write_layer_summary", "write_pair_outputs", "write_pathways"]

EVAL_FORMAT_VERSION = 3
_CURVES = tuple(f"{metric}{ci}" for metric in ("efficacy", "efficacy_positive", "efficacy_negative", "efficacy_raw",
                                                "efficacy_positive_raw", "efficacy_negative_raw", "cosine",
                                                "contrast_shift") for ci in ("", "_ci"))  # (dirs, alphas[, 2])
ALPHA_UNITS = {
    "alphas": "R, the mean residual norm of the training rows at the steered positions (instruction tokens; "
              "action tokens in the expert): α = 1 adds a vector of length R",
    "alphas_vector_units": "multiples of the stored direction d, α·R/‖d‖: what the server's `alpha` multiplies "
                           "(`\"alpha_units\": \"vector\"`); clamp entries: α itself, the level between the "
                           "frame's own concept's mean projection (0) and the other's (1)",
}
REFERENCE_METHOD = "mean_difference"  # every method is compared with it, paired, in the same mode


def _json_floats(tensor: torch.Tensor) -> Any:
    """Return a tensor as nested Python floats, NaN/inf as None (JSON has neither)."""
    values = tensor.double().tolist()
    if isinstance(values, float):
        return values if math.isfinite(values) else None
    return [_json_floats(torch.tensor(v, dtype=torch.float64)) if isinstance(v, list) else
            (v if math.isfinite(v) else None) for v in values]


def request_entry(head: dict[str, Any], name: str, alpha_vector: float) -> dict[str, Any] | None:
    """Return the server request's `steering` entry that pushes a negative-task frame as the evaluation did,
    or None for the action expert (the server steers the language model)."""
    if head["stream"] != "lm":
        return None
    method, mode = entry_parts(name)
    entry = {"pair": head["pair"], "layer": head["layer"], "direction": method, "alpha": alpha_vector}
    return entry | ({"alpha_units": "vector"} if mode == "add" else {"mode": mode})


def _direction_entry(d: int, name: str, head: dict[str, Any], alphas: tuple[float, ...],
                     metrics: dict[str, torch.Tensor], vector_scale: torch.Tensor, names: list[str],
                     holm_p: torch.Tensor | None) -> dict[str, Any]:
    """Return one direction's curves and its `best` entry (cross-fitted efficacy, p-values, the paired difference
    from the reference method in the same mode, request)."""
    groups = list(ACTION_GROUPS)
    method, mode = entry_parts(name)
    entry = {"method": method, "mode": mode, **{key: _json_floats(metrics[key][d]) for key in _CURVES}}
    entry |= {key: _json_floats(metrics[key][d]) for key in ("z", "p_random", "p_permuted") if key in metrics}
    entry["efficacy_half"] = _json_floats(metrics["efficacy_half"][:, d])
    entry["alphas_vector_units"] = _json_floats(vector_scale[d])
    if holm_p is not None:
        entry["p_random_holm"] = _json_floats(holm_p[d])
    for key in ("shift", "shift_ci", "shift_raw"):
        entry[key] = {g: _json_floats(metrics[key][d, :, i]) for i, g in enumerate(groups)}
    best = int(metrics["best_alpha_index"][d])
    alpha_vector = float(vector_scale[d, best])
    entry["best"] = {
        "alpha": alphas[best], "alpha_vector": alpha_vector, "reversed": alphas[best] < 0,
        **{key.replace("crossfit", "efficacy"): _json_floats(metrics[key][d]) for key in
           ("crossfit", "crossfit_ci", "crossfit_positive", "crossfit_positive_ci", "crossfit_negative",
            "crossfit_negative_ci")},
        "selected_alphas": [alphas[int(i)] for i in metrics["crossfit_alpha_index"][:, d]],
        "efficacy_all_frames": entry["efficacy"][best],
        **{key: _json_floats(metrics[f"best_{key}"][d]) for key in ("z", "p_random", "p_permuted")
           if f"best_{key}" in metrics},
        "shift": {g: entry["shift"][g][best] for g in groups},
        "shift_raw": {g: entry["shift_raw"][g][best] for g in groups},
        "contrast_shift": entry["contrast_shift"][best],
        "request": request_entry(head, name, alpha_vector),
    }
    if holm_p is not None:
        entry["best"]["p_random_holm"] = entry["p_random_holm"][best]
    reference = entry_name(REFERENCE_METHOD, mode)
    if not is_null(name) and reference in names and reference != name:
        other = names.index(reference)
        difference, ci = paired_difference(metrics["crossfit"], metrics["crossfit_boot"], d, other)
        closeness = [-(metrics[key] - 1).abs() for key in ("crossfit", "crossfit_boot")]  # 0 at the swap itself
        gain, gain_ci = paired_difference(*closeness, d, other)
        entry["best"]["vs_reference"] = {  # NaN (None) where a half holds no frames of a side
            "reference": reference, **{key: _json_floats(torch.tensor(value, dtype=torch.float64)) for key, value in
                                       (("difference", difference), ("ci", ci), ("gain", gain), ("gain_ci", gain_ci))}}
    return entry


def holm_family(names: list[str], metrics: dict[str, torch.Tensor], zero_index: int) -> torch.Tensor | None:
    """Return (D, A) Holm-adjusted p against the random null over the family of every tested entry (method × mode)
    at every α ≠ 0; NaN at α = 0 and for the nulls. None without a random null."""
    if "p_random" not in metrics:
        return None
    p = metrics["p_random"].double()
    family = torch.zeros_like(p, dtype=torch.bool)
    family[[i for i, n in enumerate(names) if not is_null(n)]] = True
    family[:, zero_index] = False
    out = torch.full_like(p, math.nan)
    out[family] = holm(p[family])
    return out


def pair_record(head: dict[str, Any], names: list[str], alphas: tuple[float, ...],
                metrics: dict[str, torch.Tensor], vector_scale: torch.Tensor) -> dict[str, Any]:
    """Return the JSON of one pair's dose-response (`head` holds pair, layer, stream, split, frames, selection...)."""
    groups = list(ACTION_GROUPS)
    holm_p = holm_family(names, metrics, alphas.index(0.0))
    directions = {name: _direction_entry(d, name, head, alphas, metrics, vector_scale, names, holm_p)
                  for d, name in enumerate(names)}
    return {
        "format_version": EVAL_FORMAT_VERSION,
        **head,
        "alphas": list(alphas),
        "alpha_units": ALPHA_UNITS,
        "metric": "efficacy",
        "action_groups": groups,
        "directions": directions,
        "random": {"names": [n for n in names if n.startswith("random_")],
                   "permuted": [n for n in names if n.startswith("permuted_")],
                   **{key: _json_floats(metrics[f"random_{key}"]) for key in ("mean", "std", "low", "high")}},
        "swap": {"shift": dict(zip(groups, _json_floats(metrics["swap_shift"]), strict=True)),
                 "shift_raw": dict(zip(groups, _json_floats(metrics["swap_shift_raw"]), strict=True)),
                 "contrast_shift": _json_floats(metrics["swap_contrast_shift"])},
    }


def write_pair_outputs(folder: Path, record: dict[str, Any], tensors: dict[str, torch.Tensor]) -> None:
    """Write dose_response.json/.safetensors and the three PNGs of one pair into `folder` (already staged)."""
    folder.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in sorted(tensors.items())}, str(folder / f"{DOSE_RESPONSE_FILE}.safetensors"))
    record = {**record, "plots": {"efficacy": EFFICACY_PLOT, "shift": SHIFT_PLOT, "trajectory": TRAJECTORY_PLOT}}
    write_json(folder / f"{DOSE_RESPONSE_FILE}.json", record)
    plot_efficacy(folder / EFFICACY_PLOT, record)
    plot_shift(folder / SHIFT_PLOT, record)
    plot_trajectory(folder / TRAJECTORY_PLOT, record, tensors)


# ----------------------------------------------------------------------------- per layer


def record_warnings(record: dict[str, Any]) -> list[str]:
    """Return the record's notes and warnings: the settings' note, in-sample, too few episodes, shared halves."""
    notes = [n for n in (record.get("note"), record.get("in_sample_note"), record.get("positions_note"),
                         record.get("null", {}).get("note")) if n]
    episodes = record["episodes"]
    if min(episodes.values()) < MIN_EPISODES_PER_SIDE:
        notes.append(f"{record['pair']}: {episodes['positive']} positive / {episodes['negative']} negative held-out "
                     f"episodes; below {MIN_EPISODES_PER_SIDE} per side the episode bootstrap has too few distinct "
                     "resamples: intervals unreliable")
    if record.get("include_decoder_bias"):
        notes.append(f"{record['pair']}: residual_direction was written with --include-decoder-bias (the seed's "
                     "decode(Δ)): it carries the SAE's b_dec, a constant offset, not only the concepts' difference")
    if record["selection"]["by"] == "frames":
        notes.append(f"{record['pair']}: a side has one held-out episode, so the selection and report halves split "
                     "its frames (not independent)")
    return notes


def write_layer_summary(layer_path: Path, pair_names: list[str]) -> Path:
    """Write summary.json and summary.md of one layer from its pairs' dose_response.json; return the .md path."""
    rows, notes, plots = [], [], {}
    for pair in pair_names:
        record = read_json(layer_path / pair / f"{DOSE_RESPONSE_FILE}.json")
        notes += [n for n in record_warnings(record) if n not in notes]
        plots[pair] = f"{pair}/{EFFICACY_PLOT}"
        for name in named(record):
            entry = record["directions"][name]
            rows.append({"pair": pair, "direction": name, "method": entry["method"], "mode": entry["mode"],
                         **entry["best"]})
    summary = {"format_version": EVAL_FORMAT_VERSION, "layer": layer_path.name, "notes": notes, "rows": rows,
               "plots": plots}
    write_json(layer_path / SUMMARY_JSON, summary)
    md_path = layer_path / SUMMARY_MD
    write_text(md_path, summary_markdown(summary))
    return md_path


def fmt(value: float | None) -> str:
    """Return a number with 3 decimals, or – for a missing one."""
    return "–" if value is None else f"{value:.3f}"


def with_ci(value: float | None, ci: list[float | None]) -> str:
    """Return `value [low, high]`."""
    return f"{fmt(value)} [{fmt(ci[0])}, {fmt(ci[1])}]"


def alpha_text(row: dict[str, Any]) -> str:
    """Return `α (R) / α (vector)` with the reversed flag."""
    return f"{row['alpha']:g} / {row['alpha_vector']:.4g}" + (" reversed?" if row["reversed"] else "")


SELECTION_TEXT = (
    "Best α (in units of R, the mean residual norm at the steered positions / in multiples of the stored vector, "
    "what the server multiplies): the α ≠ 0 whose efficacy over all held-out frames is closest to 1; a negative "
    "one is flagged `reversed?` (the direction pushes away from the task it names). Efficacy (action std units; "
    "1 = steering reproduces the instruction swap, 0 = no effect) is cross-fitted: α is chosen on one half of "
    "the held-out episodes and read on the other, both ways, averaged. Every frame is steered toward the other "
    "task; `positive`/`negative` are the frames of that task. 95% intervals resample episodes. p: rank among the "
    "null directions, (1 + #null ≥ observed) / (1 + N): random ones with the training rows' covariance, each "
    "through the same selection; mean differences of episode labels permuted, at their own (smaller) size and "
    "the row's α. The nulls are added (not clamped) and shared by every method: a clamp row is ranked against "
    "them at the same α. Holm: the per-α p against the random null, adjusted over every method × mode × α ≠ 0 "
    "of the pair, read at the row's α. Gain vs mean_difference: how much closer to the instruction swap "
    "(efficacy 1) the row's cross-fitted efficacy is than the mean difference's in the same mode, "
    "|1 − e_mean_difference| − |1 − e| (positive: closer; overshooting 1 is not better), with a paired interval "
    "(the same resampled episodes for both); the plain difference of efficacies is in summary.json.\n\n"
    "Modes: add puts h + α·R·d̂ at the steered tokens; clamp sets each steered token's projection on d̂ to "
    "m_own + α·(m_other − m_own), the two concepts' mean projections (α = 1: the other concept's level, no "
    "overshoot whatever the token's start).")


def summary_markdown(summary: dict[str, Any]) -> str:
    """Return the summary.md text: notes, the table, the request entries, the shifts and the plots."""
    groups = list(ACTION_GROUPS)
    lines = [f"# Steering evaluation, {summary['layer']}", ""]
    lines += [f"**{note}**" for note in summary["notes"]] + ([""] if summary["notes"] else [])
    lines += [SELECTION_TEXT, "", "| pair | method | mode | α (R / vector) | efficacy [95% CI] | "
              "gain vs mean_difference [95% CI] | positive-task frames | negative-task frames | p random | "
              "p random, Holm | p permuted |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in summary["rows"]:
        versus = row.get("vs_reference")
        lines.append(f"| {row['pair']} | {row['method']} | {row['mode']} | {alpha_text(row)} | "
                     f"{with_ci(row['efficacy'], row['efficacy_ci'])} | "
                     f"{with_ci(versus['gain'], versus['gain_ci']) if versus else '–'} | "
                     f"{with_ci(row['efficacy_positive'], row['efficacy_positive_ci'])} | "
                     f"{with_ci(row['efficacy_negative'], row['efficacy_negative_ci'])} | "
                     f"{fmt(row.get('p_random'))} | {fmt(row.get('p_random_holm'))} | {fmt(row.get('p_permuted'))} |")
    requests = [row for row in summary["rows"] if row["request"] is not None]
    if requests:
        lines += ["", "Server request entry of each row (`steering`: pushes a negative-task frame toward the "
                      "positive task, as evaluated; negate `alpha` for the other way):", ""]
        lines += [f"- {row['pair']}, {row['direction']}: `{json.dumps(row['request'])}`" for row in requests]
    lines += ["", "Action shift at the best α, mean ‖Δa‖ over the horizon in action std units (raw units in "
                  "dose_response.json); contrast: the contrast state axis's rate toward the other task:", "",
              "| pair | direction | " + " | ".join(groups) + " | contrast |", "|---|---|" + "---|" * (len(groups) + 1)]
    for row in summary["rows"]:
        lines.append(f"| {row['pair']} | {row['direction']} | " + " | ".join(fmt(row["shift"][g]) for g in groups)
                     + f" | {fmt(row['contrast_shift'])} |")
    lines += [""] + [f"![{pair}]({path})" for pair, path in summary["plots"].items()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- pathways


def cross_fitted_choice(candidates: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Return the cross-fitted best of (layer, direction, α) candidates, each with `efficacy_half` (2, alphas).

    On each half the candidate and α ≠ 0 closest to 1 is chosen and its efficacy read on the other half;
    `efficacy` is the mean of both reads, `chosen` the two choices (selected on half 0, on half 1).
    """
    if not candidates:
        return None
    chosen, reads = [], []
    for half in (0, 1):
        options = [(abs(c["efficacy_half"][half][a] - 1.0), i, a) for i, c in enumerate(candidates)
                   for a, alpha in enumerate(c["alphas"]) if alpha != 0 and c["efficacy_half"][half][a] is not None]
        if not options:
            return None
        _, i, a = min(options)
        c = candidates[i]
        chosen.append({"layer": c["layer"], "direction": c["direction"], "alpha": c["alphas"][a],
                       "alpha_vector": c["alphas_vector_units"][a]})
        reads.append(c["efficacy_half"][1 - half][a])
    value = None if None in reads else sum(reads) / 2
    return {"chosen": chosen, "efficacy_reads": reads, "efficacy": value}


def write_pathways(eval_root: Path, layers: list[tuple[int, str]], pair_names: list[str]) -> Path:
    """Write pathways.json and pathways.md: per pair, the best language-model direction against the best
    action-expert one, each chosen (layer, direction, α) on one half of the held-out episodes and read on the
    other, both ways; `layers` are the evaluated (layer, stream). Return the .md path."""
    rows, notes = [], []
    for pair in pair_names:
        row: dict[str, Any] = {"pair": pair}
        for stream in ("lm", "expert"):
            candidates = []
            for layer, where in layers:
                if where == stream:
                    record = read_json(eval_root / stream_layer_dir(layer, stream) / pair / f"{DOSE_RESPONSE_FILE}.json")
                    notes += [n for n in record_warnings(record) if n not in notes]
                    candidates += [{"layer": layer, "direction": name, "alphas": record["alphas"],
                                    **{k: record["directions"][name][k] for k in ("efficacy_half", "alphas_vector_units")}}
                                   for name in named(record)]
            row[stream] = cross_fitted_choice(candidates)
        rows.append(row)
    pathways = {"format_version": EVAL_FORMAT_VERSION, "notes": notes, "rows": rows}
    write_json(eval_root / f"{PATHWAYS_FILE}.json", pathways)
    md_path = eval_root / f"{PATHWAYS_FILE}.md"
    write_text(md_path, pathways_markdown(pathways))
    return md_path


def _choice_text(choice: dict[str, Any]) -> str:
    return f"{choice['direction']}, layer {choice['layer']}, α = {choice['alpha']:g} R ({choice['alpha_vector']:.4g} d)"


def pathways_markdown(pathways: dict[str, Any]) -> str:
    """Return the pathways.md text: one row per pair, the language model's best direction beside the expert's."""
    lines = ["# Steering pathways: language model vs action expert", ""]
    lines += [f"**{note}**" for note in pathways["notes"]] + ([""] if pathways["notes"] else [])
    lines += [
        "Per pair and pathway, the (layer, direction, α) whose efficacy is closest to 1 (the instruction swap) on "
        "one half of the held-out episodes, read on the other half, both ways: language model (SAE and "
        "mean-difference directions at the instruction tokens) and action expert (mean difference of the decision "
        "rows, at every action token). Efficacy: the mean of the two reads (action std units).", "",
        "| pair | LM: chosen on half 0 / on half 1 | LM efficacy | expert: chosen on half 0 / on half 1 | "
        "expert efficacy |", "|---|---|---|---|---|",
    ]
    for row in pathways["rows"]:
        cells = [row["pair"]]
        for stream in ("lm", "expert"):
            best = row[stream]
            if best is None:
                cells += ["–", "–"]
                continue
            texts = [_choice_text(c) for c in best["chosen"]]
            cells += [texts[0] if texts[0] == texts[1] else " / ".join(texts), fmt(best["efficacy"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
