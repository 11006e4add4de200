"""Synthetic LIBERO files: exact schema and attributes, determinism, and the motion they promise."""

from __future__ import annotations

import json
import re

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.data import libero
from steering_core.synthetic.libero import (
    DEMO_SUITE_TASKS,
    DRAWER_CLOSE,
    DRAWER_OPEN,
    STOVE_OFF,
    STOVE_ON,
    MotionSpec,
    SyntheticSettings,
    SyntheticTask,
    make_demo,
    write_demo_suite,
    write_libero_file,
)

SMALL = SyntheticSettings(image_size=16, num_steps=40, length_jitter=6, state_dim=20)
OPEN_TASK, CLOSE_TASK, STOVE_ON_TASK, STOVE_OFF_TASK = DEMO_SUITE_TASKS

# the released files' datasets: name -> (dtype, trailing shape)
EXPECTED = {
    "obs/agentview_rgb": (np.uint8, (16, 16, 3)),
    "obs/eye_in_hand_rgb": (np.uint8, (16, 16, 3)),
    "obs/ee_pos": (np.float64, (3,)),
    "obs/ee_ori": (np.float64, (3,)),
    "obs/ee_states": (np.float64, (6,)),
    "obs/gripper_states": (np.float64, (2,)),
    "obs/joint_states": (np.float64, (7,)),
    "actions": (np.float64, (7,)),
    "states": (np.float64, (20,)),
    "robot_states": (np.float64, (9,)),
    "rewards": (np.uint8, ()),
    "dones": (np.uint8, ()),
}


def test_file_has_the_exact_libero_layout(tmp_path):
    written = write_libero_file(tmp_path, OPEN_TASK, num_demos=3, settings=SMALL)
    assert written.path.name == "KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet_demo.hdf5"
    assert re.fullmatch(r"KITCHEN_SCENE\d+_[a-z_]+_demo\.hdf5", written.path.name)
    with h5py.File(written.path, "r") as handle:
        assert list(handle) == ["data"]
        data = handle["data"]
        assert sorted(data) == ["demo_0", "demo_1", "demo_2"]
        attrs = data.attrs
        problem = json.loads(attrs["problem_info"])
        assert problem["language_instruction"] == DRAWER_OPEN
        assert {"problem_name", "domain_name"} <= set(problem)
        assert f"(:language {DRAWER_OPEN})" in attrs["bddl_file_content"]
        assert attrs["bddl_file_name"].endswith("KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet.bddl")
        env_args = json.loads(attrs["env_args"])
        kwargs = env_args["env_kwargs"]
        assert (kwargs["camera_heights"], kwargs["camera_widths"], kwargs["control_freq"]) == (16, 16, 20)
        assert kwargs["camera_names"] == ["robot0_eye_in_hand", "agentview"]
        assert {"type", "env_name", "problem_name", "bddl_file"} <= set(env_args)
        assert attrs["env_name"] and attrs["macros_image_convention"] == "opengl"
        lengths = [truth.num_steps for truth in written.demos]
        assert int(attrs["num_demos"]) == 3 and int(attrs["total"]) == sum(lengths)
        for key, steps in zip(["demo_0", "demo_1", "demo_2"], lengths):
            demo = data[key]
            assert sorted(demo) == ["actions", "dones", "obs", "rewards", "robot_states", "states"]
            assert sorted(demo["obs"]) == sorted(n.split("/")[1] for n in EXPECTED if n.startswith("obs/"))
            for name, (dtype, trailing) in EXPECTED.items():
                assert demo[name].dtype == dtype, name
                assert demo[name].shape == (steps, *trailing), name
            assert int(demo.attrs["num_samples"]) == steps
            assert "<mujoco" in demo.attrs["model_file"]
            np.testing.assert_array_equal(demo.attrs["init_state"], demo["states"][0])
            ee_states = np.hstack([demo["obs/ee_pos"][()], demo["obs/ee_ori"][()]])
            np.testing.assert_array_equal(demo["obs/ee_states"][()], ee_states)
            assert demo["rewards"][()].tolist() == [0] * (steps - 1) + [1]
            assert demo["dones"][()].tolist() == [0] * (steps - 1) + [1]
    # and our own reader accepts it
    assert libero.validate_file(written.path).demo_lengths == dict(zip(["demo_0", "demo_1", "demo_2"], lengths))
    assert libero.instruction_from_filename(written.path) == DRAWER_OPEN


def test_generation_is_deterministic_per_seed():
    a, truth_a = make_demo(STOVE_ON_TASK, 3, SMALL)
    b, truth_b = make_demo(STOVE_ON_TASK, 3, SMALL)
    c, _ = make_demo(STOVE_ON_TASK, 3, SMALL.model_copy(update={"seed": 1}))
    assert truth_a == truth_b
    for name in ("agentview_rgb", "eye_in_hand_rgb", "ee_pos", "actions", "states"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.ee_pos, c.ee_pos)


@pytest.mark.parametrize("task", DEMO_SUITE_TASKS, ids=lambda t: t.instruction)
def test_motion_matches_the_spec(task):
    spec = task.motion
    for index in range(4):
        demo, truth = make_demo(task, index, SMALL)
        state = demo.state8().astype(np.float64)
        axis_values = state[:, spec.axis]
        # terminal displacement: the chosen axis moves `distance` in `direction`
        delta = axis_values[-1] - axis_values[0]
        assert np.sign(delta) == spec.direction
        assert abs(delta) == pytest.approx(spec.distance, abs=0.01)
        assert truth.axis_delta == pytest.approx(delta, abs=1e-6)
        # the other orientation/position axes barely move (axis 0 carries the shared 4 cm approach)
        for other in range(6):
            if other not in (spec.axis, 0):
                assert abs(state[-1, other] - state[0, other]) < 0.01
        # all of the motion happens inside [start_step, end_step]
        inside = axis_values[truth.end_step] - axis_values[truth.start_step]
        assert inside == pytest.approx(delta, abs=0.005)
        steps = np.abs(np.diff(axis_values))
        outside = np.r_[steps[: truth.start_step], steps[truth.end_step :]]
        assert outside.max() < 0.005 < steps[truth.start_step : truth.end_step].max()
        assert 0 < truth.start_step < truth.end_step < truth.num_steps - 1
        # the gripper closes exactly during the window
        closed = demo.actions[:, 6] > 0
        assert np.flatnonzero(closed).tolist() == list(range(truth.start_step, truth.end_step + 1))


def test_pairs_move_one_axis_in_opposite_directions():
    """A naive contrast: the axis with the largest opposite-signed mean displacement is the spec's axis."""
    for pos_task, neg_task in [(OPEN_TASK, CLOSE_TASK), (STOVE_ON_TASK, STOVE_OFF_TASK)]:
        pos = np.array([_displacement(pos_task, i) for i in range(4)]).mean(axis=0)
        neg = np.array([_displacement(neg_task, i) for i in range(4)]).mean(axis=0)
        opposite = np.where(np.sign(pos) != np.sign(neg), np.minimum(abs(pos), abs(neg)), 0.0)
        assert int(np.argmax(opposite)) == pos_task.motion.axis == neg_task.motion.axis
        assert pos[pos_task.motion.axis] > 0.05 and neg[neg_task.motion.axis] < -0.05


def _displacement(task, index):
    state = make_demo(task, index, SMALL)[0].state8()
    return state[-1] - state[0]


def test_images_are_upside_down_renders_that_change_over_time():
    demo, _ = make_demo(OPEN_TASK, 0, SyntheticSettings(image_size=32, num_steps=20))
    for frames in (demo.agentview_rgb, demo.eye_in_hand_rgb):
        assert frames.shape == (20, 32, 32, 3) and frames.dtype == np.uint8
        assert frames.std() > 10
        assert not np.array_equal(frames[0], frames[-1])
    # upright, the agent view has a bright wall on top; LIBERO stores renders rotated 180 degrees
    upright = demo.agentview_rgb[:, ::-1, ::-1].astype(float)
    assert upright[:, :8, :, 0].mean() > upright[:, -8:, :, 0].mean() + 50
    stored = demo.agentview_rgb.astype(float)
    assert stored[:, -8:, :, 0].mean() > stored[:, :8, :, 0].mean() + 50


def test_window_must_fit_the_episode():
    with pytest.raises(ValueError, match="must lie inside"):
        MotionSpec(axis=1, direction=1, window=(0.9, 0.99), window_jitter=0.05)
    with pytest.raises(ValueError):
        MotionSpec(axis=6, direction=1)  # grippers follow the grasp, they are not motion axes
    with pytest.raises(ValueError, match="no demos requested"):
        task = SyntheticTask(instruction="x", motion=MotionSpec(axis=0, direction=1))
        write_libero_file("/nonexistent", task, num_demos=0)


def test_demo_suite_and_cli(tmp_path):
    settings = SyntheticSettings(image_size=16, num_steps=10)
    files = write_demo_suite(tmp_path / "lib", demos_per_task=2, settings=settings)
    assert sorted(f.path.name for f in files) == [
        "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet_demo.hdf5",
        "KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet_demo.hdf5",
        "KITCHEN_SCENE3_turn_on_the_stove_demo.hdf5",
        "KITCHEN_SCENE8_turn_off_the_stove_demo.hdf5",
    ]
    assert {f.instruction for f in files} == {DRAWER_OPEN, DRAWER_CLOSE, STOVE_ON, STOVE_OFF}
    assert all(len(f.demos) == 2 for f in files)

    out = tmp_path / "cli"
    result = CliRunner().invoke(
        app,
        ["make-demos", "--output-dir", str(out), "--image-size", "16", "--demos-per-task", "2", "--num-steps", "10"],
    )
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == sorted(f.path.name for f in files)
    for path in out.iterdir():
        info = libero.validate_file(path)
        assert info.num_demos == 2
        first = libero.read_demo(path, "demo_0")
        assert first.agentview_rgb.shape[1:] == (16, 16, 3)
