"""The GPU check's render section: LIBERO's simulator steps/s with both 256 px cameras rendered every step, MuJoCo's
EGL on the GPU (NVIDIA's driver) against the software renderer (Mesa's llvmpipe), the same episode (see
`bench.gpu_check`).

The episode and its timing are `bench.rollout_throughput`'s part 1 (libero_goal "turn on the stove", initial state
0, the dummy action; blocks with `DeferredCameras` armed before each step against blocks without rendering). Each
renderer runs in its own process, as a rollout worker does (one thread for llvmpipe, OpenMP and MKL), since the GL
driver is fixed when MuJoCo is imported. The software process hides CUDA's GPUs (robosuite would take them for EGL
device numbers) and picks Mesa's software device, which Mesa numbers after any GPU render node. Both processes
render the two cameras at the initial state once more, and the images are compared: a renderer drawing black or
another scene shows there.

    python -m bench.gpu_render_section gpu|software --cache-dir DIR --settings JSON   (one renderer's process)
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench.common import print_child_result, run_child
from bench.rollout_throughput import THREAD_VARIABLES
from steering_core.rollout.renderer import nvidia_egl_problem

if TYPE_CHECKING:  # the harness imports the policy stack (6 s), which a renderer's process does without
    from bench.gpu_harness import Context, Section

LABELS = {"gpu": "EGL on the GPU", "software": "EGL in software"}


def render(ctx: Context) -> Section:
    """Simulator steps/s with both cameras rendered every step: EGL on the GPU against the software renderer."""
    from bench.gpu_harness import Section

    section = Section()
    runs: dict[str, dict[str, Any]] = {}
    for renderer, label in LABELS.items():
        problem = nvidia_egl_problem(os.environ) if renderer == "gpu" else None
        if problem is None:
            argv = [renderer, f"--cache-dir={ctx.folder}", f"--settings={json.dumps(ctx.sizes.render)}"]
            try:
                runs[renderer] = run_child("gpu_render_section", argv, env=dict.fromkeys(THREAD_VARIABLES, "1"))
            except RuntimeError as error:
                problem = f"its process failed: {str(error).strip().splitlines()[-1]}"
        if problem is not None:
            section.notes.append(f"render: {label} not measured: {problem}.")
            continue
        run = runs[renderer]
        section.measure(f"sim steps/s, both 256 px cameras every step, {label}: {run['renderer']}", run["render"],
                        f"no render {run['plain']:.1f} steps/s", run["render"] / run["plain"])
    if len(runs) == 2:
        gpu, software = runs["gpu"], runs["software"]
        section.measure("sim steps/s with both cameras, EGL on the GPU vs software", gpu["render"],
                        f"software {software['render']:.2f} steps/s", gpu["render"] / software["render"])
        frames = [np.load(run["frames"]).astype(np.float32) for run in (gpu, software)]
        section.measure("both cameras at the initial state, GPU vs software: mean |difference| (levels of 255)",
                        float(np.abs(frames[0] - frames[1]).mean()), f"mean level {frames[1].mean():.1f}")
    settings = ctx.sizes.render
    section.notes.append(f"render: best of {settings['rounds']} x {settings['render_steps']} rendered and "
                         f"{settings['plain_steps']} plain steps per renderer, each in its own one-thread process.")
    return section


def measure(renderer: str, folder: Path, settings: dict[str, int]) -> dict[str, Any]:
    """Return steps/s without and with both cameras rendered every step (best of the rounds), the renderer's name
    and the file of both cameras' images at the initial state (2, 256, 256, 3) uint8, measured in this process on
    `renderer`."""
    from bench.rollout_throughput import RESOLUTION, open_env, step_rates
    from steering_core.rollout.libero_env import CAMERAS
    from steering_core.rollout.renderer import choose_renderer, gl_renderer

    choose_renderer(renderer)
    if renderer == "software":
        os.environ.pop("CUDA_VISIBLE_DEVICES", None)
        from mujoco.egl import egl_ext

        os.environ["MUJOCO_EGL_DEVICE_ID"] = str(len(egl_ext.eglQueryDevicesEXT()) - 1)  # Mesa's software device
    env, init_state = open_env(folder)
    rates = step_rates(env, init_state, settings)
    env.set_init_state(init_state)
    frames = folder / f"render-{renderer}.npy"
    np.save(frames, np.stack([env.env.sim.render(camera_name=camera, width=RESOLUTION, height=RESOLUTION)
                              for camera in CAMERAS]))  # as robosuite's camera sensors render
    name = gl_renderer(env)
    env.close()
    return {"renderer": name, "plain": max(rates["no render"]), "render": max(rates["both cameras every step"]),
            "frames": str(frames)}


def main(argv: list[str] | None = None) -> None:
    """Measure one renderer in this process; print the result as the JSON line `run_child` reads."""
    arguments = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    arguments.add_argument("renderer", choices=list(LABELS))
    arguments.add_argument("--cache-dir", type=Path, required=True)
    arguments.add_argument("--settings", type=json.loads, required=True)
    args = arguments.parse_args(argv)
    args.cache_dir.mkdir(parents=True, exist_ok=True)
    print_child_result(measure(args.renderer, args.cache_dir, args.settings))


if __name__ == "__main__":
    main()
