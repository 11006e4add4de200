"""Rollout test helpers: a stand-in for `steering_core.rollout.episode.EpisodeRecord` (same fields) and a
synthetic pair of cells whose toward-task success grows with α, written with the real cell writer."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from steering_core.rollout.records import RolloutCell, TaskRef, write_cell

PAIR = "open_vs_close"
OTHER_PAIR = "on_vs_off"
JOINT = "top_drawer_joint"
DRAWER_GOALS = {JOINT: [("open", -0.14), ("close", 0.0)]}
OPEN = TaskRef("libero_90", 7, "open the top drawer of the cabinet")
CLOSE = TaskRef("libero_90", 0, "close the top drawer of the cabinet")
ALPHAS = (1.0, 2.0, 4.0)
RUN = {"policy": "tiny random pi0.5", "checkpoint_sha256": "ab" * 32, "replan_steps": 5, "max_steps": 40}


@dataclass
class Episode:
    """The fields of `EpisodeRecord` (steering_core.rollout.episode), built by `make_episode`."""

    prompt: str
    init_index: int
    outcome: str
    steps: int
    success_step: int | None
    toward_step: int | None
    joints: dict[str, np.ndarray]
    robot_qpos: np.ndarray
    actions: np.ndarray
    policy_calls: int
    jerk: float
    joint_limit_hits: int
    frames: list[np.ndarray] = field(default_factory=list)


def make_episode(prompt: str, outcome: str, steps: int, init_index: int = 0, *, seed: int = 0, drift: float = 0.0,
                 frames: int = 0) -> Episode:
    """Return an episode of `steps` steps ending in `outcome`; its drawer joint drifts by `drift` per step."""
    rng = np.random.default_rng(seed)
    joint = np.clip(np.cumsum(np.r_[0.0, np.full(steps, drift)]) + rng.normal(0, 0.003, steps + 1), -0.16, 0.01)
    qpos = np.cumsum(rng.normal(0, 0.01, (steps + 1, 7)), axis=0)
    side = np.full((224, 224, 3), 40 * seed % 256, np.uint8)
    return Episode(
        prompt=prompt, init_index=init_index, outcome=outcome, steps=steps,
        success_step=steps if outcome == "instructed" else None, toward_step=steps if outcome == "toward" else None,
        joints={JOINT: joint}, robot_qpos=qpos, actions=rng.normal(0, 0.3, (steps, 7)).astype(np.float32),
        policy_calls=-(-steps // 5), jerk=float(np.sqrt(np.mean(np.diff(qpos, 3, axis=0) ** 2))) if steps > 2
        else float("nan"), joint_limit_hits=int(seed % 3 == 0), frames=[side] * frames)


def toward_count(condition: str, alpha_toward: float, n: int) -> int:
    """Return how many of `n` episodes reach the other task's goal in the synthetic pair's `condition`."""
    if condition == "steered":
        return min(n, int(2 * alpha_toward + 0.5))  # 2, 4, 8 of 10 at α 1, 2, 4
    return {"instruction_swap": n - 1, "unsteered": 0}.get(condition, int(alpha_toward >= 4))  # controls: rare


def write_pair_cells(layer_path: Path, n: int = 10, pair: str = PAIR, frames: int = 2) -> list[dict]:
    """Write every cell of a synthetic pair under `layer_path/pair/`; return their records."""
    records = []
    conditions = [(c, a) for a in ALPHAS for c in ("steered", "random_0", "random_1", "random_2", "random_3",
                                                    f"wrong_concept:{OTHER_PAIR}")]
    conditions += [("instruction_swap", 0.0), ("unsteered", 0.0)]
    for side, own, other in (("positive", OPEN, CLOSE), ("negative", CLOSE, OPEN)):
        for condition, size in conditions:
            cell = RolloutCell(pair, 12, side, condition, size if side == "negative" else -size, own, other)
            k = toward_count(condition, size, n)
            prompt = other.instruction if condition == "instruction_swap" else own.instruction
            episodes = [make_episode(prompt, "toward" if i < k else ("instructed" if i % 4 == 3 else "neither"),
                                     steps=20 + 3 * i, init_index=i, seed=i,
                                     drift=(-1 if other is OPEN else 1) * 0.0015 * size * (condition == "steered"),
                                     frames=frames if i == 0 else 0) for i in range(n)]
            records.append(write_cell(layer_path / pair / cell.name, cell, episodes, seeds=[7] * n, run=RUN))
    return records
