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
from steering_core.rollout.stats import Paired, Proportion, mcnemar, proportion
from steering_core.storage.fileio import read_json, write_json, write_text

OUTCOME_COLUMNS = ("toward", "instructed", "neither")
EVIDENCE_P = 0.05  # one-sided exact McNemar p below which a paired difference counts as evidence
ANSWER_TEXT = (
    "Per pair and side, cross-fitted: the steered direction's best α toward the other task (its highest toward-task "
    "success, the smallest α on ties) is chosen on one half of the initial states and read on the other, both ways, "
    "so no episode scores the α it chose. Cells share initial states and seeds, so every comparison is paired: "
    f"`yes` only when the exact McNemar test (one-sided, p < {EVIDENCE_P:g}) finds the cross-fitted steered cell "
    "above α = 0 and above every random direction read the same way; otherwise `no evidence`. Wilson 95% intervals "
    "are shown beside; the instruction swap (the other task's instruction, no steering) is the ceiling.")

Outcomes = dict[tuple[int, int], bool]  # (initial state, seed) -> reached the other task's goal


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


def cell_row(record: dict[str, Any], unsteered: Outcomes | None = None) -> dict[str, Any]:
    """Return the pair table's row of one cell; `unsteered`: its side's α = 0 episodes, to test it against."""
    vs_unsteered = None if unsteered is None or record["kind"] == "unsteered" else paired(outcomes(record), unsteered)
    return {key: record[key] for key in ("side", "condition", "alpha", "alpha_toward", "cell")} | {
        "n": success(record).n, **{outcome: record["success"][outcome] for outcome in OUTCOME_COLUMNS},
        **{key: record[key] for key in ("mean_steps", "mean_jerk", "joint_limit_hits")},
        "first_outcome": record["episodes"][0]["outcome"],
        "vs_unsteered": vs_unsteered.to_json() if vs_unsteered else None}


def cell_rows(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Return the pair table's rows, each cell tested against its side's α = 0 cell on the paired episodes."""
    zero = {r["side"]: outcomes(r) for r in _at(records, "unsteered")}
    return [cell_row(r, zero.get(r["side"])) for r in records]


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


def outcomes(record: Mapping[str, Any], outcome: str = "toward") -> Outcomes:
    """Return each episode of a cell record, keyed by its (initial state, seed), to whether it ended in `outcome`."""
    return {(row["init_index"], row["seed"]): row["outcome"] == outcome for row in record["episodes"]}


def paired(a: Outcomes, b: Outcomes) -> Paired:
    """Return the exact McNemar test of `a` above `b` on the episodes both ran."""
    keys = sorted(a.keys() & b.keys())
    return mcnemar([a[key] for key in keys], [b[key] for key in keys])


def crossfit(steered: Mapping[float, Outcomes]) -> tuple[tuple[float, float], list[list[tuple[int, int]]]]:
    """Return the α chosen on each half of the episodes, and the halves (sorted episodes, alternately).

    Half h's α is the one with the most successes on half h (the smallest α on ties); it is read on half 1 − h.
    """
    keys = sorted(set.intersection(*(set(cell) for cell in steered.values())))
    halves = [keys[0::2], keys[1::2]]
    chosen = tuple(max(sorted(steered), key=lambda alpha: (sum(steered[alpha][k] for k in half), -alpha))
                   for half in halves)
    return chosen, halves


def read_crossfit(cells: Mapping[float, Outcomes], chosen: tuple[float, float],
                  halves: list[list[tuple[int, int]]]) -> Outcomes | None:
    """Return the episodes of half 1 − h read at the α chosen on half h, both ways; None when a cell is missing."""
    if any(alpha not in cells for alpha in chosen):
        return None
    return {key: cells[chosen[h]][key] for h in (0, 1) for key in halves[1 - h] if key in cells[chosen[h]]}


def _by_condition(cells: Sequence[dict[str, Any]]) -> dict[str, dict[float, Outcomes]]:
    """Return condition -> α toward -> the cell's outcomes."""
    grouped: dict[str, dict[float, Outcomes]] = {}
    for record in cells:
        grouped.setdefault(record["condition"], {})[record["alpha_toward"]] = outcomes(record)
    return grouped


def _side_answer(cells: Sequence[dict[str, Any]], side: str) -> dict[str, Any]:
    """Return one side's comparison: the steered best α (on all episodes, as plotted), the cross-fitted steered
    success and its McNemar tests against α = 0 and every control, the ceiling, and `answer` ("yes" /
    "no evidence") with `text` saying why (see ANSWER_TEXT)."""
    steered = [r for r in _at(cells, "steered") if r["alpha_toward"] > 0]
    swap, zero = _at(cells, "instruction_swap"), _at(cells, "unsteered")
    row: dict[str, Any] = {"side": side, "ceiling": success(swap[0]).to_json() if swap else None}
    if not steered:
        return row | {"answer": "no evidence", "text": "no steered cells with α toward the other task > 0"}
    best = max(steered, key=lambda r: (success(r).k / success(r).n, -r["alpha_toward"]))
    alpha = best["alpha_toward"]
    randoms = _at(cells, "random", alpha)
    edge = max(randoms, key=lambda r: success(r).k / success(r).n) if randoms else None
    row |= {"alpha_toward": alpha, "alpha": best["alpha"], "steered": success(best).to_json(),
            "random_edge": success(edge).to_json() if edge else None, "random_count": len(randoms),
            "unsteered": success(zero[0]).to_json() if zero else None,
            "wrong_concept": {r["condition"].partition(":")[2]: success(r).to_json()
                              for r in _at(cells, "wrong_concept", alpha)}}
    conditions = _by_condition(cells)
    chosen, halves = crossfit({r["alpha_toward"]: outcomes(r) for r in steered})
    found = read_crossfit(conditions["steered"], chosen, halves)
    tests = {"α = 0": paired(found, outcomes(zero[0]))} if zero else {}
    for condition, by_alpha in conditions.items():
        control = read_crossfit(by_alpha, chosen, halves) if condition.startswith(("random", "wrong")) else None
        if control is not None:
            tests[condition] = paired(found, control)
    steered_rate = proportion(sum(found.values()), len(found))
    row["crossfit"] = {"alphas_toward": list(chosen), "steered": steered_rate.to_json(),
                       "mcnemar": {name: test.to_json() for name, test in tests.items()}}
    random_tests = {name: test for name, test in tests.items() if name.startswith("random")}
    missing = ([] if random_tests else ["no random controls at the chosen α to compare"]) + (
        [] if zero else ["no α = 0 cell to compare"])
    failing = [f"α = 0 (p = {test.p_greater:.3g}, {test.only_a} vs {test.only_b} discordant episodes)"
               for test in [tests.get("α = 0")] if test is not None and test.p_greater >= EVIDENCE_P]
    beaten = [test for test in random_tests.values() if test.p_greater >= EVIDENCE_P]
    if beaten:
        failing.append(f"{len(beaten)} of {len(random_tests)} random directions (largest p = "
                       f"{max(test.p_greater for test in beaten):.3g})")
    ceiling = f"; ceiling (instruction swap) {Proportion(**row['ceiling']).text()}" if swap else ""
    head = (f"cross-fitted steered toward-task success (α chosen on each half of the initial states: {chosen[0]:+g} and "
            f"{chosen[1]:+g}, each read on the other half) is {steered_rate.text()}")
    if not missing and not failing:
        worst = max(random_tests.values(), key=lambda test: test.p_greater)
        text = (f"yes: {head}, above α = 0 (exact McNemar p = {tests['α = 0'].p_greater:.3g}) and each of "
                f"{len(random_tests)} random directions (p ≤ {worst.p_greater:.3g}) on the paired episodes{ceiling}")
        return row | {"answer": "yes", "text": text}
    why = missing + ([f"not above {' and '.join(failing)} at p < {EVIDENCE_P:g}"] if failing else [])
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
        "cells": cell_rows(records),
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


def _p_value(test: dict[str, Any] | None) -> str:
    return "–" if test is None else f"{test['p_greater']:.3g}"


def pair_markdown(summary: dict[str, Any]) -> str:
    """Return cells.md: the pair's tasks, one row per cell, the plots."""
    lines = [f"# Rollouts of {summary['pair']}, layer {summary['layer']}", ""]
    lines += [f"- {side} side: {task['instruction']!r} ({task['suite']} task {task['index']})"
              for side, task in summary["tasks"].items()]
    lines += ["", "Success: k/n episodes [Wilson 95%]; the first goal reached ends an episode. α in × R; α toward: "
                  "the push toward the other task. Jerk: RMS third difference of the arm joints (rad/step³).", "",
              "p vs α = 0: the exact McNemar test (one-sided) of the cell's toward-task successes above its side's α = 0 "
              "cell on the same episodes.", "",
              "| side | condition | α | α toward | n | toward | p vs α = 0 | instructed | neither | mean steps | "
              "mean jerk | joint-limit hits |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in summary["cells"]:
        lines.append(f"| {row['side']} | {row['condition']} | {row['alpha']:+g} | {row['alpha_toward']:+g} | "
                     f"{row['n']} | {_proportion(row['toward'])} | {_p_value(row['vs_unsteered'])} | "
                     + " | ".join(_proportion(row[o]) for o in OUTCOME_COLUMNS[1:])
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
              "instruction swap (ceiling) | cross-fitted steered | p vs α = 0 | p vs random (largest) | answer |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for pair in summary["pairs"]:
        for row in pair["answers"]:
            wrong = ", ".join(f"{name} {_proportion(p)}" for name, p in row.get("wrong_concept", {}).items()) or "–"
            alpha = f"{row['alpha_toward']:+g}" if "alpha_toward" in row else "–"
            fitted = row.get("crossfit", {})
            tests = fitted.get("mcnemar", {})
            randoms = [test for name, test in tests.items() if name.startswith("random")]
            lines.append(f"| [{pair['pair']}]({pair['pair']}/{ROLLOUT_PAIR_TABLE}.md) | {row['side']} | {alpha} | "
                         f"{_proportion(row.get('steered'))} | {_proportion(row.get('random_edge'))} | "
                         f"{_proportion(row.get('unsteered'))} | {wrong} | {_proportion(row['ceiling'])} | "
                         f"{_proportion(fitted.get('steered'))} | {_p_value(tests.get('α = 0'))} | "
                         f"{_p_value(max(randoms, key=lambda t: t['p_greater'], default=None))} | {row['answer']} |")
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
