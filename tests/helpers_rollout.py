"""Rollout test helpers: a scripted policy, an env that records its actions, and openpi's LIBERO loop written out
independently (rendering every step) to compare `run_episode` against; episodes built directly as `EpisodeRecord`s
and a synthetic pair of cells whose toward-task success grows with α, written with the real cell writer."""

from __future__ import annotations

import collections
import hashlib
import math
from pathlib import Path

import numpy as np
from PIL import Image

from steering_core.rollout.cells import Cell
from steering_core.rollout.episode import EpisodeRecord
from steering_core.rollout.records import CellTasks, TaskRef, write_cell


def reference_resize_with_pad(image: np.ndarray, size: int) -> np.ndarray:
    """PIL bilinear to (int(H / r), int(W / r)), then numpy zero padding with the odd row or column last."""
    height, width = image.shape[:2]
    ratio = max(width / size, height / size)
    new_width, new_height = int(width / ratio), int(height / ratio)
    small = np.array(Image.fromarray(image, "RGB").resize((new_width, new_height), Image.Resampling.BILINEAR))
    rows, cols = size - new_height, size - new_width
    return np.pad(small, ((rows // 2, rows - rows // 2), (cols // 2, cols - cols // 2), (0, 0)))


def reference_axis_angle(quat: np.ndarray) -> np.ndarray:
    """Axis-angle of an (x, y, z, w) unit quaternion via atan2 (another formula than robosuite's)."""
    vector = np.asarray(quat[:3], dtype=np.float64)
    norm = float(np.linalg.norm(vector))
    if norm == 0.0:
        return np.zeros(3)
    return vector / norm * 2.0 * math.atan2(norm, float(quat[3]))


class RecordingEnv:
    """An env proxy that records every action passed to `step` (and passes everything else through)."""

    def __init__(self, env):
        self._env = env
        self.actions: list[list[float]] = []

    def step(self, action):
        self.actions.append(list(action))
        return self._env.step(action)

    def __getattr__(self, name):
        return getattr(self._env, name)


class ScriptedPolicy:
    """Returns fixed (10, 7) float32 chunks in turn; `on_call(call_index)` may change the sim before returning."""

    def __init__(self, env: RecordingEnv, calls: int, seed: int = 0, on_call=None):
        self.env = env
        self.chunks = np.random.default_rng(seed).uniform(-0.6, 0.6, (calls, 10, 7)).astype(np.float32)
        self.on_call = on_call
        self.elements: list[dict] = []
        self.call_steps: list[int] = []  # env steps (wait steps included) taken before each call
        self.events: list[tuple] = []

    def infer(self, observation: dict) -> np.ndarray:
        self.elements.append({key: np.copy(value) for key, value in observation.items()})
        self.call_steps.append(len(self.env.actions))
        if self.on_call is not None:
            self.on_call(len(self.elements) - 1)
        return self.chunks[len(self.elements) - 1]

    def episode_start(self, task: str, episode_id: int) -> None:
        self.events.append(("start", task, episode_id))

    def episode_end(self, success: bool) -> None:
        self.events.append(("end", success))


class ObservationPolicy:
    """Returns (10, 7) float32 chunks drawn from a hash of the observation's state, images and prompt: its actions
    depend on nothing but the observation (row-independent). Records the size of every `infer_batch` call."""

    def __init__(self, salt: int = 0):
        self.salt = salt
        self.batch_sizes: list[int] = []
        self.events: list[tuple] = []

    def infer(self, observation: dict) -> np.ndarray:
        digest = hashlib.sha256(str(self.salt).encode())
        for key in ("observation/state", "observation/image", "observation/wrist_image"):
            digest.update(np.ascontiguousarray(observation[key]).tobytes())
        digest.update(observation["prompt"].encode())
        rng = np.random.default_rng(int.from_bytes(digest.digest()[:8], "little"))
        return rng.uniform(-0.6, 0.6, (10, 7)).astype(np.float32)

    def infer_batch(self, observations: list[dict]) -> list[np.ndarray]:
        self.batch_sizes.append(len(observations))
        return [self.infer(observation) for observation in observations]

    def episode_start(self, task: str, episode_id: int) -> None:
        self.events.append(("start", episode_id))

    def episode_end(self, success: bool) -> None:
        self.events.append(("end", success))


def openpi_loop(env, policy, *, prompt, init_state, max_steps, seed=7, wait=10, replan=5, frames=None):
    """Run openpi's examples/libero/main.py episode loop on an env rendering every step; return (done, steps).

    The env is seeded and reset first, as `run_episode` does per episode. `frames`, a list, receives the policy's
    view of the agentview camera after the wait steps and after every step.
    """
    env.seed(seed)
    env.reset()
    plan = collections.deque()
    obs = env.set_init_state(init_state)
    t, done = 0, False
    while t < max_steps + wait:
        if t < wait:
            obs, _, done, _ = env.step([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0])
            t += 1
            if t == wait and frames is not None:
                frames.append(reference_resize_with_pad(np.rot90(obs["agentview_image"], 2), 224))
            continue
        if not plan:
            element = {
                "observation/image": reference_resize_with_pad(np.rot90(obs["agentview_image"], 2), 224),
                "observation/wrist_image": reference_resize_with_pad(np.rot90(obs["robot0_eye_in_hand_image"], 2), 224),
                "observation/state": np.concatenate(
                    (obs["robot0_eef_pos"], reference_axis_angle(obs["robot0_eef_quat"]), obs["robot0_gripper_qpos"])
                ),
                "prompt": prompt,
            }
            plan.extend(policy.infer(element)[:replan])
        obs, _, done, _ = env.step(plan.popleft().tolist())
        if frames is not None:
            frames.append(reference_resize_with_pad(np.rot90(obs["agentview_image"], 2), 224))
        if done:
            return True, t - wait + 1
        t += 1
    return False, t - wait


PAIR = "open_vs_close"
OTHER_PAIR = "on_vs_off"
JOINT = "top_drawer_joint"
DRAWER_GOALS = {JOINT: [("open", -0.14), ("close", 0.0)]}
OPEN = TaskRef("libero_90", 7, "open the top drawer of the cabinet")
CLOSE = TaskRef("libero_90", 0, "close the top drawer of the cabinet")
ALPHAS = (1.0, 2.0, 4.0)
RUN = {"policy": "tiny random pi0.5", "checkpoint_sha256": "ab" * 32, "replan_steps": 5, "max_steps": 40}


def make_episode(prompt: str, outcome: str, steps: int, init_index: int = 0, *, seed: int = 0, drift: float = 0.0,
                 frames: int = 0) -> EpisodeRecord:
    """Return an episode of `steps` steps ending in `outcome`; its drawer joint drifts by `drift` per step."""
    rng = np.random.default_rng(seed)
    joint = np.clip(np.cumsum(np.r_[0.0, np.full(steps, drift)]) + rng.normal(0, 0.003, steps + 1), -0.16, 0.01)
    qpos = np.cumsum(rng.normal(0, 0.01, (steps + 1, 7)), axis=0)
    side = np.full((224, 224, 3), 40 * seed % 256, np.uint8)
    return EpisodeRecord(
        prompt=prompt, init_index=init_index, outcome=outcome, steps=steps,
        success_step=steps if outcome == "instructed" else None, toward_step=steps if outcome == "toward" else None,
        joints={JOINT: joint}, robot_qpos=qpos, actions=rng.normal(0, 0.3, (steps, 7)).astype(np.float32),
        policy_calls=-(-steps // 5), jerk=float(np.sqrt(np.mean(np.diff(qpos, 3, axis=0) ** 2))) if steps > 2
        else float("nan"), joint_limit_hits=int(seed % 3 == 0), frames=[side] * frames)


def toward_count(condition: str, alpha_toward: float, n: int) -> int:
    """Return how many of `n` episodes reach the other task's goal in the synthetic pair's `condition`."""
    if condition == "sae":
        return min(n, int(2 * alpha_toward + 0.5))  # 2, 4, 8 of 10 at α 1, 2, 4
    return {"instruction_swap": n - 1, "unsteered": 0}.get(condition, int(alpha_toward >= 4))  # controls: rare


def write_pair_cells(layer_path: Path, n: int = 10, pair: str = PAIR, frames: int = 2) -> list[dict]:
    """Write every cell of a synthetic pair under `layer_path/pair/`; return their records."""
    records = []
    conditions = [(c, a) for a in ALPHAS for c in ("sae", "random_0", "random_1", "random_2", "random_3",
                                                    f"wrong_concept:{OTHER_PAIR}/sae")]
    conditions += [("instruction_swap", 0.0), ("unsteered", 0.0)]
    for side, own, other in (("positive", OPEN, CLOSE), ("negative", CLOSE, OPEN)):
        for condition, size in conditions:
            cell = Cell.pushed(pair, 12, side, condition, size)
            k = toward_count(condition, size, n)
            prompt = other.instruction if condition == "instruction_swap" else own.instruction
            episodes = [make_episode(prompt, "toward" if i < k else ("instructed" if i % 4 == 3 else "neither"),
                                     steps=20 + 3 * i, init_index=i, seed=i,
                                     drift=(-1 if other is OPEN else 1) * 0.0015 * size * (condition == "sae"),
                                     frames=frames if i == 0 else 0) for i in range(n)]
            records.append(write_cell(layer_path / pair / cell.name, cell, CellTasks(own, other), episodes, seeds=[7] * n, run=RUN))
    return records
