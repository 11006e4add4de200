"""Reports of the rollouts: per pair `cells.md`/`cells.json` (one row per cell) and the two PNGs, per layer
`summary.md`/`summary.json`: one answer per pair, side and steered direction (method x mode) in plain language
(does steering toward the other task beat the random controls and α = 0?), the methods table comparing the
directions head to head, the plots and first-episode videos linked.

Layout: ROLLOUTS_ROOT/layerNN/<pair>/<cell>/rollouts.json (records.write_cell), the pair files in <pair>/, the
summaries in layerNN/. α is in residual_norm units (× R), the evaluation phase's unit, in add mode, and a
fraction of the way between the two concepts' levels in clamp mode.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from steering_core.layout import JOINTS_PLOT, ROLLOUT_FILE, ROLLOUT_PAIR_TABLE, SUCCESS_PLOT, SUMMARY_JSON, SUMMARY_MD
from steering_core.pairs import SIDES
from steering_core.rollout.cells import KINDS, STEERED, condition_kind, steered_parts
from steering_core.rollout.plots import Thresholds, plot_joints, plot_success
from steering_core.rollout.records import ADD_UNITS, CLAMP_UNITS, ROLLOUT_FORMAT_VERSION, read_cell
from steering_core.rollout.stats import Paired, Proportion, holm, mcnemar, proportion
from steering_core.storage.fileio import read_json, write_json, write_text

OUTCOME_COLUMNS = ("toward", "instructed", "neither")
EVIDENCE_P = 0.05  # one-sided exact McNemar p below which a paired difference counts as evidence
ANSWER_TEXT = (
    "Per pair, side and steered direction (method, and mode: add, or clamp), cross-fitted: the direction's best α "
    "toward the other task (its highest toward-task success, the smallest α on ties) is chosen on one half of the "
    "initial states and read on the other, both ways, so no episode scores the α it chose. Cells share initial "
    f"states and seeds, so every comparison is paired: `yes` only when the exact McNemar test (one-sided, p < "
    f"{EVIDENCE_P:g}) finds the cross-fitted steered cell above α = 0 and above every random direction read the same "
    "way; otherwise `no evidence`. Wilson 95% intervals are shown beside; the instruction swap (the other task's "
    "instruction, no steering) is the ceiling.")
METHODS_TEXT = (
    "The directions head to head, per pair and side: each one's cross-fitted α (chosen on each half of the initial "
    "states, read on the other), toward-task and instructed-task success there (does the policy still complete its "
    "own instruction? compare with α = 0's), and one-sided exact McNemar p-values on the same episodes: above α = 0, "
    "above the random directions (the largest p over them) and above each other direction, each read at its own "
    "cross-fitted α. In brackets: Holm-adjusted over every p-value of that pair and side. The random controls are "
    "shared between methods and modes at the same α (add mode, norm-matched to the catalog's default direction), "
    "so a clamp direction is compared with them at the same α value, a level fraction rather than × R.")

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


def steered_conditions(records: Sequence[dict[str, Any]]) -> list[str]:
    """Return the steered conditions (method x mode: `sae`, `probe+clamp`) of the records, in their order."""
    return list(dict.fromkeys(r["condition"] for r in records if r["kind"] == STEERED))


def side_answer(records: Sequence[dict[str, Any]], side: str, condition: str) -> dict[str, Any]:
    """Return one side's comparison for one steered condition (see `_side_answer`), saying when the other task's
    goal already held at the start of some episodes (then only breaking it and reaching it again counts)."""
    cells = [r for r in records if r["side"] == side]
    row = _side_answer(cells, side, condition)
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


def _by_condition(cells: Sequence[dict[str, Any]], outcome: str = "toward") -> dict[str, dict[float, Outcomes]]:
    """Return condition -> α toward -> the cell's `outcome` per episode."""
    grouped: dict[str, dict[float, Outcomes]] = {}
    for record in cells:
        grouped.setdefault(record["condition"], {})[record["alpha_toward"]] = outcomes(record, outcome)
    return grouped


@dataclass(frozen=True)
class Crossfitted:
    """A steered condition read cross-fitted: the α chosen on each half and, per episode, whether it reached the
    other task's goal (`toward`) or its own (`instructed`) at the α chosen on the other half."""

    alphas: tuple[float, float]
    halves: list[list[tuple[int, int]]]
    toward: Outcomes
    instructed: Outcomes

    def read(self, cells: Mapping[float, Outcomes]) -> Outcomes | None:
        """Return another condition's episodes read the same way (None when it lacks a chosen α)."""
        return read_crossfit(cells, self.alphas, self.halves)


def crossfitted(cells: Sequence[dict[str, Any]], condition: str) -> Crossfitted | None:
    """Return one side's `condition` read cross-fitted (see `crossfit`), or None without cells of α toward > 0."""
    pushed = [r for r in cells if r["condition"] == condition and r["alpha_toward"] > 0]
    if not pushed:
        return None
    toward, instructed = (_by_condition(pushed, outcome)[condition] for outcome in ("toward", "instructed"))
    chosen, halves = crossfit(toward)
    return Crossfitted(chosen, halves, read_crossfit(toward, chosen, halves), read_crossfit(instructed, chosen, halves))


def control_tests(fit: Crossfitted, cells: Sequence[dict[str, Any]]) -> dict[str, Paired]:
    """Return the exact McNemar tests of a cross-fitted condition above its side's α = 0 cell ("α = 0") and above
    every random direction and wrong concept read the same way (by condition)."""
    zero = _at(cells, "unsteered")
    tests = {"α = 0": paired(fit.toward, outcomes(zero[0]))} if zero else {}
    for condition, by_alpha in _by_condition(cells).items():
        control = fit.read(by_alpha) if condition_kind(condition) in ("random", "wrong_concept") else None
        if control is not None:
            tests[condition] = paired(fit.toward, control)
    return tests


def _side_answer(cells: Sequence[dict[str, Any]], side: str, condition: str) -> dict[str, Any]:
    """Return one side's comparison for `condition`: its best α (on all episodes, as plotted), its cross-fitted
    success and McNemar tests against α = 0 and every control, the ceiling, and `answer` ("yes" / "no evidence")
    with `text` saying why (see ANSWER_TEXT)."""
    steered = [r for r in cells if r["condition"] == condition and r["alpha_toward"] > 0]
    swap, zero = _at(cells, "instruction_swap"), _at(cells, "unsteered")
    method, mode = steered_parts(condition)
    row: dict[str, Any] = {"side": side, "condition": condition, "method": method, "mode": mode,
                           "ceiling": success(swap[0]).to_json() if swap else None}
    if not steered:
        return row | {"answer": "no evidence", "text": f"no {condition} cells with α toward the other task > 0"}
    best = max(steered, key=lambda r: (success(r).k / success(r).n, -r["alpha_toward"]))
    alpha = best["alpha_toward"]
    randoms = _at(cells, "random", alpha)
    edge = max(randoms, key=lambda r: success(r).k / success(r).n) if randoms else None
    row |= {"alpha_toward": alpha, "alpha": best["alpha"], "steered": success(best).to_json(),
            "random_edge": success(edge).to_json() if edge else None, "random_count": len(randoms),
            "unsteered": success(zero[0]).to_json() if zero else None,
            "wrong_concept": {r["condition"].partition(":")[2]: success(r).to_json()
                              for r in _at(cells, "wrong_concept", alpha)}}
    fit = crossfitted(cells, condition)
    chosen, found = fit.alphas, fit.toward
    tests = control_tests(fit, cells)
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
    head = (f"cross-fitted {condition} toward-task success (α chosen on each half of the initial states: "
            f"{chosen[0]:+g} and {chosen[1]:+g}, each read on the other half) is {steered_rate.text()}")
    if not missing and not failing:
        worst = max(random_tests.values(), key=lambda test: test.p_greater)
        text = (f"yes: {head}, above α = 0 (exact McNemar p = {tests['α = 0'].p_greater:.3g}) and each of "
                f"{len(random_tests)} random directions (p ≤ {worst.p_greater:.3g}) on the paired episodes{ceiling}")
        return row | {"answer": "yes", "text": text}
    why = missing + ([f"not above {' and '.join(failing)} at p < {EVIDENCE_P:g}"] if failing else [])
    return row | {"answer": "no evidence", "text": f"no evidence: {head}; " + "; ".join(why) + ceiling}


def method_rows(records: Sequence[dict[str, Any]], side: str) -> list[dict[str, Any]]:
    """Return one side's methods table: per steered condition (method x mode) its cross-fitted α, toward-task and
    instructed-task success, and one-sided exact McNemar p-values above α = 0, above the random directions (the
    largest p over them) and above every other condition (each read at its own cross-fitted α, on the same
    episodes), with Holm's adjustment over all of the side's p-values (`p_holm`, the same shape as `p`)."""
    cells = [r for r in records if r["side"] == side]
    zero = _at(cells, "unsteered")
    fits = {c: fit for c in steered_conditions(cells) if (fit := crossfitted(cells, c)) is not None}
    rows = []
    for condition, fit in fits.items():
        tests = control_tests(fit, cells)
        randoms = [test.p_greater for name, test in tests.items() if condition_kind(name) == "random"]
        method, mode = steered_parts(condition)
        rows.append({
            "pair": cells[0]["pair"], "side": side, "condition": condition, "method": method, "mode": mode,
            "alphas_toward": list(fit.alphas),
            "toward": proportion(sum(fit.toward.values()), len(fit.toward)).to_json(),
            "instructed": proportion(sum(fit.instructed.values()), len(fit.instructed)).to_json(),
            "instructed_unsteered": success(zero[0], "instructed").to_json() if zero else None,
            "random_count": len(randoms),
            "p": {"unsteered": tests["α = 0"].p_greater if zero else None, "random": max(randoms, default=None),
                  "methods": {other: paired(fit.toward, theirs.toward).p_greater
                              for other, theirs in fits.items() if other != condition}}})
    # the family: every p-value of the side's table, as (row, key) or (row, "methods", other condition)
    family = [(row, key, None) for row in rows for key in ("unsteered", "random") if row["p"][key] is not None]
    family += [(row, "methods", other) for row in rows for other in row["p"]["methods"]]
    for row in rows:
        row["p_holm"] = {"unsteered": None, "random": None, "methods": {}}
    values = [row["p"][key] if other is None else row["p"][key][other] for row, key, other in family]
    for (row, key, other), value in zip(family, holm(values), strict=True):
        if other is None:
            row["p_holm"][key] = value
        else:
            row["p_holm"]["methods"][other] = value
    return rows


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
        "answers": [side_answer(records, side, condition) for side in tasks
                    for condition in steered_conditions(records)],
        "methods": [row for side in tasks for row in method_rows(records, side)],
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
    lines += ["", "Success: k/n episodes [Wilson 95%]; the first goal reached ends an episode. α in × R (clamp cells, "
                  "`<method>+clamp`: the fraction of the way from this side's concept level to the other's); α toward: "
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
               "alpha_units": {"add": ADD_UNITS, "clamp": CLAMP_UNITS},
               "methods": [row for pair in pairs for row in pair["methods"]], "pairs": pairs}
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


def _p_holm(p: float | None, adjusted: float | None) -> str:
    return "–" if p is None else f"{p:.3g} ({adjusted:.3g})"


def methods_markdown(rows: Sequence[dict[str, Any]]) -> list[str]:
    """Return the methods table of summary.md (see METHODS_TEXT), or nothing without rows."""
    if not rows:
        return []
    lines = ["", "## Methods compared", "", METHODS_TEXT, "",
             "| pair | side | direction | α toward (per half) | toward | instructed | instructed at α = 0 | "
             "p vs α = 0 | p vs random (largest) | p vs each other direction |", "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        p, adjusted = row["p"], row["p_holm"]
        others = ", ".join(f"{other} {_p_holm(value, adjusted['methods'][other])}"
                           for other, value in p["methods"].items()) or "–"
        lines.append(f"| {row['pair']} | {row['side']} | {row['condition']} | "
                     + " / ".join(f"{alpha:+g}" for alpha in row["alphas_toward"])
                     + f" | {_proportion(row['toward'])} | {_proportion(row['instructed'])} | "
                     f"{_proportion(row['instructed_unsteered'])} | {_p_holm(p['unsteered'], adjusted['unsteered'])} | "
                     f"{_p_holm(p['random'], adjusted['random'])} | {others} |")
    return lines


def summary_markdown(summary: dict[str, Any]) -> str:
    """Return summary.md: the note, the answers table, the methods table, the plain-language answers, the plots
    and the videos."""
    lines = [f"# Closed-loop steered rollouts, {summary['layer']}", ""]
    lines += [f"**{summary['note']}**", ""] if summary["note"] else []
    lines += [ANSWER_TEXT + " α toward the other task: × R (the evaluation's unit) in add mode, the level fraction in "
              "clamp mode.", "",
              "| pair | side | direction | best α toward | steered: toward | random edge | α = 0 | wrong concept | "
              "instruction swap (ceiling) | cross-fitted steered | p vs α = 0 | p vs random (largest) | answer |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for pair in summary["pairs"]:
        for row in pair["answers"]:
            wrong = ", ".join(f"{name} {_proportion(p)}" for name, p in row.get("wrong_concept", {}).items()) or "–"
            alpha = f"{row['alpha_toward']:+g}" if "alpha_toward" in row else "–"
            fitted = row.get("crossfit", {})
            tests = fitted.get("mcnemar", {})
            randoms = [test for name, test in tests.items() if name.startswith("random")]
            lines.append(f"| [{pair['pair']}]({pair['pair']}/{ROLLOUT_PAIR_TABLE}.md) | {row['side']} | "
                         f"{row['condition']} | {alpha} | "
                         f"{_proportion(row.get('steered'))} | {_proportion(row.get('random_edge'))} | "
                         f"{_proportion(row.get('unsteered'))} | {wrong} | {_proportion(row['ceiling'])} | "
                         f"{_proportion(fitted.get('steered'))} | {_p_value(tests.get('α = 0'))} | "
                         f"{_p_value(max(randoms, key=lambda t: t['p_greater'], default=None))} | {row['answer']} |")
    lines += methods_markdown(summary["methods"])
    for pair in summary["pairs"]:
        name = pair["pair"]
        lines += ["", f"## {name}", ""]
        lines += [f"- {row['side']} side, {row['condition']} ({pair['tasks'][row['side']]['instruction']!r} pushed "
                  f"toward the other task): {row['text']}" for row in pair["answers"]]
        lines += [""] + [f"![{name}: {plot}]({name}/{path})\n" for plot, path in pair["plots"].items()]
        lines += ["First episode of each cell (agentview MP4), by α toward the other task and outcome:", ""]
        by_condition: dict[str, list[str]] = {}
        for cell in pair["cells"]:
            if cell["cell"] in pair["videos"]:
                by_condition.setdefault(f"{cell['side']}, {cell['condition']}", []).append(
                    f"[{cell['alpha_toward']:+g} {cell['first_outcome']}]({name}/{pair['videos'][cell['cell']]})")
        lines += [f"- {key}: " + " · ".join(links) for key, links in by_condition.items()] or ["- none recorded"]
    return "\n".join(lines) + "\n"
