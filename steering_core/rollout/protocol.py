"""openpi's LIBERO client protocol (examples/libero/main.py @15a9616): constants, state and image preprocessing."""

from __future__ import annotations

import math

import numpy as np
from PIL import Image

DUMMY_ACTION = (0.0,) * 6 + (-1.0,)  # wait steps: no motion, gripper open
WAIT_STEPS = 10  # the simulator drops objects at reset: wait before the policy acts
RESIZE = 224
REPLAN_STEPS = 5
ENV_RESOLUTION = 256  # the training data's render size
SEED = 7
# policy steps per episode, wait steps excluded: the longest training demo plus a margin (openpi's numbers;
# lerobot's LIBERO wrapper gives libero_spatial 280, we follow openpi)
MAX_STEPS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520, "libero_90": 400}


def max_steps(suite: str) -> int:
    """Return openpi's step budget of a suite."""
    if suite not in MAX_STEPS:
        raise ValueError(f"no step budget for LIBERO suite {suite!r}; expected one of {sorted(MAX_STEPS)}")
    return MAX_STEPS[suite]


def quat2axisangle(quat: np.ndarray) -> np.ndarray:
    """Return the axis-angle (3,) of a unit quaternion (x, y, z, w), as robosuite's transform_utils computes it.

    w is clipped to [-1, 1]; a rotation whose sin(θ/2) is exactly 0 gives zeros. The input is not modified.
    """
    x, y, z, w = (float(value) for value in quat)
    w = min(max(w, -1.0), 1.0)
    sin_half = math.sqrt(1.0 - w * w)
    if sin_half == 0.0:  # robosuite: math.isclose(den, 0.0), which with default tolerances means == 0
        return np.zeros(3)
    return np.array([x, y, z]) * 2.0 * math.acos(w) / sin_half  # robosuite's order of operations


def resize_with_pad(image: np.ndarray, size: int = RESIZE) -> np.ndarray:
    """Return uint8 (size, size, C): PIL bilinear resize keeping the aspect ratio, centred on zeros.

    openpi_client.image_tools.resize_with_pad for one uint8 (H, W, C) image: ratio max(W, H) / size, new size
    (int(H / ratio), int(W / ratio)), pad floor(diff / 2) top and left. A (size, size) image is returned as is.
    """
    height, width = image.shape[:2]
    if (height, width) == (size, size):
        return image
    ratio = max(width / size, height / size)
    new_height, new_width = int(height / ratio), int(width / ratio)
    resized = np.asarray(Image.fromarray(image).resize((new_width, new_height), resample=Image.BILINEAR))
    out = np.zeros((size, size) + image.shape[2:], dtype=np.uint8)
    top, left = (size - new_height) // 2, (size - new_width) // 2
    out[top : top + new_height, left : left + new_width] = resized
    return out


def preprocess_image(render: np.ndarray, size: int = RESIZE) -> np.ndarray:
    """Return the policy's image (size, size, 3) uint8 from a render: rotated 180 degrees, resized with padding.

    robosuite's renders are upside down (its default "opengl" image convention keeps OpenGL's bottom-up rows);
    the training data (OpenVLA's LIBERO conversion) flipped both axes, so openpi rotates live renders to match.
    """
    return resize_with_pad(np.ascontiguousarray(render[::-1, ::-1]), size)


def robot_state(obs: dict) -> np.ndarray:
    """Return openpi's state (8,) float64: eef position, eef axis-angle, gripper qpos (2)."""
    return np.concatenate((obs["robot0_eef_pos"], quat2axisangle(obs["robot0_eef_quat"]), obs["robot0_gripper_qpos"]))


def policy_observation(images: tuple[np.ndarray, np.ndarray], obs: dict, prompt: str, size: int = RESIZE) -> dict:
    """Return openpi's observation element from the (agentview, wrist) renders and the env's observation dict."""
    agentview, wrist = images
    return {
        "observation/image": preprocess_image(agentview, size),
        "observation/wrist_image": preprocess_image(wrist, size),
        "observation/state": robot_state(obs),
        "prompt": str(prompt),
    }
