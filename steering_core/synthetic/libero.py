"""Synthetic LIBERO demo files in the exact released hdf5 schema, with known right answers.

Each task moves one axis of the openpi 8-D state (ee_pos 0..2, ee_ori 3..5) in a chosen
direction, by a chosen distance, inside a chosen window of the episode; everything else
stays still apart from a small shared "approach" motion and seeded noise. Later steps
(contrast manifests, concept maps, steering) are tested against these answers.

Images are rendered upright (bright "wall" on top, dark "table" below, a marker following
the end effector) and stored rotated by 180 degrees, like LIBERO's raw OpenGL renders, so a
correct `rotate180` conversion gives upright frames again.
"""

from __future__ import annotations

import json
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import h5py
import numpy as np
from pydantic import Field, model_validator

from steering_core.data.libero import DATA_GROUP, DEMO_KEY, LiberoDemo, task_file_name
from steering_core.storage.fileio import atomic_path
from steering_core.storage.schema import StrictModel

STATE_AXES = ("ee_x", "ee_y", "ee_z", "ee_rx", "ee_ry", "ee_rz", "gripper_left", "gripper_right")
CONTROL_HZ = 20                 # LIBERO's control frequency
POS_ACTION_SCALE = 0.05         # metres per unit action (robosuite OSC_POSE output_max)
ORI_ACTION_SCALE = 0.5          # radians per unit action (robosuite OSC_POSE output_max)
GRIPPER_OPEN, GRIPPER_CLOSED = 0.039, 0.010  # Panda finger qpos (metres)
APPROACH_AXIS, APPROACH_DISTANCE = 0, 0.04   # every task first reaches forward 4 cm (same sign everywhere)
HOME_EE_POS = np.array([-0.10, 0.00, 1.00])  # a typical Panda start above a LIBERO table
HOME_EE_ORI = np.array([3.14, 0.00, 0.00])   # gripper pointing down (axis-angle)
HOME_JOINTS = np.array([0.0, -0.16, 0.0, -2.44, 0.0, 2.23, 0.79])
ENV_NAME = "Libero_Kitchen_Tabletop_Manipulation"
PROBLEM_NAME = "libero_kitchen_tabletop_manipulation"


class MotionSpec(StrictModel):
    """Which state axis a task moves, which way, how far and when."""

    axis: int = Field(ge=0, le=5)                 # index into the 8-D state; grippers follow the grasp
    direction: Literal[1, -1]
    distance: float = Field(default=0.12, gt=0)   # metres (axes 0..2) or radians (3..5) over the window
    window: tuple[float, float] = (0.35, 0.75)    # start/end as fractions of the episode
    window_jitter: float = Field(default=0.04, ge=0, le=0.2)  # per-demo shift of the window, fraction

    @model_validator(mode="after")
    def _window_inside_episode(self) -> MotionSpec:
        start, end = self.window
        if not 0.0 <= start - self.window_jitter < end + self.window_jitter <= 1.0:
            raise ValueError(
                f"window {self.window} with jitter {self.window_jitter} must lie inside [0, 1], start < end"
            )
        return self


class SyntheticTask(StrictModel):
    """One LIBERO task file to generate."""

    instruction: str
    scene: str = "KITCHEN_SCENE1"  # file name prefix, as in LIBERO-90
    motion: MotionSpec

    @property
    def file_name(self) -> str:
        """Return the LIBERO file name, e.g. `KITCHEN_SCENE3_turn_on_the_stove_demo.hdf5`."""
        return task_file_name(self.instruction, self.scene)


class SyntheticSettings(StrictModel):
    """Sizes and randomness of generated demos (real values as defaults)."""

    image_size: int = Field(default=128, ge=8, le=512)    # LIBERO renders 128x128; tests pass 16 or 32
    num_steps: int = Field(default=120, ge=8, le=5000)    # real demos are 100-300 steps; tests pass ~12
    length_jitter: int = Field(default=0, ge=0)    # demos get num_steps + [0, length_jitter] steps
    noise_std: float = Field(default=5e-4, ge=0)   # per-step noise on ee axes, well below any motion
    state_dim: int = Field(default=48, ge=11)      # flattened MuJoCo state width (scene-dependent)
    seed: int = 0


@dataclass(frozen=True)
class DemoTruth:
    """The known right answer for one generated demo."""

    file: str
    demo: str
    instruction: str
    axis: int
    direction: int
    start_step: int       # first step of the motion window
    end_step: int         # last step of the motion window (inclusive)
    axis_delta: float     # state[axis] at the last step minus at the first step
    num_steps: int


@dataclass(frozen=True)
class SyntheticFile:
    """A written file and the answers for its demos (in demo order)."""

    path: Path
    instruction: str
    demos: tuple[DemoTruth, ...]


# The demo suite: two concept pairs with distinct axes, real LIBERO-90 scene names.
DRAWER_OPEN = "open the top drawer of the cabinet"
DRAWER_CLOSE = "close the top drawer of the cabinet"
STOVE_ON = "turn on the stove"
STOVE_OFF = "turn off the stove"
DEMO_SUITE_TASKS: tuple[SyntheticTask, ...] = (
    SyntheticTask(instruction=DRAWER_OPEN, scene="KITCHEN_SCENE1", motion=MotionSpec(axis=2, direction=1)),
    SyntheticTask(instruction=DRAWER_CLOSE, scene="KITCHEN_SCENE10", motion=MotionSpec(axis=2, direction=-1)),
    SyntheticTask(instruction=STOVE_ON, scene="KITCHEN_SCENE3", motion=MotionSpec(axis=5, direction=1, distance=0.6)),
    SyntheticTask(instruction=STOVE_OFF, scene="KITCHEN_SCENE8", motion=MotionSpec(axis=5, direction=-1, distance=0.6)),
)


def make_demo(task: SyntheticTask, demo_index: int, settings: SyntheticSettings) -> tuple[LiberoDemo, DemoTruth]:
    """Return one deterministic demo (arrays in LIBERO dtypes) and its known answer."""
    rng = np.random.default_rng([settings.seed, zlib.crc32(task.instruction.encode()), demo_index])
    steps = settings.num_steps + int(rng.integers(0, settings.length_jitter + 1))
    motion = task.motion
    shift = rng.uniform(-motion.window_jitter, motion.window_jitter)
    start = round((motion.window[0] + shift) * (steps - 1))
    end = max(start + 1, round((motion.window[1] + shift) * (steps - 1)))

    t = np.arange(steps)
    pose = np.tile(np.concatenate([HOME_EE_POS, HOME_EE_ORI]), (steps, 1))
    pose[:, :3] += rng.uniform(-0.02, 0.02, size=3)  # each demo starts from a slightly different place
    approach_end = max(1, start // 2)
    pose[:, APPROACH_AXIS] += APPROACH_DISTANCE * _ramp(t, 0, approach_end)
    progress = _ramp(t, start, end)
    pose[:, motion.axis] += motion.direction * motion.distance * progress
    pose += rng.normal(0.0, settings.noise_std, size=pose.shape)
    ee_pos, ee_ori = pose[:, :3], pose[:, 3:]

    grasp = ((t >= start) & (t <= end)).astype(np.float64)  # fingers close on the handle/knob
    finger = GRIPPER_OPEN + (GRIPPER_CLOSED - GRIPPER_OPEN) * grasp
    gripper_states = np.stack([finger, -finger], axis=1)
    joint_states = HOME_JOINTS + 0.5 * np.tanh(pose @ _JOINT_MIX)  # smooth stand-in for inverse kinematics

    actions = np.zeros((steps, 7))
    actions[:-1, :3] = np.diff(ee_pos, axis=0) / POS_ACTION_SCALE
    actions[:-1, 3:6] = np.diff(ee_ori, axis=0) / ORI_ACTION_SCALE
    actions[:, :6] = np.clip(actions[:, :6], -1.0, 1.0)
    actions[:, 6] = np.where(grasp > 0, 1.0, -1.0)  # LIBERO: -1 open, +1 close

    states = np.zeros((steps, settings.state_dim))
    states[:, 0] = t / CONTROL_HZ
    states[:, 1:8] = joint_states
    states[:, 8:10] = gripper_states
    states[:, 10] = progress  # the articulated object's joint (drawer slide, knob angle)
    robot_states = np.concatenate([gripper_states, ee_pos, _axis_angle_to_quat_xyzw(ee_ori)], axis=1)
    last = np.zeros(steps, dtype=np.uint8)
    last[-1] = 1

    size, tint = settings.image_size, zlib.crc32(task.scene.encode()) % 64
    demo = LiberoDemo(
        key=DEMO_KEY.format(index=demo_index),
        agentview_rgb=_render_agentview(ee_pos, size, tint),
        eye_in_hand_rgb=_render_wrist(finger, t, size, tint),
        ee_pos=ee_pos,
        ee_ori=ee_ori,
        ee_states=np.concatenate([ee_pos, ee_ori], axis=1),
        gripper_states=gripper_states,
        joint_states=joint_states,
        actions=actions,
        states=states,
        robot_states=robot_states,
        rewards=last.copy(),
        dones=last,
    )
    state8 = demo.state8()
    truth = DemoTruth(
        file=task.file_name,
        demo=demo.key,
        instruction=task.instruction,
        axis=motion.axis,
        direction=motion.direction,
        start_step=start,
        end_step=end,
        axis_delta=float(state8[-1, motion.axis] - state8[0, motion.axis]),
        num_steps=steps,
    )
    return demo, truth


def write_libero_file(
    folder: str | Path,
    task: SyntheticTask,
    *,
    num_demos: int = 50,
    settings: SyntheticSettings = SyntheticSettings(),
    demo_indices: Sequence[int] | None = None,
) -> SyntheticFile:
    """Write one task file in the LIBERO schema; return its path and per-demo answers.

    `demo_indices` picks the demo keys (default 0..num_demos-1), so tests can make gaps.
    """
    indices = list(range(num_demos)) if demo_indices is None else list(demo_indices)
    if not indices:
        raise ValueError("write_libero_file: no demos requested; pass num_demos >= 1")
    path = Path(folder) / task.file_name
    made = [make_demo(task, index, settings) for index in indices]
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as handle:
        data = handle.create_group(DATA_GROUP)
        _write_file_attrs(data, task, settings, num_demos=len(made), total=sum(d.num_steps for d, _ in made))
        for demo, _ in made:
            _write_demo(data, demo)
    return SyntheticFile(path=path, instruction=task.instruction, demos=tuple(truth for _, truth in made))


MAX_FILE_BYTES = 2 << 30  # one task file's demos, built in memory before the file is written
CAMERAS = 2               # agentview and eye-in-hand, uint8 RGB
STEP_FLOATS = 36          # float64 values per step besides the MuJoCo state: actions, ee pose, grippers, joints, ...


def check_demo_request(demos_per_task: int, settings: SyntheticSettings, where: str = "make-demos") -> None:
    """Raise before anything is made when one task file's demos (built in memory before they are written) would
    exceed `MAX_FILE_BYTES`, stating the estimate, the product it came from and the counts to lower."""
    steps = settings.num_steps + settings.length_jitter
    step_bytes = CAMERAS * settings.image_size**2 * 3 + (settings.state_dim + STEP_FLOATS) * 8
    estimate = demos_per_task * steps * step_bytes
    if estimate > MAX_FILE_BYTES:
        raise ValueError(f"{where}: an estimated {estimate / 2**30:,.1f} GiB per task file = demos_per_task "
                         f"{demos_per_task:,} x up to {steps} steps x {step_bytes:,} bytes ({CAMERAS} cameras of "
                         f"{settings.image_size}x{settings.image_size} RGB and the state); expected at most "
                         f"{MAX_FILE_BYTES >> 30} GiB: lower --demos-per-task, --num-steps or --image-size")


def write_demo_suite(
    folder: str | Path,
    *,
    demos_per_task: int = 4,
    settings: SyntheticSettings = SyntheticSettings(),
    tasks: Sequence[SyntheticTask] = DEMO_SUITE_TASKS,
) -> list[SyntheticFile]:
    """Write the two-pair demo suite (drawer open/close, stove on/off) into `folder`; return the files
    (`check_demo_request` first)."""
    check_demo_request(demos_per_task, settings)
    Path(folder).mkdir(parents=True, exist_ok=True)
    return [write_libero_file(folder, task, num_demos=demos_per_task, settings=settings) for task in tasks]


# ----------------------------------------------------------------------------- internals

_JOINT_MIX = np.linspace(-1.0, 1.0, 6 * 7).reshape(6, 7) * 0.3  # fixed pose -> joint coupling


def _ramp(t: np.ndarray, start: int, end: int) -> np.ndarray:
    """Return a smoothstep from 0 (t <= start) to 1 (t >= end), float64 (T,)."""
    u = np.clip((t - start) / max(end - start, 1), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _axis_angle_to_quat_xyzw(axis_angle: np.ndarray) -> np.ndarray:
    """Return unit quaternions (T, 4) in robosuite's (x, y, z, w) order from axis-angle vectors (T, 3)."""
    angle = np.linalg.norm(axis_angle, axis=1, keepdims=True)
    axis = axis_angle / np.maximum(angle, 1e-12)
    return np.concatenate([axis * np.sin(angle / 2), np.cos(angle / 2)], axis=1)


def _rotate180(frames: np.ndarray) -> np.ndarray:
    """Return (T, H, W, 3) frames flipped along H and W: how LIBERO's raw renders are stored."""
    return np.ascontiguousarray(frames[:, ::-1, ::-1])


def _render_agentview(ee_pos: np.ndarray, size: int, tint: int) -> np.ndarray:
    """Return (T, size, size, 3) uint8: wall above, table below, a marker at the end effector."""
    steps = ee_pos.shape[0]
    rows = np.arange(size)[:, None] / size
    cols = np.arange(size)[None, :] / size
    scene = np.empty((size, size, 3))
    upper = rows < 0.45
    scene[..., 0] = np.where(upper, 200 - 60 * rows, 70 + 40 * cols)
    scene[..., 1] = np.where(upper, 190 - 30 * cols, 50 + 30 * rows)
    scene[..., 2] = 120 + tint
    frames = np.broadcast_to(scene, (steps, size, size, 3)).copy()
    # marker centre follows ee x (image column) and ee z (image row: higher hand, higher marker)
    centre_col = np.clip(0.5 + 2.0 * (ee_pos[:, 0] - HOME_EE_POS[0]), 0.1, 0.9) * size
    centre_row = np.clip(0.6 - 2.0 * (ee_pos[:, 2] - HOME_EE_POS[2]), 0.1, 0.9) * size
    radius = max(1.0, size / 12)
    yy, xx = np.mgrid[0:size, 0:size]
    marker = (np.abs(yy[None] - centre_row[:, None, None]) <= radius) & (
        np.abs(xx[None] - centre_col[:, None, None]) <= radius
    )
    frames[marker] = (250.0, 40.0, 40.0)
    return _rotate180(np.clip(np.rint(frames), 0, 255).astype(np.uint8))


def _render_wrist(finger: np.ndarray, t: np.ndarray, size: int, tint: int) -> np.ndarray:
    """Return (T, size, size, 3) uint8: drifting stripes, fingers as dark bands that close in."""
    cols = np.arange(size)[None, None, :]
    rows = np.arange(size)[None, :, None]
    phase = (t[:, None, None] * 3 + cols + rows // 2) % 16
    frames = np.empty((t.shape[0], size, size, 3))
    frames[..., 0] = 90 + 8 * phase
    frames[..., 1] = 60 + tint + 2 * rows
    frames[..., 2] = 150 - 4 * phase
    band = (size * 0.45 * finger / GRIPPER_OPEN)[:, None, None]  # wider gap = more open
    fingers = (np.abs(cols - size / 2) >= band) & (rows >= size * 0.7)
    frames[np.broadcast_to(fingers, frames.shape[:3])] = 20.0
    return _rotate180(np.clip(np.rint(frames), 0, 255).astype(np.uint8))


def _bddl_text(task: SyntheticTask) -> str:
    """Return a small BDDL problem carrying the task's `(:language ...)` line."""
    return (
        "(define (problem LIBERO_Kitchen_Tabletop_Manipulation)\n"
        "  (:domain robosuite)\n"
        f"  (:language {task.instruction})\n"
        "  (:fixtures\n    kitchen_table - kitchen_table\n  )\n"
        "  (:goal\n    (And)\n  )\n"
        ")\n"
    )


def _write_file_attrs(
    data: h5py.Group, task: SyntheticTask, settings: SyntheticSettings, *, num_demos: int, total: int
) -> None:
    bddl_file = f"libero/libero/bddl_files/libero_90/{task.file_name.removesuffix('_demo.hdf5')}.bddl"
    env_kwargs = {
        "robots": ["Panda"],
        "controller_configs": {"type": "OSC_POSE"},
        "bddl_file_name": bddl_file,
        "has_renderer": False,
        "has_offscreen_renderer": True,
        "ignore_done": True,
        "use_camera_obs": True,
        "camera_depths": False,
        "camera_names": ["robot0_eye_in_hand", "agentview"],
        "reward_shaping": True,
        "control_freq": CONTROL_HZ,
        "camera_heights": settings.image_size,
        "camera_widths": settings.image_size,
        "camera_segmentations": None,
    }
    data.attrs["env_name"] = ENV_NAME
    data.attrs["problem_info"] = json.dumps(
        {"problem_name": PROBLEM_NAME, "domain_name": "robosuite", "language_instruction": task.instruction}
    )
    data.attrs["macros_image_convention"] = "opengl"  # why raw frames are upside down
    data.attrs["bddl_file_name"] = bddl_file
    data.attrs["bddl_file_content"] = _bddl_text(task)
    data.attrs["env_args"] = json.dumps(
        {
            "type": 1,
            "env_name": ENV_NAME,
            "problem_name": PROBLEM_NAME,
            "bddl_file": bddl_file,
            "env_kwargs": env_kwargs,
        }
    )
    data.attrs["num_demos"] = num_demos
    data.attrs["total"] = total


def _write_demo(data: h5py.Group, demo: LiberoDemo) -> None:
    group = data.create_group(demo.key)
    obs = group.create_group("obs")
    for name in ("agentview_rgb", "eye_in_hand_rgb"):
        obs.create_dataset(name, data=getattr(demo, name))
    for name in ("ee_pos", "ee_ori", "ee_states", "gripper_states", "joint_states"):
        obs.create_dataset(name, data=getattr(demo, name).astype(np.float64))
    for name in ("actions", "states", "robot_states"):
        group.create_dataset(name, data=getattr(demo, name).astype(np.float64))
    group.create_dataset("rewards", data=demo.rewards.astype(np.uint8))
    group.create_dataset("dones", data=demo.dones.astype(np.uint8))
    group.attrs["num_samples"] = demo.num_steps
    group.attrs["model_file"] = '<mujoco model="synthetic_libero"><worldbody/></mujoco>'
    group.attrs["init_state"] = demo.states[0]
