"""One closed-loop episode under openpi's LIBERO protocol, watching a second goal besides the instructed one."""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from steering_core.rollout.libero_env import DeferredCameras
from steering_core.rollout.predicates import Goal, goal_joints, read_joints
from steering_core.rollout.protocol import (
    DUMMY_ACTION,
    REPLAN_STEPS,
    RESIZE,
    SEED,
    WAIT_STEPS,
    policy_observation,
    preprocess_image,
)

ACTION_DIM = 7
LIMIT_MARGIN = 0.01  # rad: an arm joint this close to its model range limit counts as a hit


class RolloutPolicy(Protocol):
    """A policy the rollout loop asks for action chunks (in-process or over openpi's websocket protocol)."""

    def infer(self, observation: dict) -> np.ndarray:
        """Return (H, 7) float actions for openpi's observation element."""
        ...

    def episode_start(self, task: str, episode_id: int) -> None: ...

    def episode_end(self, success: bool) -> None: ...


@dataclass
class EpisodeRecord:
    """What one episode did; step arrays have a row for the state after the wait steps, then one per step."""

    prompt: str  # instruction the policy saw
    init_index: int  # index into the task's initial states
    outcome: str  # "instructed" | "toward" | "neither" (the first goal reached ends the episode)
    steps: int  # policy steps executed (wait steps excluded)
    success_step: int | None  # step at which the instructed goal (the env's `done`) held
    toward_step: int | None  # step at which the watched (steered-toward) goal came to hold
    joints: dict[str, np.ndarray]  # goal-tested joint name -> qpos per step, (steps + 1,) float64
    robot_qpos: np.ndarray  # (steps + 1, 7) arm joint positions
    actions: np.ndarray  # (steps, 7) float32 actions executed
    policy_calls: int
    jerk: float  # RMS third difference of robot_qpos (rad / step^3); NaN with fewer than 4 rows
    joint_limit_hits: int  # steps with an arm joint within LIMIT_MARGIN of its range limit
    # a recorded episode's agentview as the policy sees it (224, 224, 3), after the wait steps and after every step
    frames: list[np.ndarray] = field(default_factory=list)
    toward_at_start: bool = False  # the watched goal already held after the wait steps (it must break, then hold)


def jerk(robot_qpos: np.ndarray) -> float:
    """Return the RMS third difference over steps and joints of (steps + 1, joints) positions; NaN (no third
    difference, recorded as null) with fewer than 4 rows."""
    if len(robot_qpos) < 4:
        return math.nan
    return float(np.sqrt(np.mean(np.diff(robot_qpos, n=3, axis=0) ** 2)))


def _arm_joints(env) -> tuple[list[int], np.ndarray]:
    """Return the arm joints' qpos addresses and their model ranges (joints, 2), ±inf where unlimited."""
    robot, model = env.env.robots[0], env.env.sim.model
    ranges = np.array(model.jnt_range[robot._ref_joint_indexes], dtype=np.float64)
    ranges[~np.asarray(model.jnt_limited[robot._ref_joint_indexes], dtype=bool)] = (-np.inf, np.inf)
    return list(robot._ref_joint_pos_indexes), ranges


def _chunk(actions, replan_steps: int) -> np.ndarray:
    """Return the first `replan_steps` rows of a policy's (H, 7) chunk, or raise if it has fewer."""
    actions = np.asarray(actions)
    if actions.ndim != 2 or actions.shape[1] != ACTION_DIM or len(actions) < replan_steps:
        raise ValueError(
            f"policy returned actions of shape {actions.shape}, expected (H, {ACTION_DIM}) with H >= {replan_steps} "
            "(the replanning interval)"
        )
    return actions[:replan_steps]


def run_episode(
    env,
    policy: RolloutPolicy,
    *,
    prompt: str,
    init_state: np.ndarray,
    init_index: int,
    max_steps: int,
    toward_goal: Goal | None,
    replan_steps: int = REPLAN_STEPS,
    wait_steps: int = WAIT_STEPS,
    record_frames: bool = False,
    seed: int = SEED,
    episode_id: int = 0,
) -> EpisodeRecord:
    """Return the record of one episode of `policy` on `env` (an OffScreenRenderEnv), as openpi runs it.

    Seed, reset, set the initial state, take `wait_steps` dummy actions, then execute the first `replan_steps`
    actions of each chunk, asking the policy when the plan is empty. After every step the instructed goal (the
    env's `done`) and `toward_goal` are checked; the first that holds ends the episode, else `max_steps` does. A
    toward goal that already holds after the wait steps (the other task's start is this one's goal: a drawer the
    instruction closes starts open) counts only once it has stopped holding and holds again: doing nothing is not
    reaching it. Cameras render only for the observations the policy sees, and at every step of an episode whose
    frames are recorded (`record_frames`: its video plays at the control rate).
    """
    if toward_goal is not None:
        toward_goal.check(env)  # before any step: a scene without the goal's objects is a configuration error
    policy.episode_start(prompt, episode_id)
    env.seed(seed)
    env.reset()
    cameras = DeferredCameras(env)
    joints = goal_joints(Goal.of_env(env), env) | (goal_joints(toward_goal, env) if toward_goal is not None else {})
    arm_addresses, arm_ranges = _arm_joints(env)

    if wait_steps == 0:
        cameras.arm()
    obs = env.set_init_state(init_state)
    for wait in range(wait_steps):
        if wait == wait_steps - 1:
            cameras.arm()
        obs, _, _, _ = env.step(list(DUMMY_ACTION))

    toward_at_start = toward_goal is not None and toward_goal.holds(env)
    toward_armed = not toward_at_start
    joint_rows = [read_joints(env, joints)]
    qpos_rows = [env.env.sim.data.qpos[arm_addresses].copy()]
    actions, frames = [], []
    images = cameras.take(obs) if record_frames else None  # a recorded episode renders every step
    if record_frames:
        frames.append(preprocess_image(images[0], RESIZE))
    plan: collections.deque = collections.deque()
    policy_calls, steps, success_step, toward_step = 0, 0, None, None
    while steps < max_steps:
        if not plan:
            element = policy_observation(images if record_frames else cameras.take(obs), obs, prompt)
            plan.extend(_chunk(policy.infer(element), replan_steps))
            policy_calls += 1
        action = plan.popleft()
        if record_frames or (not plan and steps + 1 < max_steps):
            cameras.arm()  # the next step's observation feeds the next policy call (or the video)
        obs, _, done, _ = env.step(action.tolist())
        if record_frames:
            images = cameras.take(obs)
            frames.append(preprocess_image(images[0], RESIZE))
        steps += 1
        actions.append(action)
        joint_rows.append(read_joints(env, joints))
        qpos_rows.append(env.env.sim.data.qpos[arm_addresses].copy())
        success_step = steps if done else None
        if toward_goal is not None:
            holds = toward_goal.holds(env)
            toward_step = steps if holds and toward_armed else None
            toward_armed = toward_armed or not holds
        if done or toward_step is not None:
            break

    outcome = "instructed" if success_step is not None else "toward" if toward_step is not None else "neither"
    robot_qpos = np.array(qpos_rows, dtype=np.float64)
    near_limit = (robot_qpos[1:] < arm_ranges[:, 0] + LIMIT_MARGIN) | (robot_qpos[1:] > arm_ranges[:, 1] - LIMIT_MARGIN)
    record = EpisodeRecord(
        prompt=prompt,
        init_index=init_index,
        outcome=outcome,
        steps=steps,
        success_step=success_step,
        toward_step=toward_step,
        joints={name: np.array([row[name] for row in joint_rows], dtype=np.float64) for name in joints},
        robot_qpos=robot_qpos,
        actions=np.array(actions, dtype=np.float32).reshape(steps, ACTION_DIM),
        policy_calls=policy_calls,
        jerk=jerk(robot_qpos),
        joint_limit_hits=int(near_limit.any(axis=1).sum()),
        frames=frames,
        toward_at_start=toward_at_start,
    )
    policy.episode_end(outcome == "instructed")
    return record
