"""LIBERO environments as openpi's client builds them, with camera images rendered only when asked for.

`prepare_libero` must run before anything here touches the simulator: importing `libero.libero` without
`$LIBERO_CONFIG_PATH/config.yaml` asks a question on stdin, and hf-libero takes its scene assets from the
module global `libero.libero._assets_path_cache` when set (else it downloads them from the hub).
"""

from __future__ import annotations

import difflib
import functools
import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import yaml

from steering_core.rollout.renderer import choose_renderer

CAMERAS = ("agentview", "robot0_eye_in_hand")  # openpi's two cameras, in its observation order
CONFIG_NAME = "config.yaml"

_prepared = False  # set by prepare_libero: importing libero.libero before it may stop at a stdin question


def default_config_dir() -> Path:
    """Return the folder the LIBERO config is written to by default."""
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").expanduser()
    return cache_home / "latent-steering" / "libero"


def libero_config(benchmark_root: Path) -> dict[str, str]:
    """Return hf-libero's config: every path inside the installed `libero/libero` package (as its defaults)."""
    return {
        "benchmark_root": str(benchmark_root),
        "bddl_files": str(benchmark_root / "bddl_files"),
        "init_states": str(benchmark_root / "init_files"),
        "datasets": str(benchmark_root.parent / "datasets"),
        "assets": str(benchmark_root / "assets"),
    }


def _write_config(config_dir: Path) -> None:
    """Write the config into `config_dir` (sibling temp file, then rename) unless it already holds it."""
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("package `libero` (hf-libero) is not installed; install lerobot[libero]")
    text = yaml.safe_dump(libero_config(Path(spec.submodule_search_locations[0]) / "libero"))
    path = config_dir / CONFIG_NAME
    if path.is_file() and path.read_text() == text:
        return
    config_dir.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{CONFIG_NAME}.{os.getpid()}.tmp")
    temporary.write_text(text)
    temporary.replace(path)


def prepare_libero(assets: Path | None, config_dir: Path | None = None) -> None:
    """Make `libero.libero` importable without questions and point it at `assets` (None: hf-libero downloads).

    Chooses the renderer first (`renderer.choose_renderer`: EGL, on NVIDIA's driver where a GPU is visible). Writes
    the config into `config_dir` (default `default_config_dir()`) and sets LIBERO_CONFIG_PATH, unless
    LIBERO_CONFIG_PATH already holds a config. Pass `assets` verified (`assets.resolve_assets`).
    """
    choose_renderer()  # read when robosuite imports mujoco
    existing = os.environ.get("LIBERO_CONFIG_PATH")
    if "libero.libero" not in sys.modules and not (existing and (Path(existing) / CONFIG_NAME).is_file()):
        config_dir = Path(config_dir) if config_dir is not None else default_config_dir()
        _write_config(config_dir)
        os.environ["LIBERO_CONFIG_PATH"] = str(config_dir)
    import libero.libero

    global _prepared
    libero.libero._assets_path_cache = None if assets is None else str(assets)
    _prepared = True


def _require_prepared() -> None:
    if not _prepared:
        raise RuntimeError("LIBERO is not set up: call prepare_libero(resolve_assets(...)) first")


@functools.cache
def _suite(suite: str):
    """Return the LIBERO benchmark object of a suite (libero_goal, libero_90, ...)."""
    _require_prepared()
    from libero.libero import benchmark

    suites = benchmark.get_benchmark_dict()
    if suite not in suites:
        raise ValueError(f"LIBERO suite {suite!r} is unknown; expected one of {sorted(suites)}")
    return suites[suite]()


def find_task(suite: str, index: int):
    """Return task `index` of a suite: libero's Task (name, language, problem_folder, bddl_file, ...)."""
    tasks = _suite(suite)
    if not 0 <= index < tasks.n_tasks:
        raise ValueError(f"LIBERO suite {suite}: task index {index} out of range, expected 0..{tasks.n_tasks - 1}")
    return tasks.get_task(index)


def task_index(suite: str, language: str) -> int:
    """Return the index of the suite's task whose instruction (or task name) is `language`.

    libero_90 repeats some instructions in several scenes: then pass the task name (`KITCHEN_SCENE10_...`).
    """
    tasks = [find_task(suite, index) for index in range(_suite(suite).n_tasks)]
    matches = [index for index, task in enumerate(tasks) if language in (task.language, task.name)]
    if len(matches) == 1:
        return matches[0]
    if matches:
        named = ", ".join(f"{index} ({tasks[index].name})" for index in matches)
        raise ValueError(f"LIBERO suite {suite}: {language!r} is the instruction of tasks {named}; pass the task name")
    close = difflib.get_close_matches(language, [task.language for task in tasks], n=5, cutoff=0.5)
    hint = f"; close: {close}" if close else ""
    raise ValueError(f"LIBERO suite {suite} has no task {language!r}{hint}")


def bddl_path(task) -> Path:
    """Return the task's BDDL file."""
    _require_prepared()
    from libero.libero import get_libero_path

    return Path(get_libero_path("bddl_files")) / task.problem_folder / task.bddl_file


def initial_states(suite: str, index: int) -> np.ndarray:
    """Return the task's fixed initial states (n, state_dim) float64 (50 per task in the benchmark)."""
    return np.asarray(_suite(suite).get_task_init_states(index))


def make_env(task, resolution: int = 256):
    """Return an OffScreenRenderEnv of the task built as openpi's client does (both cameras, square renders).

    Call `env.seed`, `env.reset()` and `env.set_init_state` per episode; the env is not seeded here.
    """
    from libero.libero.envs import OffScreenRenderEnv

    return OffScreenRenderEnv(bddl_file_name=str(bddl_path(task)), camera_heights=resolution, camera_widths=resolution)


class DeferredCameras:
    """The env's camera observables, rendering only after `arm()`; the other steps cost no render.

    robosuite samples observables inside `env.step`, between physics substeps (here after the 24th of 25), so
    an image cannot be rendered after the step returns. Instead each camera's own sensor is wrapped: armed, it
    runs unchanged (the same arrays as an env rendering every step); unarmed, it returns zeros. A hard reset
    (LIBERO's default) rebuilds the sensors: build a DeferredCameras after every `env.reset()`.
    """

    def __init__(self, env, cameras: tuple[str, ...] = CAMERAS):
        from robosuite.utils.observables import sensor

        self.cameras = cameras
        self.armed = False
        self._rendered: set[str] = set()
        inner = env.env
        for camera in cameras:
            index = inner.camera_names.index(camera)
            blank = np.zeros((inner.camera_heights[index], inner.camera_widths[index], 3), dtype=np.uint8)
            original = inner._observables[f"{camera}_image"]._sensor

            @sensor(modality=original.__modality__)
            def deferred(obs_cache, camera=camera, original=original, blank=blank):
                if not self.armed:
                    return blank
                self._rendered.add(camera)
                return original(obs_cache)

            inner.modify_observable(observable_name=f"{camera}_image", attribute="sensor", modifier=deferred)

    def arm(self) -> None:
        """Render the cameras at the next observation update (the next `env.step` or `set_init_state`)."""
        self.armed = True
        self._rendered.clear()

    def take(self, obs: dict) -> tuple[np.ndarray, ...]:
        """Return the cameras' images (H, W, 3) uint8 from `obs`, rendered since `arm()`, and disarm."""
        missing = [camera for camera in self.cameras if camera not in self._rendered]
        if not self.armed or missing:
            raise RuntimeError(f"camera images {missing or list(self.cameras)} were not rendered: call arm() first")
        self.armed = False
        return tuple(obs[f"{camera}_image"] for camera in self.cameras)
