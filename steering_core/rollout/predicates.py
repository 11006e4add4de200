"""A LIBERO task's goal (its BDDL goal predicates) evaluated on any env whose scene holds the objects it names.

A goal is a conjunction of predicates such as ("open", "wooden_cabinet_1_top_region") or ("on", "plate_1",
"main_table_stove_front_region"), evaluated by the env's own `_eval_predicate` (libero's predicate functions),
so a goal gives the same answer as the env's `done` would in its own task.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from steering_core.rollout.libero_env import bddl_path

JOINT_PREDICATES = ("open", "close", "turnon", "turnoff")  # unary predicates that read articulated joints


class GoalError(ValueError):
    """A goal that cannot be evaluated on an env."""


@dataclass(frozen=True)
class Goal:
    """A task's instruction and goal predicates; `source` names the BDDL file (for messages)."""

    instruction: str
    predicates: tuple[tuple[str, ...], ...]
    source: str

    @classmethod
    def from_bddl(cls, path: Path, instruction: str) -> Goal:
        """Return the goal parsed from a BDDL file with libero's parser."""
        from libero.libero.envs.bddl_utils import robosuite_parse_problem

        problem = robosuite_parse_problem(str(path))
        predicates = tuple(tuple(str(term) for term in predicate) for predicate in problem["goal_state"])
        return cls(instruction, predicates, Path(path).name)

    @classmethod
    def of_env(cls, env) -> Goal:
        """Return the goal of the env's own task (the one its `done` tests), with the BDDL's instruction."""
        predicates = tuple(tuple(str(term) for term in predicate) for predicate in env.env.parsed_problem["goal_state"])
        return cls(env.language_instruction, predicates, Path(env.env.bddl_file_name).name)

    @classmethod
    def from_task(cls, task) -> Goal:
        """Return a libero Task's goal, with the task's instruction (`task.language`, which openpi prompts)."""
        return cls.from_bddl(bddl_path(task), task.language)

    def objects(self) -> list[str]:
        """Return the object, fixture and region names the predicates test, in order, without repeats."""
        return list(dict.fromkeys(name for predicate in self.predicates for name in predicate[1:]))

    def check(self, env) -> None:
        """Raise GoalError unless the env's scene has every object the goal names."""
        states = env.env.object_states_dict
        missing = [name for name in self.objects() if name not in states]
        if missing:
            raise GoalError(
                f"goal {self.instruction!r} ({self.source}) names {missing}, absent from the env's scene "
                f"({env.env.__class__.__name__}); expected a scene with these objects"
            )

    def holds(self, env) -> bool:
        """Return whether every predicate holds at the env's current state (call `check` once before)."""
        return all(env.env._eval_predicate(list(predicate)) for predicate in self.predicates)


def goal_joints(goal: Goal, env) -> dict[str, int]:
    """Return joint name -> qpos address of the articulated joints the goal's unary predicates test.

    Drawers are regions (sites) of a cabinet, the stove is an object: both carry the joints libero reads.
    """
    goal.check(env)
    inner = env.env
    joints: dict[str, int] = {}
    for predicate in goal.predicates:
        if predicate[0] not in JOINT_PREDICATES:
            continue
        name = predicate[1]
        holder = inner.object_sites_dict[name] if name in inner.object_sites_dict else inner.get_object(name)
        for joint in holder.joints or ():
            joints[joint] = int(inner.sim.model.get_joint_qpos_addr(joint))  # hinge / slide: one address
    return joints


def read_joints(env, joints: dict[str, int]) -> dict[str, float]:
    """Return joint name -> qpos now for the joints of `goal_joints`."""
    qpos = env.env.sim.data.qpos
    return {name: float(qpos[address]) for name, address in joints.items()}


def goal_thresholds(goals: list[Goal], env, points: int = 401) -> dict[str, list[tuple[str, float]]]:
    """Return joint name -> (predicate, qpos) where each joint predicate of `goals` changes truth along the joint's
    range: found by sweeping the range in `points` steps with libero's own predicate (to ±range/(points - 1)), the
    other joints where they are. The sim's state is restored after."""
    inner = env.env
    sim, saved = inner.sim, inner.sim.get_state()
    found: dict[str, list[tuple[str, float]]] = {}
    try:
        for goal in goals:
            for predicate in goal.predicates:
                if predicate[0] not in JOINT_PREDICATES:
                    continue
                for name, address in goal_joints(Goal(goal.instruction, (predicate,), goal.source), env).items():
                    grid = np.linspace(*sim.model.jnt_range[sim.model.joint_name2id(name)], points)
                    truth = []
                    for value in grid:
                        sim.data.qpos[address] = value
                        sim.forward()
                        truth.append(bool(inner._eval_predicate(list(predicate))))
                    found.setdefault(name, []).extend(
                        (predicate[0], float((grid[i] + grid[i + 1]) / 2))
                        for i in range(points - 1) if truth[i] != truth[i + 1])
    finally:
        sim.set_state(saved)
        sim.forward()
    return found
