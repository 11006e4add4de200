"""Rollout settings, the run config's `rollout` section and the grid of paired cells (no simulator)."""

import re
import textwrap
from pathlib import Path

import pytest

from steering_core.config import load_run_config
from steering_core.pairs import other_side
from steering_core.rollout.cells import Cell
from steering_core.rollout.grid import cells, chunks
from steering_core.rollout.plan import config_jobs
from steering_core.rollout.settings import RolloutSettings
from tasks.rollout import job_inputs

CONFIG = """\
sources: {folders: [demos]}
dataset: {repo_id: libero_ds}
pairs:
  - {name: open_vs_close, positive: open the top drawer of the cabinet, negative: close the top drawer of the cabinet}
  - {name: on_vs_off, positive: turn on the stove, negative: turn off the stove}
layers: [1, 2]
model: {checkpoint: ckpt, tokenizer: tok.model, arch: {width: 64, depth: 4}}
rollout:
  pairs:
    open_vs_close: {positive: {suite: libero_90, task: 7}, negative: {suite: libero_90, task: 0}}
    on_vs_off: {positive: {suite: libero_90, task: KITCHEN_SCENE3_turn_on_the_stove}, negative: {suite: libero_90, task: 39}}
  alphas: [2, 0, 1]
  episodes: 7
  chunk_episodes: 3
  random_directions: 2
"""


def config(tmp_path: Path, extra: str = "", text: str = CONFIG):
    path = tmp_path / "run.yaml"
    path.write_text(textwrap.dedent(text) + extra, encoding="utf-8")
    return load_run_config(path)


def test_cells_are_the_issue_grid_with_signs_toward_the_other_task():
    settings = RolloutSettings(alphas=(0, 1, 2), random_directions=2)
    grid = cells("p", 3, settings, other_pairs=["q"])
    for side, sign in (("negative", 1.0), ("positive", -1.0)):
        mine = [c for c in grid if c.side == side]
        # α = 0 and the swap once; at each push the steered direction, 2 random controls and the wrong concept
        assert len(mine) == 2 + 2 * 4
        assert {(c.condition, c.alpha) for c in mine if c.alpha_toward == 2} == {
            ("steered", 2 * sign), ("random_0", 2 * sign), ("random_1", 2 * sign), ("wrong_concept:q", 2 * sign)}
        swap = next(c for c in mine if c.condition == "instruction_swap")
        assert swap.prompt_side != side and swap.steering_pair is None
    assert len({c.name for c in grid}) == len(grid)
    wrong = next(c for c in grid if c.condition == "wrong_concept:q")
    assert (wrong.steering_pair, wrong.direction("residual")) == ("q", "residual")
    assert next(c for c in grid if c.condition == "random_1").direction("residual") == "random_1"
    assert not [c for c in cells("p", 3, settings, other_pairs=[]) if c.condition.startswith("wrong")]


def test_chunks_partition_the_initial_states_every_cell_shares():
    settings = RolloutSettings(episodes=7, first_init_state=5, chunk_episodes=3)
    assert chunks(settings) == [(5, 6, 7), (8, 9, 10), (11,)]


def test_run_config_section_gives_jobs_per_cell_and_chunk(tmp_path):
    run = config(tmp_path)
    assert run.rollout.settings().alphas == (0.0, 1.0, 2.0)
    assert run.rollout_targets() == [("open_vs_close", 1), ("on_vs_off", 1), ("open_vs_close", 2), ("on_vs_off", 2)]
    jobs = config_jobs(run, "on_vs_off", 2)
    assert len(jobs) == 2 * (2 + 2 * 4) * 3  # cells x chunks
    assert {job.output_dir.parent for job in jobs} == {tmp_path / "data/rollouts/layer02/on_vs_off"}
    wrong = {job.cell.condition for job in jobs if job.cell.condition.startswith("wrong")}
    assert wrong == {"wrong_concept:open_vs_close"}  # the next rolled-out pair, cyclically
    assert {job.init_states for job in jobs} == {(0, 1, 2), (3, 4, 5), (6,)}


def test_rollout_layers_must_be_run_layers(tmp_path):
    assert config(tmp_path, "  layers: [2]\n").rollout_targets() == [("open_vs_close", 2), ("on_vs_off", 2)]
    with pytest.raises(ValueError, match=r"rollout.layers \[3\] are not layers of this run"):
        config(tmp_path, "  layers: [3]\n")


@pytest.mark.parametrize(("replace", "message"), [
    ("alphas: [2, 0, 1]", "alphas: [1, 2]", ),
    ("alphas: [2, 0, 1]", "alphas: [0, -1]"),
    ("    on_vs_off:", "    off_vs_on:"),
    ("task: 39", "task: -1"),
    ("suite: libero_90, task: 7", "suite: libero_100, task: 7"),
    ("random_directions: 2", "random_directions: 2\n  policy: http://gpu:8000"),
])
def test_bad_rollout_sections_are_refused_naming_the_field(tmp_path, replace, message):
    with pytest.raises(ValueError, match="rollout"):
        config(tmp_path, text=CONFIG.replace(replace, message))


def test_envs_per_worker_defaults_to_eight_or_the_chunks_episodes_and_refuses_bad_counts(tmp_path):
    assert [RolloutSettings().lockstep_envs(n) for n in (1, 5, 8, 20)] == [1, 5, 8, 8]
    assert [RolloutSettings(envs_per_worker=3).lockstep_envs(n) for n in (1, 5)] == [1, 3]
    assert config(tmp_path, "  envs_per_worker: 64\n").rollout.envs_per_worker == 64
    expected = ("envs_per_worker {}: expected a positive integer up to 64 (LIBERO envs in one process), or null "
                "for min(8, the chunk's episodes)")
    for bad in (0, -2, 65):
        with pytest.raises(ValueError, match=re.escape(expected.format(bad))):
            config(tmp_path, f"  envs_per_worker: {bad}\n")


def test_the_last_layer_is_refused_for_rollouts(tmp_path):
    with pytest.raises(ValueError, match="last decoder layer"):
        config(tmp_path, text=CONFIG.replace("layers: [1, 2]", "layers: [1, 3]").replace(
            "depth: 4}}", "depth: 4}}\nevaluate: null"))


def test_a_chunk_identity_changes_with_every_input_that_changes_its_episodes(tmp_path):
    run = config(tmp_path)
    job = next(j for j in config_jobs(run, "open_vs_close", 1) if j.cell.condition == "steered")
    vectors = job.vectors_root / "layer01" / "open_vs_close"
    vectors.mkdir(parents=True)
    (vectors / "residual_direction.safetensors").write_bytes(b"one")
    base = job_inputs(job)
    (vectors / "residual_direction.safetensors").write_bytes(b"two")
    assert job_inputs(job) != base
    cell = job.cell
    for change in ({"cell": Cell(cell.pair, cell.layer, cell.side, cell.condition, 4.0)}, {"init_states": (9,)},
                   {"cell": Cell(cell.pair, cell.layer, other_side(cell.side), cell.condition, cell.alpha)},
                   {"cell": Cell(cell.pair, cell.layer, cell.side, "random_0", cell.alpha)}):
        assert job_inputs(job.model_copy(update=change)) != job_inputs(job), change
    unsteered = next(j for j in config_jobs(run, "open_vs_close", 1) if j.cell.condition == "unsteered")
    assert job_inputs(unsteered)["vectors"] is None


def test_preflight_names_each_libero_task_it_cannot_find(tmp_path):
    from steering_core.preflight import run_problems

    bad = CONFIG.replace("task: 39", "task: 99").replace("task: KITCHEN_SCENE3_turn_on_the_stove", "task: turn on the oven")
    problems = run_problems(config(tmp_path, text=bad))
    assert any("libero_90: task index 99 out of range" in line for line in problems), problems
    assert any("turn on the oven" in line for line in problems), problems
    many = run_problems(config(tmp_path, "  first_init_state: 45\n"))
    assert any("libero_90[7]: initial states 45..51 asked, the task has 50 (0..49)" in line for line in many), many
    assert not [line for line in run_problems(config(tmp_path)) if "libero" in line.lower()]
    ambiguous = CONFIG.replace("task: KITCHEN_SCENE3_turn_on_the_stove", "task: turn on the stove")
    assert any("tasks 20 (KITCHEN_SCENE3_turn_on_the_stove), 44" in line for line in run_problems(
        config(tmp_path, text=ambiguous)))


def test_a_chunk_identity_covers_the_code_it_runs():
    from steering_core.identity import code_modules
    from tasks.rollout import CHUNK_CODE

    modules = set(code_modules(CHUNK_CODE))
    assert {f"steering_core.rollout.{name}" for name in (
        "run", "episode", "libero_env", "protocol", "predicates", "assets", "records", "client", "cells")} <= modules
    assert {"steering_core.evaluate.run", "steering_core.pi05.policy", "steering_core.serve.catalog"} <= modules


def test_settings_enter_a_chunk_identity_only_when_they_change_its_episodes():
    from tasks.rollout import settings_inputs

    base = RolloutSettings()
    for change in ({"max_steps": 40}, {"seed": 8}, {"noise_seed": 1}, {"videos": False}, {"direction": "mean_difference"}):
        assert settings_inputs(base.model_copy(update=change)) != settings_inputs(base), change
    for change in ({"policy": "ws://gpu:8000"}, {"libero_assets": "/assets"}, {"device": "cpu"}, {"note": "x"},
                   {"chunk_episodes": 2}, {"envs_per_worker": 3}, {"compiled": True}, {"compiled": False}):
        assert settings_inputs(base.model_copy(update=change)) == settings_inputs(base), change
