"""Reports of the rollouts: per pair `cells.md`/`cells.json` (one row per cell) and the two PNGs, per layer
`summary.md`/`summary.json` (one row per pair and side, the plots and first-episode videos linked, and a
plain-language answer: does steering toward the other task beat the random controls and α = 0?).

Layout: ROLLOUTS_ROOT/layerNN/<pair>/<cell>/rollouts.json (records.write_cell), the pair files in <pair>/, the
summaries in layerNN/. α is in residual_norm units (× R), the evaluation phase's unit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from steering_core.layout import JOINTS_PLOT, ROLLOUT_FILE, ROLLOUT_PAIR_TABLE, SUCCESS_PLOT, SUMMARY_JSON, SUMMARY_MD
from steering_core.pairs import SIDES
from steering_core.rollout.cells import KINDS
from steering_core.rollout.plots import Thresholds, plot_joints, plot_success
from steering_core.rollout.records import ROLLOUT_FORMAT_VERSION, read_cell
from steering_core.rollout.stats import Proportion, exceeds
from steering_core.storage.fileio import read_json, write_json, write_text

OUTCOME_COLUMNS = ("toward", "instructed", "neither")
ANSWER_TEXT = (
    "Per pair and side: the steered direction's best α toward the other task (its highest toward-task success, "
    "the smallest α on ties) against the random band's upper edge at that α (the random direction with the most "
    "toward-task successes) and against α = 0. `yes` only when the steered Wilson 95% interval lies wholly above "
    "both; overlapping intervals are `no evidence` (the best α is chosen on these same episodes, so only a clear "
    "gap counts). The instruction swap (the other task's instruction, no steering) is the ceiling.")


def read_pair_cells(pair_path: Path, cell_dirs: Sequence[Path] | None = None
                    ) -> list[tuple[dict[str, Any], dict[str, np.ndarray]]]:
    """Return (record, arrays) of the cells `cell_dirs` (default: every complete cell of the pair folder), by side,
    kind, condition and α toward."""
    if cell_dirs is None:
        cell_dirs = [path.parent for path in pair_path.glob(f"*/{ROLLOUT_FILE}.json")]
    cells = [read_cell(path) for path in cell_dirs]
    if not cells:
        raise FileNotFoundError(f"{pair_path}: no rollout cells ({ROLLOUT_FILE}.json in its subfolders)")
    return sorted(cells, key=lambda c: (SIDES.index(c[0]["side"]), KINDS.index(c[0]["kind"]), c[0]["condition"],
                                        c[0]["alpha_toward"]))


def success(record: dict[str, Any], outcome: str = "toward") -> Proportion:
    """Return one outcome's count of a cell record as a Proportion."""
    return Proportion(**record["success"][outcome])


def cell_row(record: dict[str, Any]) -> dict[str, Any]:
    """Return the pair table's row of one cell."""
    return {key: record[key] for key in ("side", "condition", "alpha", "alpha_toward", "cell")} | {
        "n": success(record).n, **{outcome: record["success"][outcome] for outcome in OUTCOME_COLUMNS},
        **{key: record[key] for key in ("mean_steps", "mean_jerk", "joint_limit_hits")},
        "first_outcome": record["episodes"][0]["outcome"]}


def _at(records: Sequence[dict[str, Any]], kind: str, alpha_toward: float | None = None) -> list[dict[str, Any]]:
    return [r for r in records if r["kind"] == kind
            and (alpha_toward is None or math.isclose(r["alpha_toward"], alpha_toward, abs_tol=1e-9))]


def side_answer(records: Sequence[dict[str, Any]], side: str) -> dict[str, Any]:
    """Return one side's comparison (see `_side_answer`), saying when the other task's goal already held at the
    start of some episodes (then only breaking it and reaching it again counts)."""
    cells = [r for r in records if r["side"] == side]
    row = _side_answer(cells, side)
    at_start, episodes = sum(r["toward_at_start"] for r in cells), sum(len(r["episodes"]) for r in cells)
    if at_start:
        row["toward_at_start"] = {"k": at_start, "n": episodes}
        row["text"] += (f"; the other task's goal already held at the start of {at_start} of {episodes} episodes (its "
                        "start state is this side's goal, e.g. an open drawer to close): only undoing and redoing it "
                        "counts, so read the instructed success and the joint trajectories")
    return row


def _side_answer(cells: Sequence[dict[str, Any]], side: str) -> dict[str, Any]:
    """Return one side's comparison: the steered best α, the random edge, α = 0, wrong concepts, the ceiling and
    `answer` ("yes" / "no evidence") with `text` saying why (see ANSWER_TEXT)."""
    steered = [r for r in _at(cells, "steered") if r["alpha_toward"] > 0]
    swap, zero = _at(cells, "instruction_swap"), _at(cells, "unsteered")
    row: dict[str, Any] = {"side": side, "ceiling": success(swap[0]).to_json() if swap else None}
    if not steered:
        return row | {"answer": "no evidence", "text": "no steered cells with α toward the other task > 0"}
    best = max(steered, key=lambda r: (success(r).k / success(r).n, -r["alpha_toward"]))
    alpha = best["alpha_toward"]
    randoms = _at(cells, "random", alpha)
    edge = max(randoms, key=lambda r: success(r).k / success(r).n) if randoms else None
    found = success(best)
    row |= {"alpha_toward": alpha, "alpha": best["alpha"], "steered": found.to_json(),
            "random_edge": success(edge).to_json() if edge else None, "random_count": len(randoms),
            "unsteered": success(zero[0]).to_json() if zero else None,
            "wrong_concept": {r["condition"].partition(":")[2]: success(r).to_json()
                              for r in _at(cells, "wrong_concept", alpha)}}
    controls = [(f"the random band's upper edge of {len(randoms)} directions", row["random_edge"],
                 "no random controls at this α to compare"), ("α = 0", row["unsteered"], "no α = 0 cell to compare")]
    missing = [absent for _, entry, absent in controls if entry is None]
    gaps = [(name, Proportion(**entry)) for name, entry, _ in controls if entry is not None]
    overlapping = [f"{name} ({other.text()})" for name, other in gaps if not exceeds(found, other)]
    ceiling = f"; ceiling (instruction swap) {Proportion(**row['ceiling']).text()}" if swap else ""
    head = f"steered toward-task success at α = {alpha:+g} is {found.text()}"
    if not missing and not overlapping:
        text = f"yes: {head}, above " + " and ".join(f"{n} ({o.text()})" for n, o in gaps) + ceiling
        return row | {"answer": "yes", "text": text}
    why = missing + ([f"its interval overlaps {' and '.join(overlapping)}"]
                                                            if overlapping else [])
    return row | {"answer": "no evidence", "text": f"no evidence: {head}; " + "; ".join(why) + ceiling}


def write_pair_report(pair_path: Path, thresholds: Thresholds | None = None,
                      cell_dirs: Sequence[Path] | None = None) -> dict[str, Any]:
    """Write the pair's PNGs and cells.md/cells.json from its cell folders (`cell_dirs`, default all of them);
    return the pair summary (cells.json).

    `thresholds`: per goal-tested joint, (goal label, qpos threshold) drawn on the joint plot (default: those the
    cells recorded).
    """
    cells = read_pair_cells(pair_path, cell_dirs)
    records = [record for record, _ in cells]
    if thresholds is None:  # the goals' boundaries each chunk recorded (run.thresholds)
        thresholds = {joint: [tuple(entry) for entry in entries] for r in records
                      for joint, entries in r["run"].get("thresholds", {}).items()}
    tasks = {side: next(r["instructed"] for r in records if r["side"] == side)
             for side in SIDES if any(r["side"] == side for r in records)}
    plots = {"success": SUCCESS_PLOT}
    plot_success(pair_path / SUCCESS_PLOT, records)
    if any(r["joints"] for r in records):  # goals on articulated objects (drawer, knob) only
        plots["joints"] = JOINTS_PLOT
        plot_joints(pair_path / JOINTS_PLOT, cells, thresholds)
    summary = {
        "format_version": ROLLOUT_FORMAT_VERSION,
        "pair": records[0]["pair"], "layer": records[0]["layer"],
        "episodes_per_cell": max(success(r).n for r in records),
        "tasks": tasks,
        "answers": [side_answer(records, side) for side in tasks],
        "cells": [cell_row(r) for r in records],
        "plots": plots,
        "videos": {r["cell"]: f"{r['cell']}/{r['episodes'][0]['video']}" for r in records if r["episodes"][0]["video"]},
    }
    write_json(pair_path / f"{ROLLOUT_PAIR_TABLE}.json", summary)
    write_text(pair_path / f"{ROLLOUT_PAIR_TABLE}.md", pair_markdown(summary))
    return summary


def _number(value: float | None, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}g}"


def _proportion(entry: dict[str, Any] | None) -> str:
    return "–" if entry is None else Proportion(**entry).text()


def pair_markdown(summary: dict[str, Any]) -> str:
    """Return cells.md: the pair's tasks, one row per cell, the plots."""
    lines = [f"# Rollouts of {summary['pair']}, layer {summary['layer']}", ""]
    lines += [f"- {side} side: {task['instruction']!r} ({task['suite']} task {task['index']})"
              for side, task in summary["tasks"].items()]
    lines += ["", "Success: k/n episodes [Wilson 95%]; the first goal reached ends an episode. α in × R; α toward: "
                  "the push toward the other task. Jerk: RMS third difference of the arm joints (rad/step³).", "",
              "| side | condition | α | α toward | n | toward | instructed | neither | mean steps | mean jerk | "
              "joint-limit hits |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in summary["cells"]:
        lines.append(f"| {row['side']} | {row['condition']} | {row['alpha']:+g} | {row['alpha_toward']:+g} | "
                     f"{row['n']} | "
                     + " | ".join(_proportion(row[o]) for o in OUTCOME_COLUMNS)
                     + f" | {_number(row['mean_steps'])} | {_number(row['mean_jerk'])} | {row['joint_limit_hits']} |")
    lines += [""] + [f"![{name}]({path})\n" for name, path in summary["plots"].items()]
    return "\n".join(lines) + "\n"


def write_layer_summary(layer_path: Path, pair_names: Sequence[str], note: str | None = None) -> Path:
    """Write summary.json and summary.md of one layer from its pairs' cells.json; return the .md path.

    `note` is said first, in bold (e.g. that the policy is a tiny random model, whose success says nothing).
    """
    pairs = [read_json(layer_path / pair / f"{ROLLOUT_PAIR_TABLE}.json") for pair in pair_names]
    summary = {"format_version": ROLLOUT_FORMAT_VERSION, "layer": layer_path.name, "note": note,
               "alpha_units": "residual_norm: × R, the mean residual norm at the steered positions (the evaluation's "
                              "unit)", "pairs": pairs}
    write_json(layer_path / SUMMARY_JSON, summary)
    md_path = layer_path / SUMMARY_MD
    write_text(md_path, summary_markdown(summary))
    return md_path


def write_layer(layer_path: Path, cells: Mapping[str, Sequence[Path]], note: str | None = None) -> Path:
    """Write the report of every pair whose cells (pair -> cell folders of the current grid) are all done, then the
    layer's summary; return its .md path."""
    done = [name for name, folders in cells.items() if all((f / f"{ROLLOUT_FILE}.json").is_file() for f in folders)]
    for name in done:
        write_pair_report(layer_path / name, cell_dirs=cells[name])
    return write_layer_summary(layer_path, done, note=note)


def summary_markdown(summary: dict[str, Any]) -> str:
    """Return summary.md: the note, the answers table, the plain-language answers, the plots and the videos."""
    lines = [f"# Closed-loop steered rollouts, {summary['layer']}", ""]
    lines += [f"**{summary['note']}**", ""] if summary["note"] else []
    lines += [ANSWER_TEXT + " α in × R (the evaluation's unit), toward the other task.", "",
              "| pair | side | best α toward | steered: toward | random edge | α = 0 | wrong concept | "
              "instruction swap (ceiling) | answer |", "|---|---|---|---|---|---|---|---|---|"]
    for pair in summary["pairs"]:
        for row in pair["answers"]:
            wrong = ", ".join(f"{name} {_proportion(p)}" for name, p in row.get("wrong_concept", {}).items()) or "–"
            alpha = f"{row['alpha_toward']:+g}" if "alpha_toward" in row else "–"
            lines.append(f"| [{pair['pair']}]({pair['pair']}/{ROLLOUT_PAIR_TABLE}.md) | {row['side']} | {alpha} | "
                         f"{_proportion(row.get('steered'))} | {_proportion(row.get('random_edge'))} | "
                         f"{_proportion(row.get('unsteered'))} | {wrong} | {_proportion(row['ceiling'])} | "
                         f"{row['answer']} |")
    for pair in summary["pairs"]:
        name = pair["pair"]
        lines += ["", f"## {name}", ""]
        lines += [f"- {row['side']} side ({pair['tasks'][row['side']]['instruction']!r} pushed toward the other "
                  f"task): {row['text']}" for row in pair["answers"]]
        lines += [""] + [f"![{name}: {plot}]({name}/{path})\n" for plot, path in pair["plots"].items()]
        lines += ["First episode of each cell (agentview MP4), by α toward the other task and outcome:", ""]
        by_condition: dict[str, list[str]] = {}
        for cell in pair["cells"]:
            if cell["cell"] in pair["videos"]:
                by_condition.setdefault(f"{cell['side']}, {cell['condition']}", []).append(
                    f"[{cell['alpha_toward']:+g} {cell['first_outcome']}]({name}/{pair['videos'][cell['cell']]})")
        lines += [f"- {key}: " + " · ".join(links) for key, links in by_condition.items()] or ["- none recorded"]
    return "\n".join(lines) + "\n"
