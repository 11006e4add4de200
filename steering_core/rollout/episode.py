"""Closed-loop episodes under openpi's LIBERO protocol, watching a second goal besides the instructed one: one
episode on one env (`run_episode`), or several envs in lockstep sharing batched policy calls (`run_lockstep`)."""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

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

    def infer_batch(self, observations: list[dict]) -> list[np.ndarray]:
        """Return (H, 7) float actions for each observation element, in one call; each row as `infer` alone."""
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


class Episode:
    """One episode stepped from outside: `start` it, give it a plan whenever `needs_plan` (the policy's chunk for its
    `observation()`), `step` it until it has `ended`, then take its `record()`. `run_episode` drives one;
    `run_lockstep` drives several, one env each, batching the policy calls of those that need a plan."""

    def __init__(self, env, policy: RolloutPolicy, *, prompt: str, init_state: np.ndarray, init_index: int,
                 max_steps: int, toward_goal: Goal | None, replan_steps: int = REPLAN_STEPS,
                 wait_steps: int = WAIT_STEPS, record_frames: bool = False, seed: int = SEED,
                 episode_id: int = 0) -> None:
        self.env, self.policy, self.prompt, self.toward_goal = env, policy, prompt, toward_goal
        self.init_state, self.init_index, self.max_steps = init_state, init_index, max_steps
        self.replan_steps, self.wait_steps, self.record_frames = replan_steps, wait_steps, record_frames
        self.seed, self.episode_id = seed, episode_id

    def start(self) -> None:
        """Seed and reset the env, set the initial state and take the wait steps."""
        env, toward_goal = self.env, self.toward_goal
        if toward_goal is not None:
            toward_goal.check(env)  # before any step: a scene without the goal's objects is a configuration error
        self.policy.episode_start(self.prompt, self.episode_id)
        env.seed(self.seed)
        env.reset()
        self.cameras = DeferredCameras(env)
        self.joint_names = goal_joints(Goal.of_env(env), env) | (
            goal_joints(toward_goal, env) if toward_goal is not None else {})
        self.arm_addresses, self.arm_ranges = _arm_joints(env)

        if self.wait_steps == 0:
            self.cameras.arm()
        self.obs = env.set_init_state(self.init_state)
        for wait in range(self.wait_steps):
            if wait == self.wait_steps - 1:
                self.cameras.arm()
            self.obs, _, _, _ = env.step(list(DUMMY_ACTION))

        self.toward_at_start = toward_goal is not None and toward_goal.holds(env)
        self.toward_armed = not self.toward_at_start
        self.joint_rows = [read_joints(env, self.joint_names)]
        self.qpos_rows = [env.env.sim.data.qpos[self.arm_addresses].copy()]
        self.actions: list[np.ndarray] = []
        self.frames: list[np.ndarray] = []
        # a recorded episode renders every step
        self.images = self.cameras.take(self.obs) if self.record_frames else None
        if self.record_frames:
            self.frames.append(preprocess_image(self.images[0], RESIZE))
        self.plan: collections.deque = collections.deque()
        self.policy_calls, self.steps, self.success_step, self.toward_step = 0, 0, None, None

    @property
    def ended(self) -> bool:
        """Return True once a goal holds (the instructed one: the env's `done`) or the step budget is spent."""
        return self.success_step is not None or self.toward_step is not None or self.steps >= self.max_steps

    @property
    def needs_plan(self) -> bool:
        """Return True when the next step needs a new chunk from the policy."""
        return not self.plan

    def observation(self) -> dict:
        """Return openpi's observation element of the current state (the cameras were armed for it)."""
        images = self.images if self.record_frames else self.cameras.take(self.obs)
        return policy_observation(images, self.obs, self.prompt)

    def give_plan(self, actions) -> None:
        """Plan the first `replan_steps` rows of the policy's (H, 7) chunk."""
        self.plan.extend(_chunk(actions, self.replan_steps))
        self.policy_calls += 1

    def step(self) -> None:
        """Execute the next planned action and check both goals."""
        env = self.env
        action = self.plan.popleft()
        if self.record_frames or (not self.plan and self.steps + 1 < self.max_steps):
            self.cameras.arm()  # the next step's observation feeds the next policy call (or the video)
        self.obs, _, done, _ = env.step(action.tolist())
        if self.record_frames:
            self.images = self.cameras.take(self.obs)
            self.frames.append(preprocess_image(self.images[0], RESIZE))
        self.steps += 1
        self.actions.append(action)
        self.joint_rows.append(read_joints(env, self.joint_names))
        self.qpos_rows.append(env.env.sim.data.qpos[self.arm_addresses].copy())
        self.success_step = self.steps if done else None
        if self.toward_goal is not None:
            holds = self.toward_goal.holds(env)
            self.toward_step = self.steps if holds and self.toward_armed else None
            self.toward_armed = self.toward_armed or not holds

    def record(self) -> EpisodeRecord:
        """Return the ended episode's record and tell the policy it ended."""
        outcome = ("instructed" if self.success_step is not None else "toward" if self.toward_step is not None
                   else "neither")
        robot_qpos = np.array(self.qpos_rows, dtype=np.float64)
        low, high = self.arm_ranges[:, 0] + LIMIT_MARGIN, self.arm_ranges[:, 1] - LIMIT_MARGIN
        near_limit = (robot_qpos[1:] < low) | (robot_qpos[1:] > high)
        record = EpisodeRecord(
            prompt=self.prompt,
            init_index=self.init_index,
            outcome=outcome,
            steps=self.steps,
            success_step=self.success_step,
            toward_step=self.toward_step,
            joints={name: np.array([row[name] for row in self.joint_rows], dtype=np.float64)
                    for name in self.joint_names},
            robot_qpos=robot_qpos,
            actions=np.array(self.actions, dtype=np.float32).reshape(self.steps, ACTION_DIM),
            policy_calls=self.policy_calls,
            jerk=jerk(robot_qpos),
            joint_limit_hits=int(near_limit.any(axis=1).sum()),
            frames=self.frames,
            toward_at_start=self.toward_at_start,
        )
        self.policy.episode_end(outcome == "instructed")
        return record


def run_episode(env, policy: RolloutPolicy, **episode: Any) -> EpisodeRecord:
    """Return the record of one episode of `policy` on `env` (an OffScreenRenderEnv), as openpi runs it.

    `episode` holds `Episode`'s keywords: prompt, init_state, init_index, max_steps, toward_goal, and optionally
    replan_steps, wait_steps, record_frames, seed, episode_id. Seed, reset, set the initial state, take
    `wait_steps` dummy actions, then execute the first `replan_steps` actions of each chunk, asking the policy
    (`infer`) when the plan is empty. After every step the instructed goal (the env's `done`) and `toward_goal`
    are checked; the first that holds ends the episode, else `max_steps` does. A toward goal that already holds
    after the wait steps (the other task's start is this one's goal: a drawer the instruction closes starts open)
    counts only once it has stopped holding and holds again: doing nothing is not reaching it. Cameras render
    only for the observations the policy sees, and at every step of an episode whose frames are recorded
    (`record_frames`: its video plays at the control rate).
    """
    one = Episode(env, policy, **episode)
    one.start()
    while not one.ended:
        if one.needs_plan:
            one.give_plan(policy.infer(one.observation()))
        one.step()
    return one.record()


def run_lockstep(envs: list, policy: RolloutPolicy, episodes: list[dict],
                 on_record: Callable[[int, EpisodeRecord], None] | None = None) -> list[EpisodeRecord]:
    """Return the records of `episodes` (each `Episode`'s keywords, as `run_episode` takes them), run on `envs`
    in lockstep: each env runs one episode at a time and takes the next waiting one when its own ends. At every
    step the episodes needing a plan share one `policy.infer_batch` call, in slot order; each episode's record
    equals `run_episode`'s when the policy's rows do not depend on each other. `on_record(i, record)` is called
    as episode i ends. Returns the records in the order of `episodes`.
    """
    if not envs:
        raise ValueError("run_lockstep needs at least one env")
    waiting = collections.deque(enumerate(episodes))
    records: dict[int, EpisodeRecord] = {}
    slots: list[tuple[int, Episode] | None] = [None] * len(envs)

    def finish(slot: int) -> None:
        index, episode = slots[slot]
        records[index] = episode.record()
        slots[slot] = None
        if on_record is not None:
            on_record(index, records[index])

    while waiting or any(slots):
        for slot, env in enumerate(envs):
            while slots[slot] is None and waiting:
                index, keywords = waiting.popleft()
                slots[slot] = (index, Episode(env, policy, **keywords))
                slots[slot][1].start()
                if slots[slot][1].ended:  # a zero step budget
                    finish(slot)
        planning = [episode for _, episode in filter(None, slots) if episode.needs_plan]
        if planning:
            chunks = policy.infer_batch([episode.observation() for episode in planning])
            if len(chunks) != len(planning):
                raise ValueError(f"policy returned {len(chunks)} action chunks for {len(planning)} observations")
            for episode, actions in zip(planning, chunks, strict=True):
                episode.give_plan(actions)
        for slot, occupant in enumerate(slots):
            if occupant is not None:
                occupant[1].step()
                if occupant[1].ended:
                    finish(slot)
    return [records[index] for index in range(len(episodes))]
