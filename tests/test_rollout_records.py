"""A rollout cell's files: rollouts.json and .safetensors round-trip the episodes; bad cells are refused whole."""

from __future__ import annotations

import errno
import json
import re

import numpy as np
import pytest
from helpers_rollout import CLOSE, JOINT, OPEN, RUN, make_episode, write_pair_cells

from steering_core.layout import rollout_cell_dir
from steering_core.rollout.cells import Cell, condition_kind
from steering_core.rollout.records import CellTasks, merge_chunks, read_cell, write_cell
from steering_core.storage.os_limits import DiskFullError


def test_cell_names_and_condition_kinds():
    assert rollout_cell_dir("negative", "sae", 2.0) == "negative_sae_a+2"
    assert rollout_cell_dir("positive", "probe+clamp", -0.5) == "positive_probe+clamp_a-0.5"
    assert rollout_cell_dir("positive", "wrong_concept:on_vs_off/sae", -1.5) == \
        "positive_wrong_concept-on_vs_off-sae_a-1.5"
    assert rollout_cell_dir("positive", "unsteered", -0.0) == "positive_unsteered_a+0"
    assert [condition_kind(c) for c in ("sae", "mean_difference+clamp", "random_3", "wrong_concept:a_vs_b/sae",
                                        "instruction_swap", "unsteered")] == [
        "steered", "steered", "random", "wrong_concept", "instruction_swap", "unsteered"]
    cell = Cell("open_vs_close", 12, "positive", "sae", -2.0)
    assert (cell.name, cell.alpha_toward, cell.method, cell.mode) == ("positive_sae_a-2", 2.0, "sae", "add")
    clamp = Cell("open_vs_close", 12, "negative", "mean_difference+clamp", 0.5)
    assert (clamp.method, clamp.mode, clamp.direction, clamp.steering_pair) == (
        "mean_difference", "clamp", "mean_difference", "open_vs_close")
    wrong = Cell("open_vs_close", 12, "negative", "wrong_concept:on_vs_off/mean_difference", 1.0)
    assert (wrong.method, wrong.mode, wrong.direction, wrong.steering_pair) == (
        "mean_difference", "add", "mean_difference", "on_vs_off")
    control = Cell("open_vs_close", 12, "negative", "random_2", 1.0)
    assert (control.method, control.mode, control.direction) == (None, "add", "random_2")
    assert (Cell("open_vs_close", 12, "negative", "unsteered", 0.0).mode,
            Cell("open_vs_close", 12, "negative", "instruction_swap", 0.0).direction) == (None, None)


def test_cell_round_trips(tmp_path):
    cell, tasks = Cell("open_vs_close", 12, "negative", "sae", 2.0), CellTasks(CLOSE, OPEN)
    episodes = [make_episode(CLOSE.instruction, "toward", 12, init_index=3, seed=1, drift=-0.01, frames=3),
                make_episode(CLOSE.instruction, "neither", 30, init_index=4, seed=2),
                make_episode(CLOSE.instruction, "instructed", 2, init_index=5, seed=3)]
    record = write_cell(tmp_path / cell.name, cell, tasks, episodes, seeds=[7, 7, 7], run=RUN)
    read, arrays = read_cell(tmp_path / cell.name)
    assert read == json.loads(json.dumps(record))
    assert sorted(p.name for p in (tmp_path / cell.name).iterdir()) == [
        "negative_sae_a+2_ep0_toward.mp4", "rollouts.json", "rollouts.safetensors"]
    assert {key: read[key] for key in ("pair", "layer", "side", "condition", "kind", "method", "mode", "alpha",
                                       "alpha_toward", "cell", "prompt", "joints", "run")} == {
        "pair": "open_vs_close", "layer": 12, "side": "negative", "condition": "sae", "kind": "steered",
        "method": "sae", "mode": "add", "alpha": 2.0, "alpha_toward": 2.0, "cell": "negative_sae_a+2",
        "prompt": CLOSE.instruction, "joints": [JOINT], "run": RUN}
    assert read["instructed"] == {"suite": "libero_90", "index": 0, "instruction": CLOSE.instruction}
    assert read["episodes"][0] == {
        "episode": 0, "seed": 7, "init_index": 3, "outcome": "toward", "steps": 12, "success_step": None,
        "toward_step": 12, "jerk": pytest.approx(episodes[0].jerk), "joint_limit_hits": 0, "policy_calls": 3,
        "toward_at_start": False, "video": "negative_sae_a+2_ep0_toward.mp4"}
    assert read["episodes"][2]["jerk"] is None and read["mean_jerk"] == pytest.approx(
        (episodes[0].jerk + episodes[1].jerk) / 2)  # a 2-step episode has no third difference
    assert read["success"]["toward"] == {"k": 1, "n": 3, "rate": 1 / 3, "low": pytest.approx(0.0615, abs=1e-4),
                                         "high": pytest.approx(0.7923, abs=1e-4)}
    assert [read["success"][o]["k"] for o in ("instructed", "toward", "neither")] == [1, 1, 1]
    assert arrays["lengths"].tolist() == [12, 30, 2]
    assert arrays["actions"].shape == (3, 30, 7) and arrays["actions"].dtype == np.float32
    assert arrays["robot_qpos"].shape == (3, 31, 7) and arrays[f"joints/{JOINT}"].shape == (3, 31)
    for i, episode in enumerate(episodes):
        steps = episode.steps
        assert np.array_equal(arrays["actions"][i, :steps], episode.actions)
        assert np.array_equal(arrays["robot_qpos"][i, : steps + 1], episode.robot_qpos)
        assert np.array_equal(arrays[f"joints/{JOINT}"][i, : steps + 1], episode.joints[JOINT])
        assert np.isnan(arrays[f"joints/{JOINT}"][i, steps + 1:]).all() and np.isnan(arrays["actions"][i, steps:]).all()


def test_a_cell_that_fails_at_a_later_file_keeps_none(tmp_path, monkeypatch):
    """A full disk at the arrays, after the video: the cell keeps no file, not even its folder."""
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("steering_core.rollout.records.save_safetensors", full)
    cell, tasks = Cell("open_vs_close", 12, "negative", "sae", 2.0), CellTasks(CLOSE, OPEN)
    with pytest.raises(DiskFullError) as err:
        write_cell(tmp_path / cell.name, cell, tasks, [make_episode(CLOSE.instruction, "toward", 12, frames=3)],
                   seeds=[7], run=RUN)
    assert list(tmp_path.rglob("*")) == []
    assert str(err.value).startswith(f"{tmp_path / cell.name}: no space left") and "nothing was kept" in str(err.value)


def test_bad_cells_are_refused_with_every_problem(tmp_path):
    with pytest.raises(ValueError, match=r"side 'left' is not one of \['positive', 'negative'\]; condition 'random'"):
        Cell("p", 1, "left", "random", 1.0)
    with pytest.raises(ValueError, match="0 for the unsteered and instruction_swap cells"):
        Cell("p", 1, "positive", "unsteered", 1.0)
    # "steered" (the old single direction) and "residual" are no methods; a mode is clamp or nothing
    for bad in ("steered", "residual", "sae+add", "sae+", "wrong_concept:q", "wrong_concept:q/residual"):
        with pytest.raises(ValueError, match=re.escape(f"condition {bad!r} is not <method>, <method>+clamp")):
            Cell("p", 1, "positive", bad, 1.0)
    cell, tasks = Cell("p", 1, "positive", "sae", 1.0), CellTasks(OPEN, CLOSE)
    short = make_episode(OPEN.instruction, "won", 5)
    short.actions = short.actions[:4]
    with pytest.raises(ValueError) as err:
        write_cell(tmp_path / cell.name, cell, tasks, [short, make_episode(CLOSE.instruction, "toward", 3)], [7], RUN)
    assert str(err.value) == (
        "cell p/positive_sae_a+1: 1 seeds for 2 episodes; episodes saw different prompts "
        f"['{CLOSE.instruction}', '{OPEN.instruction}']; episode 0: actions is (4, 7), expected (5, 7); "
        "episode 0: outcome 'won' is not one of ['instructed', 'toward', 'neither']")
    assert not (tmp_path / cell.name).exists()


def test_pair_cells_share_initial_states(tmp_path):
    records = write_pair_cells(tmp_path, n=4, frames=0)
    assert len(records) == 2 * (3 * 6 + 2) and len({r["cell"] for r in records}) == len(records)
    assert {tuple(e["init_index"] for e in r["episodes"]) for r in records} == {(0, 1, 2, 3)}


def test_chunks_merge_into_the_record_of_all_their_episodes(tmp_path):
    cell, tasks = Cell("open_vs_close", 12, "positive", "random_1", -2.0), CellTasks(OPEN, CLOSE)
    episodes = [make_episode(OPEN.instruction, outcome, 10 + i, init_index=i, seed=i, frames=2 if i == 0 else 0)
                for i, outcome in enumerate(("neither", "toward", "instructed"))]
    episodes[1].toward_at_start = True
    whole = write_cell(tmp_path / "whole" / cell.name, cell, tasks, episodes, seeds=[7] * 3, run=RUN)
    chunks = [tmp_path / cell.name / "chunk_000", tmp_path / cell.name / "chunk_001"]
    write_cell(chunks[0], cell, tasks, episodes[:2], seeds=[7] * 2, run=RUN | {"chunk": 0})
    write_cell(chunks[1], cell, tasks, episodes[2:], seeds=[7], run=RUN | {"chunk": 1})
    merged = merge_chunks(tmp_path / cell.name, chunks)
    assert merged == whole  # the chunk index is the chunk's own; the merged record is the cell's
    arrays, reference = read_cell(tmp_path / cell.name)[1], read_cell(tmp_path / "whole" / cell.name)[1]
    assert all(np.array_equal(arrays[k], reference[k], equal_nan=True) for k in reference)
    video = tmp_path / cell.name / merged["episodes"][0]["video"]
    assert video.read_bytes() == (chunks[0] / merged["episodes"][0]["video"]).read_bytes()
    other = Cell("open_vs_close", 12, "positive", "random_2", -2.0)
    write_cell(tmp_path / "stray", other, tasks, episodes[:1], seeds=[7], run=RUN)
    with pytest.raises(ValueError, match="holds cell positive_random_2_a-2"):
        merge_chunks(tmp_path / "mixed", [chunks[0], tmp_path / "stray"])
