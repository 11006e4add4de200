"""Rollout settings, the run config's `rollout` section and the grid of paired cells (no simulator)."""

import json
import re
import textwrap
from pathlib import Path

import pytest

from steering_core.config import load_run_config
from steering_core.pairs import other_side
from steering_core.rollout.cells import Cell
from steering_core.rollout.grid import cells, chunks
from steering_core.rollout.plan import config_jobs
from steering_core.rollout.run import steering_entries
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


def config(tmp_path: Path, extra: str = "", text: str = CONFIG, methods: tuple[str, ...] = ("sae", "mean_difference")):
    """Load the run config; each pair's directions.json at layers 1 and 2 lists `methods` (as phase 3 writes it)."""
    path = tmp_path / "run.yaml"
    path.write_text(textwrap.dedent(text) + extra, encoding="utf-8")
    run = load_run_config(path)
    for layer in (1, 2):
        for pair in ("open_vs_close", "on_vs_off"):
            folder = run.layer_path(layer) / pair
            folder.mkdir(parents=True, exist_ok=True)
            listed = {name: {"file": f"{name}_direction.safetensors"} for name in methods}
            (folder / "directions.json").write_text(json.dumps({"pair": pair, "methods": listed}))
    return run


def test_cells_are_the_issue_grid_with_signs_toward_the_other_task():
    settings = RolloutSettings(alphas=(0, 1, 2), random_directions=2)
    grid = cells("p", 3, settings, other_pairs=["q"])
    for side, sign in (("negative", 1.0), ("positive", -1.0)):
        mine = [c for c in grid if c.side == side]
        # α = 0 and the swap once; at each push the default direction (sae, add), 2 random controls, the wrong concept
        assert len(mine) == 2 + 2 * 4
        assert {(c.condition, c.alpha) for c in mine if c.alpha_toward == 2} == {
            ("sae", 2 * sign), ("random_0", 2 * sign), ("random_1", 2 * sign), ("wrong_concept:q/sae", 2 * sign)}
        swap = next(c for c in mine if c.condition == "instruction_swap")
        assert swap.prompt_side != side and swap.steering_pair is None
    assert len({c.name for c in grid}) == len(grid)
    assert "negative_sae_a+2" in {c.name for c in grid}  # the default's folders: <side>_<method>_a<α>
    wrong = next(c for c in grid if c.condition == "wrong_concept:q/sae")
    assert (wrong.steering_pair, wrong.direction, wrong.mode) == ("q", "sae", "add")
    assert next(c for c in grid if c.condition == "random_1").direction == "random_1"
    assert not [c for c in cells("p", 3, settings, other_pairs=[]) if c.condition.startswith("wrong")]


def test_two_methods_in_two_modes_share_the_controls():
    settings = RolloutSettings(alphas=(0, 0.5, 1), random_directions=2, methods=("mean_difference", "sae"),
                               modes=("add", "clamp"))
    grid = cells("p", 3, settings, other_pairs=["q"])
    for side in ("negative", "positive"):
        mine = [c for c in grid if c.side == side]
        assert [c.condition for c in mine[:2]] == ["unsteered", "instruction_swap"]
        for push in (0.5, 1.0):
            # one cell per method x mode, then the random controls and the wrong concept (first method, add) once
            assert [(c.condition, c.method, c.mode) for c in mine if c.alpha_toward == push] == [
                ("mean_difference", "mean_difference", "add"), ("mean_difference+clamp", "mean_difference", "clamp"),
                ("sae", "sae", "add"), ("sae+clamp", "sae", "clamp"), ("random_0", None, "add"),
                ("random_1", None, "add"), ("wrong_concept:q/mean_difference", "mean_difference", "add")]
        assert len(mine) == 2 + 2 * 7
    assert len({c.name for c in grid}) == len(grid) == 32
    assert "positive_sae+clamp_a-0.5" in {c.name for c in grid}


def test_steering_entries_add_signed_alpha_and_clamp_to_the_level_fraction_toward_the_other_concept():
    # add: the signed α in residual_norm units, as before
    assert steering_entries(Cell.pushed("p", 3, "positive", "sae", 2.0)) == [
        {"pair": "p", "layer": 3, "alpha": -2.0, "direction": "sae", "alpha_units": "residual_norm"}]
    # clamp, t = m₋ + α(m₊ − m₋): the negative side pushed 0.25 of the way up is α = 0.25; the positive side pushed
    # 0.25 of the way down is t = m₊ + 0.25(m₋ − m₊) = m₋ + 0.75(m₊ − m₋): α = 0.75; pushed 1.5, α = −0.5
    for side, push, level in (("negative", 0.25, 0.25), ("positive", 0.25, 0.75), ("negative", 1.0, 1.0),
                              ("positive", 1.0, 0.0), ("positive", 1.5, -0.5)):
        cell = Cell.pushed("p", 3, side, "mean_difference+clamp", push)
        assert steering_entries(cell) == [
            {"pair": "p", "layer": 3, "alpha": level, "direction": "mean_difference", "mode": "clamp"}], (side, push)
    assert steering_entries(Cell.pushed("p", 3, "negative", "wrong_concept:q/sae_top_k", 1.0)) == [
        {"pair": "q", "layer": 3, "alpha": 1.0, "direction": "sae_top_k", "alpha_units": "residual_norm"}]
    assert steering_entries(Cell("p", 3, "negative", "instruction_swap", 0.0)) == []


def test_chunks_partition_the_initial_states_every_cell_shares():
    settings = RolloutSettings(episodes=7, first_init_state=5, chunk_episodes=3)
    assert chunks(settings) == [(5, 6, 7), (8, 9, 10), (11,)]


def test_run_config_section_gives_jobs_per_cell_and_chunk(tmp_path):
    run = config(tmp_path)
    assert run.rollout.settings().alphas == (0.0, 1.0, 2.0)
    assert (run.rollout.methods, run.rollout.modes) == (("sae",), ("add",))
    assert run.rollout_targets() == [("open_vs_close", 1), ("on_vs_off", 1), ("open_vs_close", 2), ("on_vs_off", 2)]
    jobs = config_jobs(run, "on_vs_off", 2)
    assert len(jobs) == 2 * (2 + 2 * 4) * 3  # cells x chunks
    assert {job.output_dir.parent for job in jobs} == {tmp_path / "data/rollouts/layer02/on_vs_off"}
    wrong = {job.cell.condition for job in jobs if job.cell.condition.startswith("wrong")}
    assert wrong == {"wrong_concept:open_vs_close/sae"}  # the next rolled-out pair, cyclically
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
    run = config(tmp_path, "  methods: [sae, mean_difference]\n  modes: [add, clamp]\n")
    job = next(j for j in config_jobs(run, "open_vs_close", 1) if j.cell.condition == "sae")
    vectors = job.vectors_root / "layer01" / "open_vs_close"
    (vectors / "sae_direction.safetensors").write_bytes(b"one")
    base = job_inputs(job)
    (vectors / "sae_direction.safetensors").write_bytes(b"two")
    assert job_inputs(job) != base
    cell = job.cell
    for change in ({"cell": Cell(cell.pair, cell.layer, cell.side, cell.condition, 4.0)}, {"init_states": (9,)},
                   {"cell": Cell(cell.pair, cell.layer, other_side(cell.side), cell.condition, cell.alpha)},
                   {"cell": Cell(cell.pair, cell.layer, cell.side, "random_0", cell.alpha)},
                   {"cell": Cell(cell.pair, cell.layer, cell.side, "mean_difference", cell.alpha)},  # the method
                   {"cell": Cell(cell.pair, cell.layer, cell.side, "sae+clamp", cell.alpha)},  # the mode
                   {"cell": Cell(cell.pair, cell.layer, cell.side, "wrong_concept:on_vs_off/sae", cell.alpha)},
                   {"cell": Cell(cell.pair, cell.layer, cell.side, "wrong_concept:on_vs_off/mean_difference",
                                 cell.alpha)}):
        assert job_inputs(job.model_copy(update=change)) != job_inputs(job), change
    # every cell of the grid has an identity of its own
    jobs = [j for j in config_jobs(run, "open_vs_close", 1) if j.chunk == 0]
    assert len({json.dumps(job_inputs(j), sort_keys=True) for j in jobs}) == len(jobs) == 2 * (2 + 2 * 7)
    unsteered = next(j for j in config_jobs(run, "open_vs_close", 1) if j.cell.condition == "unsteered")
    assert job_inputs(unsteered)["vectors"] is None


def test_rollout_methods_and_modes_are_refused_naming_the_setting(tmp_path):
    for methods, message in ((("sae", "cosine"), "methods ['sae', 'cosine']: ['cosine'] not registered"),
                             (("residual",), "methods ['residual']: ['residual'] not registered"),
                             (("sae", "sae"), "methods ['sae', 'sae']: give at least one direction method, each once"),
                             ((), "methods []: give at least one direction method, each once")):
        with pytest.raises(ValueError, match=re.escape(message)):
            RolloutSettings(methods=methods)
    for modes, message in ((("add", "add"), "modes ['add', 'add']: give add and/or clamp, each once"),
                           ((), "modes []: give add and/or clamp, each once")):
        with pytest.raises(ValueError, match=re.escape(message)):
            RolloutSettings(modes=modes)
    with pytest.raises(ValueError, match="modes"):
        RolloutSettings(modes=("scale",))
    with pytest.raises(ValueError, match=r"rollout.*methods.*not registered"):
        config(tmp_path, "  methods: [sae, cosine]\n")
    with pytest.raises(ValueError, match=r"rollout.*set by the run config: use `rollout.methods`"):
        config(tmp_path, "  direction: residual\n")


def test_a_method_phase_3_did_not_write_is_refused_when_the_jobs_are_planned(tmp_path):
    run = config(tmp_path, "  methods: [sae, sae_top_k]\n")
    path = run.layer_path(2) / "on_vs_off" / "directions.json"
    with pytest.raises(ValueError) as err:
        config_jobs(run, "on_vs_off", 2)
    assert str(err.value) == (
        f"rollout.methods ['sae', 'sae_top_k']: pair 'on_vs_off', layer 2 has no ['sae_top_k'] direction (phase 3 "
        f"wrote ['sae', 'mean_difference'] in {path}); roll out those, or add the method to steering.methods and "
        "re-run the steer step")
    # the wrong concept steers with the next pair's direction of the first method: that pair must have it too
    run = config(tmp_path, "  methods: [sae]\n")
    (run.layer_path(2) / "open_vs_close" / "directions.json").write_text(json.dumps({"methods": {"mean_difference": {}}}))
    with pytest.raises(ValueError, match=re.escape("rollout.methods ['sae']: pair 'open_vs_close', layer 2 has no "
                                                   "['sae'] direction")):
        config_jobs(run, "on_vs_off", 2)
    path.unlink()
    with pytest.raises(FileNotFoundError, match=re.escape(f"pair 'on_vs_off', layer 2 has no {path}; run the steer")):
        config_jobs(run, "on_vs_off", 2)


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
    for change in ({"max_steps": 40}, {"seed": 8}, {"noise_seed": 1}, {"videos": False}):
        assert settings_inputs(base.model_copy(update=change)) != settings_inputs(base), change
    # methods and modes only choose the grid's cells, each of which names its own method and mode (above)
    for change in ({"policy": "ws://gpu:8000"}, {"libero_assets": "/assets"}, {"device": "cpu"}, {"note": "x"},
                   {"chunk_episodes": 2}, {"envs_per_worker": 3}, {"compiled": True}, {"compiled": False},
                   {"methods": ("mean_difference", "sae")}, {"modes": ("add", "clamp")}):
        assert settings_inputs(base.model_copy(update=change)) == settings_inputs(base), change
