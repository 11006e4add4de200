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
        "yes: cross-fitted sae toward-task success (α chosen on each half of the initial states: +4 and +4, each "
        "read on the other half) is 8/10 [0.49, 0.94], above α = 0 (exact McNemar p = 0.00391) and each of 4 random "
        "directions (p ≤ 0.00781) on the paired episodes; ceiling (instruction swap) 9/10 [0.60, 0.98]")
    assert negative["crossfit"]["mcnemar"]["α = 0"] == {"n": 10, "both": 0, "only_a": 8, "only_b": 0,
                                                       "p_greater": 2**-8, "p_two_sided": 2**-7}
    assert negative["alpha"] == 4.0 and pair["answers"][0]["alpha"] == -4.0
    assert set(negative["wrong_concept"]) == {"on_vs_off/sae"} and negative["random_count"] == 4
    assert len(pair["cells"]) == 40
    row = next(c for c in pair["cells"] if c["cell"] == "negative_sae_a+2")
    assert (row["n"], row["toward"]["k"], row["alpha_toward"], row["first_outcome"]) == (10, 4, 2.0, "toward")
    table = (tmp_path / PAIR / "cells.md").read_text()
    assert ("| negative | sae | +2 | +2 | 10 | 4/10 [0.17, 0.69] | 0.0625 | 1/10 [0.02, 0.40] | 5/10 [0.24, 0.76] |"
            in table)  # 4 episodes won over α = 0, none lost: p = 2^-4

    md = write_layer_summary(tmp_path, [PAIR], note=NOTE)
    text = md.read_text()
    assert text.startswith(f"# Closed-loop steered rollouts, {tmp_path.name}\n\n**{NOTE}**\n")
    assert (f"| [{PAIR}]({PAIR}/cells.md) | negative | sae | +4 | 8/10 [0.49, 0.94] | 1/10 [0.02, 0.40] | 0/10 [0.00, 0.28] "
            "| on_vs_off/sae 1/10 [0.02, 0.40] | 9/10 [0.60, 0.98] | 8/10 [0.49, 0.94] | 0.00391 | 0.00781 | yes |") in text
    assert "- negative, sae: [+1 toward](open_vs_close/negative_sae_a+1/negative_sae_a+1_ep0_toward.mp4)" \
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
    answer = side_answer(records, "negative", "sae")
    assert answer["answer"] == "no evidence" and answer["alpha_toward"] == 2.0  # 3/3 at α 2 and 4: the smaller
    # halves {0, 2} and {1}: α 2 (2 of 2, tied with α 4: the smaller) chosen on the first, read on episode 1 (won);
    # α 1 (1 of 1, tied with 2 and 4) on the second, read on episodes 0 (won) and 2 (lost): 2 of 3, p = 2^-2
    assert answer["crossfit"]["alphas_toward"] == [2.0, 1.0]
    assert answer["text"] == (
        "no evidence: cross-fitted sae toward-task success (α chosen on each half of the initial states: +2 and "
        "+1, each read on the other half) is 2/3 [0.21, 0.94]; not above α = 0 (p = 0.25, 2 vs 0 discordant "
        "episodes) and 4 of 4 random directions (largest p = 0.25) at p < 0.05; ceiling (instruction swap) 2/3 "
        "[0.21, 0.94]")


def test_missing_controls_and_joints_are_said(tmp_path):
    episodes = [make_episode(CLOSE.instruction, "toward", 5, init_index=i, seed=i) for i in range(4)]
    for episode in episodes:
        episode.joints = {}  # a goal on no articulated object (e.g. "put the bowl on the plate")
    cell = Cell(PAIR, 12, "negative", "sae", 2.0)
    record = write_cell(tmp_path / PAIR / cell.name, cell, CellTasks(CLOSE, OPEN), episodes, [7] * 4, RUN)
    assert write_pair_report(tmp_path / PAIR)["plots"] == {"success": "success_vs_alpha.png"}
    answer = side_answer([record], "negative", "sae")
    assert answer["text"] == ("no evidence: cross-fitted sae toward-task success (α chosen on each half of the "
                              "initial states: +2 and +2, each read on the other half) is 4/4 [0.51, 1.00]; no random "
                              "controls at the chosen α to compare; no α = 0 cell to compare")
    assert answer["ceiling"] is None and side_answer([record], "positive", "sae")["text"] == (
        "no sae cells with α toward the other task > 0")


def test_a_toward_goal_holding_at_the_start_is_said_with_its_count(tmp_path):
    records = write_pair_cells(tmp_path, n=4, frames=0)
    plain = side_answer(records, "negative", "sae")
    assert "toward_at_start" not in plain and "already held" not in plain["text"]
    negative = [r for r in records if r["side"] == "negative"]
    for record in negative[:3]:
        record["toward_at_start"] = 2
    answer = side_answer(records, "negative", "sae")
    assert answer["toward_at_start"] == {"k": 6, "n": 4 * len(negative)}
    assert answer["text"].startswith(plain["text"]) and f"start of 6 of {4 * len(negative)} episodes" in answer["text"]


def cells_winning(tmp_path, won: dict[tuple[str, float], set[int]], n: int = 20,
                  instructed: dict[tuple[str, float], set[int]] | None = None) -> list[dict]:
    """Write the negative side's cells whose episodes `won[(condition, α toward)]` reach the other task's goal and
    `instructed[(condition, α toward)]` their own (default none); the rest reach neither."""
    records, instructed = [], instructed or {}
    for (condition, alpha), wins in won.items():
        cell = Cell.pushed(PAIR, 12, "negative", condition, alpha)
        own = instructed.get((condition, alpha), set())
        episodes = [make_episode(CLOSE.instruction, "toward" if i in wins else "instructed" if i in own else "neither",
                                 5, init_index=i, seed=i) for i in range(n)]
        records.append(write_cell(tmp_path / PAIR / cell.name, cell, CellTasks(CLOSE, OPEN), episodes, [7] * n, RUN))
    return records


def randoms(alpha: float) -> dict[tuple[str, float], set[int]]:
    return {(f"random_{k}", alpha): set() for k in range(4)}


def test_pairing_decides_what_unpaired_intervals_cannot(tmp_path):
    """11 of 20 against 5 of 20: the Wilson intervals overlap either way; the episodes' pairing decides."""
    superset = cells_winning(tmp_path / "a", {("unsteered", 0.0): set(range(5)), ("sae", 2.0): set(range(11)),
                                              **randoms(2.0)})
    answer = side_answer(superset, "negative", "sae")
    assert answer["answer"] == "yes"  # 6 discordant episodes, all won by steering: p = 2^-6
    assert answer["crossfit"]["mcnemar"]["α = 0"]["p_greater"] == 2**-6
    # the control: the same counts on other episodes (steering wins 11, loses 5): p = P(X >= 11 | 16, 1/2)
    disjoint = cells_winning(tmp_path / "b", {("unsteered", 0.0): set(range(5)),
                                              ("sae", 2.0): set(range(5, 16)), **randoms(2.0)})
    answer = side_answer(disjoint, "negative", "sae")
    assert answer["answer"] == "no evidence"
    assert answer["crossfit"]["mcnemar"]["α = 0"]["p_greater"] == pytest.approx(6885 / 65536, rel=1e-12)
    assert "not above α = 0 (p = 0.105, 11 vs 5 discordant episodes)" in answer["text"]


def test_the_best_alpha_is_never_scored_on_the_episodes_that_chose_it(tmp_path):
    """α 1 wins every even episode, α 2 six odd ones: chosen and read on the same episodes, α 1's 10 of 20 against
    α = 0's none would be p = 2^-10; each half's choice fails on the other half, so cross-fitted it is 0 of 20."""
    records = cells_winning(tmp_path, {("unsteered", 0.0): set(), ("sae", 1.0): set(range(0, 20, 2)),
                                       ("sae", 2.0): {1, 3, 5, 7, 9, 11}, **randoms(1.0), **randoms(2.0)})
    answer = side_answer(records, "negative", "sae")
    assert answer["alpha_toward"] == 1.0 and answer["steered"]["k"] == 10  # the full-data best, as plotted
    assert answer["crossfit"]["alphas_toward"] == [1.0, 2.0]
    assert answer["crossfit"]["steered"]["k"] == 0 and answer["answer"] == "no evidence"


def test_the_methods_table_compares_directions_head_to_head_with_holm(tmp_path):
    """sae reaches the other task in episodes 0-11 at α 2 (nothing at α 1), mean_difference in 0-1 at α 1 (nothing
    at α 2); α = 0 never, each random direction only in episode 0. Each method is read at its own cross-fitted α
    (sae 2, mean_difference 1, on both halves), so every test is on all 20 episodes."""
    won = {("unsteered", 0.0): set(), ("sae", 1.0): set(), ("sae", 2.0): set(range(12)),
           ("mean_difference", 1.0): {0, 1}, ("mean_difference", 2.0): set(),
           **{key: {0} for key in [*randoms(1.0), *randoms(2.0)]}}
    instructed = {("unsteered", 0.0): set(range(16)), ("sae", 2.0): set(range(12, 16)),
                  ("mean_difference", 1.0): set(range(2, 16))}
    cells_winning(tmp_path, won, instructed=instructed)
    pair = write_pair_report(tmp_path / PAIR)
    rows = {row["condition"]: row for row in pair["methods"]}
    assert list(rows) == ["mean_difference", "sae"] and {row["side"] for row in rows.values()} == {"negative"}
    sae, md = rows["sae"], rows["mean_difference"]
    assert (sae["method"], sae["mode"], sae["alphas_toward"], md["alphas_toward"]) == ("sae", "add", [2.0, 2.0],
                                                                                         [1.0, 1.0])
    assert (sae["toward"]["k"], sae["toward"]["n"], md["toward"]["k"]) == (12, 20, 2)
    # the cost of steering: sae's own task drops from 16 of 20 at α = 0 to 4; mean_difference's to 14
    assert (sae["instructed"]["k"], md["instructed"]["k"], sae["instructed_unsteered"]["k"]) == (4, 14, 16)
    assert sae["random_count"] == md["random_count"] == 4
    # McNemar, one-sided, on the discordant episodes: sae above α = 0 by 12 to 0 (2^-12), above each random by
    # 11 to 0 (2^-11), above mean_difference by 10 to 0 (2^-10); mean_difference above α = 0 by 2 to 0 (1/4), above
    # each random by 1 to 0 (1/2), above sae by 0 to 10 (P(X >= 0) = 1)
    assert sae["p"] == {"unsteered": 2**-12, "random": 2**-11, "methods": {"mean_difference": 2**-10}}
    assert md["p"] == {"unsteered": 0.25, "random": 0.5, "methods": {"sae": 1.0}}
    # Holm over the side's 6 p-values: sorted 2^-12 x 6, 2^-11 x 5, 2^-10 x 4, 1/4 x 3, 1/2 x 2, 1 x 1 (capped at 1)
    assert sae["p_holm"] == {"unsteered": 6 * 2**-12, "random": 5 * 2**-11, "methods": {"mean_difference": 4 * 2**-10}}
    assert md["p_holm"] == {"unsteered": 0.75, "random": 1.0, "methods": {"sae": 1.0}}
    answers = {row["condition"]: row for row in pair["answers"]}
    assert (answers["sae"]["answer"], answers["mean_difference"]["answer"]) == ("yes", "no evidence")

    write_layer_summary(tmp_path, [PAIR])
    summary = read_json(tmp_path / "summary.json")
    assert summary["methods"] == pair["methods"] and all(row["pair"] == PAIR for row in summary["methods"])
    text = (tmp_path / "summary.md").read_text()
    assert "random controls are shared between methods and modes at the same α" in text
    assert (f"| {PAIR} | negative | sae | +2 / +2 | 12/20 [0.39, 0.78] | 4/20 [0.08, 0.42] | 16/20 [0.58, 0.92] | "
            "0.000244 (0.00146) | 0.000488 (0.00244) | mean_difference 0.000977 (0.00391) |") in text
    assert f"| [{PAIR}]({PAIR}/cells.md) | negative | mean_difference | +1 |" in text


def test_both_modes_of_two_methods_are_answered_and_plotted(tmp_path):
    won = {("unsteered", 0.0): set(), **randoms(1.0)}
    for condition in ("sae", "sae+clamp", "mean_difference", "mean_difference+clamp"):
        won[condition, 1.0] = set(range(len(condition)))
    cells_winning(tmp_path, won, n=12)
    pair = write_pair_report(tmp_path / PAIR)
    conditions = ["mean_difference", "mean_difference+clamp", "sae", "sae+clamp"]
    assert [(row["condition"], row["mode"]) for row in pair["answers"]] == [
        (c, "clamp" if c.endswith("+clamp") else "add") for c in conditions]
    assert [row["condition"] for row in pair["methods"]] == conditions
    # each row is compared with the three others; the family: 4 x (α = 0, random, 3 others) p-values
    assert all(len(row["p"]["methods"]) == len(row["p_holm"]["methods"]) == 3 for row in pair["methods"])
    assert (tmp_path / PAIR / "success_vs_alpha.png").read_bytes()[:4] == b"\x89PNG"
