"""Rollout test helpers: a scripted policy, an env that records its actions, and openpi's LIBERO loop written
out independently (rendering every step) to compare `run_episode` against."""

from __future__ import annotations

import collections
import math

import numpy as np
from PIL import Image


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


def openpi_loop(env, policy, *, prompt, init_state, max_steps, seed=7, wait=10, replan=5):
    """Run openpi's examples/libero/main.py episode loop on an env rendering every step; return (done, steps).

    The env is seeded and reset first, as `run_episode` does per episode.
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
        if done:
            return True, t - wait + 1
        t += 1
    return False, t - wait
