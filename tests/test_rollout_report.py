"""Rollout reports: the pair table and the per-layer summary (answers, note, links) from synthetic cells."""

from __future__ import annotations

import re

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
    assert negative["text"] == (
        "yes: steered toward-task success at α = +4 is 8/10 [0.49, 0.94], above the random band's upper edge of 4 "
        "directions (1/10 [0.02, 0.40]) and α = 0 (0/10 [0.00, 0.28]); ceiling (instruction swap) 9/10 [0.60, 0.98]")
    assert negative["alpha"] == 4.0 and pair["answers"][0]["alpha"] == -4.0
    assert set(negative["wrong_concept"]) == {"on_vs_off"} and negative["random_count"] == 4
    assert len(pair["cells"]) == 40
    row = next(c for c in pair["cells"] if c["cell"] == "negative_steered_a+2")
    assert (row["n"], row["toward"]["k"], row["alpha_toward"], row["first_outcome"]) == (10, 4, 2.0, "toward")
    table = (tmp_path / PAIR / "cells.md").read_text()
    assert "| negative | steered | +2 | +2 | 10 | 4/10 [0.17, 0.69] | 1/10 [0.02, 0.40] | 5/10 [0.24, 0.76] |" in table

    md = write_layer_summary(tmp_path, [PAIR], note=NOTE)
    text = md.read_text()
    assert text.startswith(f"# Closed-loop steered rollouts, {tmp_path.name}\n\n**{NOTE}**\n")
    assert (f"| [{PAIR}]({PAIR}/cells.md) | negative | +4 | 8/10 [0.49, 0.94] | 1/10 [0.02, 0.40] | 0/10 [0.00, 0.28] "
            "| on_vs_off 1/10 [0.02, 0.40] | 9/10 [0.60, 0.98] | yes |") in text
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
    assert answer["text"] == (
        "no evidence: steered toward-task success at α = +2 is 3/3 [0.44, 1.00]; its interval overlaps the random "
        "band's upper edge of 4 directions (0/3 [0.00, 0.56]) and α = 0 (0/3 [0.00, 0.56]); ceiling (instruction "
        "swap) 2/3 [0.21, 0.94]")


def test_missing_controls_and_joints_are_said(tmp_path):
    episodes = [make_episode(CLOSE.instruction, "toward", 5, init_index=i, seed=i) for i in range(4)]
    for episode in episodes:
        episode.joints = {}  # a goal on no articulated object (e.g. "put the bowl on the plate")
    cell = Cell(PAIR, 12, "negative", "steered", 2.0)
    record = write_cell(tmp_path / PAIR / cell.name, cell, CellTasks(CLOSE, OPEN), episodes, [7] * 4, RUN)
    assert write_pair_report(tmp_path / PAIR)["plots"] == {"success": "success_vs_alpha.png"}
    answer = side_answer([record], "negative")
    assert answer["text"] == ("no evidence: steered toward-task success at α = +2 is 4/4 [0.51, 1.00]; no random "
                              "controls at this α to compare; no α = 0 cell to compare")
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
