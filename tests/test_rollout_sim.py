"""Closed-loop episodes in the real LIBERO simulator (CPU, one libero_goal env for the module).

`run_episode` (cameras rendered only for the policy) against openpi's loop rendering every step; `run_lockstep`
(several envs, batched policy calls) against `run_episode`; goal predicates on joint states set directly; task
lookup.
"""

import re

import numpy as np
import pytest
from helpers_rollout import ObservationPolicy, RecordingEnv, ScriptedPolicy, openpi_loop

from steering_core.rollout.assets import resolve_assets
from steering_core.rollout.episode import run_episode, run_lockstep
from steering_core.rollout.libero_env import (
    DeferredCameras,
    find_task,
    initial_states,
    make_env,
    prepare_libero,
    task_index,
)
from steering_core.rollout.predicates import Goal, GoalError, goal_joints, goal_thresholds, read_joints

SUITE = "libero_goal"
INSTRUCTION = "open the middle drawer of the cabinet"
DRAWER = "wooden_cabinet_1_middle_level"  # the middle drawer's slide joint (the env's own goal)
KNOB = "flat_stove_1_button"  # the stove knob's hinge


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    prepare_libero(resolve_assets("installed"), tmp_path_factory.mktemp("libero-config"))
    built = make_env(find_task(SUITE, task_index(SUITE, INSTRUCTION)))
    yield RecordingEnv(built)
    built.close()


@pytest.fixture(scope="module")
def init_state():
    return initial_states(SUITE, task_index(SUITE, INSTRUCTION))[3]


def goal(suite, index):
    return Goal.from_task(find_task(suite, index))


def set_joint(env, name, value):
    env.env.sim.data.qpos[env.env.sim.model.get_joint_qpos_addr(name)] = value
    env.env.sim.forward()


@pytest.mark.slow
def test_run_episode_matches_openpis_loop_rendering_every_step(env, init_state):
    naive, naive_frames = ScriptedPolicy(env, calls=3, seed=1), []
    env.actions.clear()
    done, steps = openpi_loop(env, naive, prompt=INSTRUCTION, init_state=init_state, max_steps=12, frames=naive_frames)
    naive_actions = list(env.actions)
    assert (done, steps) == (False, 12)

    scripted = ScriptedPolicy(env, calls=3, seed=1)
    env.actions.clear()
    # the watched goal is evaluated every step: turnoff in the knob's dead band flips the burner's visual flag,
    # which must not reach the images
    record = run_episode(
        env,
        scripted,
        prompt=INSTRUCTION,
        init_state=init_state,
        init_index=3,
        max_steps=12,
        toward_goal=goal("libero_90", 39),
        record_frames=True,
        episode_id=4,
    )

    assert naive.call_steps == scripted.call_steps == [10, 15, 20]  # after 10 wait steps, every 5 steps
    assert env.actions[:10] == [[0.0] * 6 + [-1.0]] * 10
    assert env.actions == naive_actions and len(env.actions) == 22  # the 12-step cut
    for mine, theirs in zip(scripted.elements, naive.elements, strict=True):
        assert np.array_equal(mine["observation/image"], theirs["observation/image"])
        assert np.array_equal(mine["observation/wrist_image"], theirs["observation/wrist_image"])
        assert mine["observation/image"].shape == (224, 224, 3) and mine["observation/image"].dtype == np.uint8
        state = mine["observation/state"]
        assert state.dtype == np.float64 and state.shape == (8,)
        assert np.array_equal(state[:3], theirs["observation/state"][:3])  # eef position
        assert np.array_equal(state[6:], theirs["observation/state"][6:])  # gripper qpos
        np.testing.assert_allclose(state[3:6], theirs["observation/state"][3:6], atol=1e-9)
        assert mine["prompt"] == INSTRUCTION
    assert len({element["observation/image"].tobytes() for element in scripted.elements}) == 3  # the robot moved

    assert (record.outcome, record.steps, record.success_step, record.toward_step) == ("neither", 12, None, None)
    assert record.policy_calls == 3 and record.prompt == INSTRUCTION and record.init_index == 3
    expected = np.concatenate([chunk[:5] for chunk in scripted.chunks])[:12]
    assert record.actions.dtype == np.float32 and np.array_equal(record.actions, expected)
    assert len(record.frames) == 13  # after the wait steps, then every step: the video plays at the control rate
    assert all(np.array_equal(mine, theirs) for mine, theirs in zip(record.frames, naive_frames, strict=True))
    assert all(np.array_equal(record.frames[5 * i], e["observation/image"]) for i, e in enumerate(scripted.elements))
    assert len({frame.tobytes() for frame in record.frames}) > 3  # the robot moves between replans too
    assert list(record.joints) == [DRAWER, KNOB] and all(v.shape == (13,) for v in record.joints.values())
    assert record.robot_qpos.shape == (13, 7) and np.isfinite(record.jerk) and record.jerk > 0
    assert scripted.events == [("start", INSTRUCTION, 4), ("end", False)]


@pytest.mark.slow
def test_instructed_success_ends_the_episode_at_the_env_done(env, init_state):
    def open_drawer(call):
        if call == 1:
            set_joint(env, DRAWER, -0.15)

    naive = ScriptedPolicy(env, calls=4, seed=2, on_call=open_drawer)
    done, steps = openpi_loop(env, naive, prompt=INSTRUCTION, init_state=init_state, max_steps=20)
    assert (done, steps) == (True, 6)  # the step after the second call

    scripted = ScriptedPolicy(env, calls=4, seed=2, on_call=open_drawer)
    record = run_episode(
        env, scripted, prompt=INSTRUCTION, init_state=init_state, init_index=3, max_steps=20, toward_goal=None
    )
    assert (record.outcome, record.steps, record.success_step, record.toward_step) == ("instructed", 6, 6, None)
    assert record.policy_calls == 2 and record.actions.shape == (6, 7) and record.frames == []
    assert list(record.joints) == [DRAWER] and record.joints[DRAWER][-1] < -0.14
    assert scripted.events[-1] == ("end", True)


@pytest.mark.slow
def test_watched_goal_ends_the_episode(env, init_state):
    def turn_knob(call):
        if call == 1:
            set_joint(env, KNOB, 1.0)

    scripted = ScriptedPolicy(env, calls=4, seed=3, on_call=turn_knob)
    env.actions.clear()
    record = run_episode(
        env,
        scripted,
        prompt="turn on the stove",
        init_state=init_state,
        init_index=3,
        max_steps=20,
        toward_goal=goal(SUITE, task_index(SUITE, "turn on the stove")),
        wait_steps=2,
        replan_steps=4,
    )
    assert (record.outcome, record.steps, record.success_step, record.toward_step) == ("toward", 5, None, 5)
    assert scripted.call_steps == [2, 6]
    assert record.joints[KNOB][0] == pytest.approx(0.0, abs=1e-3) and record.joints[KNOB][-1] >= 0.5
    assert scripted.events[-1] == ("end", False)


def test_goal_naming_absent_objects_is_refused_before_any_step(env, init_state):
    scripted = ScriptedPolicy(env, calls=1)
    env.actions.clear()
    other_scene = goal("libero_90", 28)  # KITCHEN_SCENE5: a white cabinet
    with pytest.raises(GoalError, match=r"^goal 'close the top drawer of the cabinet' \(KITCHEN_SCENE5_close_the_top"):
        run_episode(
            env, scripted, prompt="x", init_state=init_state, init_index=0, max_steps=5, toward_goal=other_scene
        )
    assert env.actions == [] and scripted.events == []
    with pytest.raises(GoalError, match=r"names \['white_cabinet_1_top_region'\], absent from the env's scene"):
        other_scene.check(env)


@pytest.mark.slow
def test_short_chunk_is_an_error(env, init_state):
    class Short(ScriptedPolicy):
        def infer(self, observation):
            return np.zeros((3, 7), dtype=np.float32)

    with pytest.raises(ValueError, match=r"policy returned actions of shape \(3, 7\), expected \(H, 7\) with H >= 5"):
        run_episode(
            env,
            Short(env, 1),
            prompt="x",
            init_state=init_state,
            init_index=0,
            max_steps=5,
            toward_goal=None,
            wait_steps=0,
        )


def test_images_are_only_taken_after_arming(env):
    cameras = DeferredCameras(env)
    with pytest.raises(RuntimeError, match="were not rendered: call arm"):
        cameras.take({})


def test_contrasting_predicates_on_joint_states_set_directly(env):
    open_top, close_top = goal("libero_90", 7), goal("libero_90", 0)
    turn_on, turn_off = goal(SUITE, task_index(SUITE, "turn on the stove")), goal("libero_90", 39)
    inner = env.env
    drawer = inner.get_object("wooden_cabinet_1").object_properties["articulation"]
    stove = inner.get_object("flat_stove_1").object_properties["articulation"]
    # the thresholds the spec states, read from the objects (strict: open < -0.14, close > 0, on >= 0.5, off < 0)
    assert (max(drawer["default_open_ranges"]), min(drawer["default_close_ranges"])) == (-0.14, 0.0)
    assert (min(stove["default_turnon_ranges"]), max(stove["default_turnoff_ranges"])) == (0.5, 0.0)

    top = goal_joints(open_top, env)
    assert list(top) == ["wooden_cabinet_1_top_level"] and goal_joints(close_top, env) == top
    assert list(goal_joints(turn_on, env)) == [KNOB] == list(goal_joints(turn_off, env))
    model = inner.sim.model
    (low, high), (knob_low, knob_high) = (model.jnt_range[model.joint_name2id(name)] for name in (*top, KNOB))
    assert (low, high) == pytest.approx((-0.16, 0.01)) and (knob_low, knob_high) == pytest.approx((-0.005, 2.1))

    for value, expected in [
        (low, (True, False)),
        (high, (False, True)),
        (-0.07, (False, False)),
        (-0.14, (False, False)),
        (0.0, (False, False)),
    ]:
        set_joint(env, "wooden_cabinet_1_top_level", value)
        assert (open_top.holds(env), close_top.holds(env)) == expected, value
        assert read_joints(env, top) == {"wooden_cabinet_1_top_level": pytest.approx(value)}
    for value, expected in [
        (knob_high, (True, False)),
        (knob_low, (False, True)),
        (0.25, (False, False)),
        (0.5, (True, False)),
        (0.0, (False, False)),
    ]:
        set_joint(env, KNOB, value)
        assert (turn_on.holds(env), turn_off.holds(env)) == expected, value

    # the sweep finds the same boundaries (to half a grid step), and leaves the state as it found it
    before = inner.sim.get_state().flatten()
    found = goal_thresholds([open_top, close_top, turn_on, turn_off], env)
    assert np.array_equal(inner.sim.get_state().flatten(), before)
    step, knob_step = (high - low) / 400, (knob_high - knob_low) / 400
    assert [label for label, _ in found["wooden_cabinet_1_top_level"]] == ["open", "close"]
    for (label, value), want, tolerance in zip([*found["wooden_cabinet_1_top_level"], *found[KNOB]],
                                               (-0.14, 0.0, 0.5, 0.0), (step, step, knob_step, knob_step), strict=True):
        assert abs(value - want) <= tolerance, (label, value)


def test_libero_90_tasks_of_the_issue():
    assert [find_task("libero_90", index).language for index in (7, 0, 20, 39)] == [
        "open the top drawer of the cabinet",
        "close the top drawer of the cabinet",
        "turn on the stove",
        "turn off the stove",
    ]
    # instructions repeat across libero_90's scenes: the task name picks one
    assert task_index("libero_90", "turn off the stove") == 39
    assert task_index("libero_90", "KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet") == 7
    assert task_index("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet") == 0
    assert task_index("libero_90", "KITCHEN_SCENE3_turn_on_the_stove") == 20
    for instruction, first, second in [
        ("open the top drawer of the cabinet", "7 (KITCHEN_SCENE1_", "11 (KITCHEN_SCENE2_"),
        ("close the top drawer of the cabinet", "0 (KITCHEN_SCENE10_", "28 (KITCHEN_SCENE5_"),
        ("turn on the stove", "20 (KITCHEN_SCENE3_", "44 (KITCHEN_SCENE9_"),
    ]:
        with pytest.raises(ValueError, match=rf"is the instruction of tasks {re.escape(first)}.*, {re.escape(second)}"):
            task_index("libero_90", instruction)
    with pytest.raises(ValueError, match=r"has no task 'open the middle drawer'; close: \['open the middle drawer of"):
        task_index(SUITE, "open the middle drawer")
    assert initial_states(SUITE, 0).shape == (50, 79)


class ScriptedGoal:
    """A watched goal whose `holds` answers from a list (then its last answer): the start check comes first."""

    predicates = ()

    def __init__(self, answers):
        self.answers = list(answers)

    def check(self, env):
        pass

    def holds(self, env):
        return self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]


@pytest.mark.parametrize(("answers", "expected"), [
    ([True, True, True, False, False, True], ("toward", 5, 5, True)),   # undone at step 3, reached again at 5
    ([True], ("neither", 8, None, True)),                               # held all along: nothing was done
    ([False, False, True], ("toward", 2, 2, False)),                    # the usual case
])
@pytest.mark.slow
def test_a_toward_goal_holding_at_the_start_counts_only_once_undone_and_redone(env, init_state, answers, expected):
    record = run_episode(env, ScriptedPolicy(env, calls=4, seed=5), prompt="turn on the stove", init_state=init_state,
                         init_index=0, max_steps=8, toward_goal=ScriptedGoal(answers), wait_steps=1)
    assert (record.outcome, record.steps, record.toward_step, record.toward_at_start) == expected


@pytest.mark.slow
def test_an_episode_does_not_depend_on_the_episodes_before_it(env, init_state):
    """A process keeps its env for the next chunk: each episode's seed and hard reset make that invisible."""
    def episode(on_env, seed):
        return run_episode(on_env, ScriptedPolicy(on_env, calls=3, seed=seed), prompt=INSTRUCTION,
                           init_state=init_state, init_index=0, max_steps=12, toward_goal=None)

    first = episode(env, 9)
    episode(env, 10)  # another episode in between, other actions
    again = episode(env, 9)
    fresh_env = make_env(find_task(SUITE, task_index(SUITE, INSTRUCTION)))
    try:
        fresh = episode(RecordingEnv(fresh_env), 9)
    finally:
        fresh_env.close()
    for other in (again, fresh):
        assert np.array_equal(other.robot_qpos, first.robot_qpos) and np.array_equal(other.actions, first.actions)
        assert all(np.array_equal(other.joints[name], first.joints[name]) for name in first.joints)


def assert_same_record(mine, theirs):
    assert (mine.prompt, mine.init_index, mine.outcome, mine.steps, mine.success_step, mine.toward_step,
            mine.policy_calls, mine.joint_limit_hits, mine.toward_at_start) == (
        theirs.prompt, theirs.init_index, theirs.outcome, theirs.steps, theirs.success_step, theirs.toward_step,
        theirs.policy_calls, theirs.joint_limit_hits, theirs.toward_at_start)
    assert np.array_equal(mine.actions, theirs.actions) and np.array_equal(mine.robot_qpos, theirs.robot_qpos)
    assert list(mine.joints) == list(theirs.joints)
    assert all(np.array_equal(mine.joints[name], theirs.joints[name]) for name in theirs.joints)
    assert np.array_equal(mine.jerk, theirs.jerk, equal_nan=True)
    assert len(mine.frames) == len(theirs.frames)
    assert all(np.array_equal(a, b) for a, b in zip(mine.frames, theirs.frames, strict=True))


@pytest.mark.slow
def test_lockstep_envs_give_each_episode_the_record_of_run_episode(env):
    """Three envs, five episodes of unequal budgets: slots are reused, replans fall on different steps, and the
    policy's rows depend only on their own observation, so every record equals the episode run alone."""
    states = initial_states(SUITE, task_index(SUITE, INSTRUCTION))
    toward = goal(SUITE, task_index(SUITE, "turn on the stove"))
    episodes = [dict(prompt=INSTRUCTION, init_state=states[index], init_index=index, max_steps=budget,
                     toward_goal=toward, record_frames=index == 1, episode_id=index)
                for index, budget in zip((1, 2, 3, 4, 5), (12, 4, 9, 7, 3), strict=True)]
    alone = [run_episode(env, ObservationPolicy(), **episode) for episode in episodes]

    task = find_task(SUITE, task_index(SUITE, INSTRUCTION))
    more = [make_env(task), make_env(task)]
    policy, ended = ObservationPolicy(), []
    try:
        together = run_lockstep([env, *more], policy, episodes, on_record=lambda _, record: ended.append(record.init_index))
    finally:
        for built in more:
            built.close()

    assert [record.init_index for record in together] == [1, 2, 3, 4, 5]
    for mine, theirs in zip(together, alone, strict=True):
        assert_same_record(mine, theirs)
    assert [record.steps for record in together] == [12, 4, 9, 7, 3]  # no goal reached: every budget spent
    assert len(together[0].frames) == 13 and together[1].frames == []
    # 1, 2, 3 start together; 4 takes 2's env after step 4 (lockstep steps 5-11), 5 takes 3's after step 9 (10-12)
    assert ended == [2, 3, 4, 1, 5]
    # replans at lockstep steps 1 (1, 2, 3), 5 (4), 6 (1, 3), 10 (4, 5), 11 (1): one call each
    assert policy.batch_sizes == [3, 1, 2, 2, 1]
    assert sum(record.policy_calls for record in alone) == 9
    assert [event for event in policy.events if event[0] == "start"] == [("start", i) for i in (1, 2, 3, 4, 5)]
    assert sum(event[0] == "end" for event in policy.events) == 5
