"""Rollout reports: the pair table and the per-layer summary (answers, note, links) from synthetic cells."""

from __future__ import annotations

import re

import pytest
from helpers_rollout import CLOSE, DRAWER_GOALS, OPEN, PAIR, RUN, make_episode, write_pair_cells

from flows.rollout import ui_rollouts
from steering_core.rollout.cells import Cell
from steering_core.rollout.records import CellTasks, write_cell
from steering_core.rollout.report import side_answer, write_layer_summary, write_pair_report
from steering_core.storage.fileio import read_json

NOTE = "The policy is a tiny random π0.5: its success rates (0) say nothing about a real policy."


def test_layer_summary_answers_links_and_notes(tmp_path):
    write_pair_cells(tmp_path, n=10, frames=2)
    pair = write_pair_report(tmp_path / PAIR, DRAWER_GOALS)
    assert [(a["side"], a["answer"], a["alpha_toward"]) for a in pair["answers"]] == [
        ("positive", "yes", 4.0), ("negative", "yes", 4.0)]
    negative = pair["answers"][1]
    # steered at α 4 wins episodes 0-7, α = 0 none (8 discordant: p = 2^-8), each random only episode 0 (7: 2^-7)
    assert negative["text"] == (
        "yes: cross-fitted steered toward-task success (α chosen on each half of the initial states: +4 and +4, each "
        "read on the other half) is 8/10 [0.49, 0.94], above α = 0 (exact McNemar p = 0.00391) and each of 4 random "
        "directions (p ≤ 0.00781) on the paired episodes; ceiling (instruction swap) 9/10 [0.60, 0.98]")
    assert negative["crossfit"]["mcnemar"]["α = 0"] == {"n": 10, "both": 0, "only_a": 8, "only_b": 0,
                                                       "p_greater": 2**-8, "p_two_sided": 2**-7}
    assert negative["alpha"] == 4.0 and pair["answers"][0]["alpha"] == -4.0
    assert set(negative["wrong_concept"]) == {"on_vs_off"} and negative["random_count"] == 4
    assert len(pair["cells"]) == 40
    row = next(c for c in pair["cells"] if c["cell"] == "negative_steered_a+2")
    assert (row["n"], row["toward"]["k"], row["alpha_toward"], row["first_outcome"]) == (10, 4, 2.0, "toward")
    table = (tmp_path / PAIR / "cells.md").read_text()
    assert ("| negative | steered | +2 | +2 | 10 | 4/10 [0.17, 0.69] | 0.0625 | 1/10 [0.02, 0.40] | 5/10 [0.24, 0.76] |"
            in table)  # 4 episodes won over α = 0, none lost: p = 2^-4

    md = write_layer_summary(tmp_path, [PAIR], note=NOTE)
    text = md.read_text()
    assert text.startswith(f"# Closed-loop steered rollouts, {tmp_path.name}\n\n**{NOTE}**\n")
    assert (f"| [{PAIR}]({PAIR}/cells.md) | negative | +4 | 8/10 [0.49, 0.94] | 1/10 [0.02, 0.40] | 0/10 [0.00, 0.28] "
            "| on_vs_off 1/10 [0.02, 0.40] | 9/10 [0.60, 0.98] | 8/10 [0.49, 0.94] | 0.00391 | 0.00781 | yes |") in text
    assert "- negative, steered: [+1 toward](open_vs_close/negative_steered_a+1/negative_steered_a+1_ep0_toward.mp4)" \
        in text
    links = re.findall(r"\]\(([^)]+)\)", text)
    assert len(links) == 2 + 2 + 40 and all((tmp_path / link).is_file() for link in links)
    summary = read_json(tmp_path / "summary.json")
    assert summary["note"] == NOTE and [p["pair"] for p in summary["pairs"]] == [PAIR]

    ui = ui_rollouts(tmp_path)  # the Prefect artifact: plots inline, the videos' paths listed
    assert ui.count("](data:image/png;base64,") == 2 and "success_vs_alpha.png)" not in ui
    assert ui.count(".mp4`") == 40 and f"in `{tmp_path}`" in ui


def test_overlapping_intervals_are_no_evidence(tmp_path):
    records = write_pair_cells(tmp_path, n=3, frames=0)
    answer = side_answer(records, "negative")
    assert answer["answer"] == "no evidence" and answer["alpha_toward"] == 2.0  # 3/3 at α 2 and 4: the smaller
    # halves {0, 2} and {1}: α 2 (2 of 2, tied with α 4: the smaller) chosen on the first, read on episode 1 (won);
    # α 1 (1 of 1, tied with 2 and 4) on the second, read on episodes 0 (won) and 2 (lost): 2 of 3, p = 2^-2
    assert answer["crossfit"]["alphas_toward"] == [2.0, 1.0]
    assert answer["text"] == (
        "no evidence: cross-fitted steered toward-task success (α chosen on each half of the initial states: +2 and "
        "+1, each read on the other half) is 2/3 [0.21, 0.94]; not above α = 0 (p = 0.25, 2 vs 0 discordant "
        "episodes) and 4 of 4 random directions (largest p = 0.25) at p < 0.05; ceiling (instruction swap) 2/3 "
        "[0.21, 0.94]")


def test_missing_controls_and_joints_are_said(tmp_path):
    episodes = [make_episode(CLOSE.instruction, "toward", 5, init_index=i, seed=i) for i in range(4)]
    for episode in episodes:
        episode.joints = {}  # a goal on no articulated object (e.g. "put the bowl on the plate")
    cell = Cell(PAIR, 12, "negative", "steered", 2.0)
    record = write_cell(tmp_path / PAIR / cell.name, cell, CellTasks(CLOSE, OPEN), episodes, [7] * 4, RUN)
    assert write_pair_report(tmp_path / PAIR)["plots"] == {"success": "success_vs_alpha.png"}
    answer = side_answer([record], "negative")
    assert answer["text"] == ("no evidence: cross-fitted steered toward-task success (α chosen on each half of the "
                              "initial states: +2 and +2, each read on the other half) is 4/4 [0.51, 1.00]; no random "
                              "controls at the chosen α to compare; no α = 0 cell to compare")
    assert answer["ceiling"] is None and side_answer([record], "positive")["text"] == (
        "no steered cells with α toward the other task > 0")


def test_a_toward_goal_holding_at_the_start_is_said_with_its_count(tmp_path):
    records = write_pair_cells(tmp_path, n=4, frames=0)
    plain = side_answer(records, "negative")
    assert "toward_at_start" not in plain and "already held" not in plain["text"]
    negative = [r for r in records if r["side"] == "negative"]
    for record in negative[:3]:
        record["toward_at_start"] = 2
    answer = side_answer(records, "negative")
    assert answer["toward_at_start"] == {"k": 6, "n": 4 * len(negative)}
    assert answer["text"].startswith(plain["text"]) and f"start of 6 of {4 * len(negative)} episodes" in answer["text"]


def cells_winning(tmp_path, won: dict[tuple[str, float], set[int]], n: int = 20) -> list[dict]:
    """Write the negative side's cells whose episodes `won[(condition, α toward)]` reach the other task's goal."""
    records = []
    for (condition, alpha), wins in won.items():
        cell = Cell.pushed(PAIR, 12, "negative", condition, alpha)
        episodes = [make_episode(CLOSE.instruction, "toward" if i in wins else "neither", 5, init_index=i, seed=i)
                    for i in range(n)]
        records.append(write_cell(tmp_path / PAIR / cell.name, cell, CellTasks(CLOSE, OPEN), episodes, [7] * n, RUN))
    return records


def randoms(alpha: float) -> dict[tuple[str, float], set[int]]:
    return {(f"random_{k}", alpha): set() for k in range(4)}


def test_pairing_decides_what_unpaired_intervals_cannot(tmp_path):
    """11 of 20 against 5 of 20: the Wilson intervals overlap either way; the episodes' pairing decides."""
    superset = cells_winning(tmp_path / "a", {("unsteered", 0.0): set(range(5)), ("steered", 2.0): set(range(11)),
                                              **randoms(2.0)})
    answer = side_answer(superset, "negative")
    assert answer["answer"] == "yes"  # 6 discordant episodes, all won by steering: p = 2^-6
    assert answer["crossfit"]["mcnemar"]["α = 0"]["p_greater"] == 2**-6
    # the control: the same counts on other episodes (steering wins 11, loses 5): p = P(X >= 11 | 16, 1/2)
    disjoint = cells_winning(tmp_path / "b", {("unsteered", 0.0): set(range(5)),
                                              ("steered", 2.0): set(range(5, 16)), **randoms(2.0)})
    answer = side_answer(disjoint, "negative")
    assert answer["answer"] == "no evidence"
    assert answer["crossfit"]["mcnemar"]["α = 0"]["p_greater"] == pytest.approx(6885 / 65536, rel=1e-12)
    assert "not above α = 0 (p = 0.105, 11 vs 5 discordant episodes)" in answer["text"]


def test_the_best_alpha_is_never_scored_on_the_episodes_that_chose_it(tmp_path):
    """α 1 wins every even episode, α 2 six odd ones: chosen and read on the same episodes, α 1's 10 of 20 against
    α = 0's none would be p = 2^-10; each half's choice fails on the other half, so cross-fitted it is 0 of 20."""
    records = cells_winning(tmp_path, {("unsteered", 0.0): set(), ("steered", 1.0): set(range(0, 20, 2)),
                                       ("steered", 2.0): {1, 3, 5, 7, 9, 11}, **randoms(1.0), **randoms(2.0)})
    answer = side_answer(records, "negative")
    assert answer["alpha_toward"] == 1.0 and answer["steered"]["k"] == 10  # the full-data best, as plotted
    assert answer["crossfit"]["alphas_toward"] == [1.0, 2.0]
    assert answer["crossfit"]["steered"]["k"] == 0 and answer["answer"] == "no evidence"
