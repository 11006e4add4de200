"""Which OpenGL driver draws LIBERO's cameras: chosen before MuJoCo is imported, named once it renders.

MuJoCo renders headless through EGL (`MUJOCO_GL=egl`). glvnd's libEGL loads the drivers named by the vendor files
(JSON) in its folders (`VENDOR_DIRS`), or only those listed in `__EGL_VENDOR_LIBRARY_FILENAMES`, and numbers their
devices in that order: NVIDIA's GPUs (10_nvidia.json), then Mesa's (50_mesa.json: GPU render nodes, its software
renderer llvmpipe last). LIBERO renders through robosuite's EGL context (robosuite/renderers/context/
egl_context.py), which initialises one device: number `MUJOCO_EGL_DEVICE_ID`, else the first of
`CUDA_VISIBLE_DEVICES`, else 0 (mujoco's own `mujoco.egl` reads `MUJOCO_EGL_DEVICE_ID` the same way, else takes the
first device that initialises). Naming NVIDIA's vendor file alone makes every device an NVIDIA GPU, so a worker's
`CUDA_VISIBLE_DEVICES` renders on the GPU of that number; `MUJOCO_EGL_DEVICE_ID` is left to the user.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

MUJOCO_GL = "MUJOCO_GL"
VENDOR_FILES = "__EGL_VENDOR_LIBRARY_FILENAMES"  # glvnd loads only these vendor files
VENDOR_FOLDERS = "__EGL_VENDOR_LIBRARY_DIRS"  # glvnd searches these folders instead of VENDOR_DIRS
VENDOR_DIRS = ("etc/glvnd/egl_vendor.d", "usr/share/glvnd/egl_vendor.d")  # glvnd's default folders, under /
NVIDIA_LIBRARY, MESA_LIBRARY = "libEGL_nvidia", "libEGL_mesa"  # the drivers' `library_path` in their vendor files
RENDERERS = ("auto", "gpu", "software")


def vendor_file(library: str, root: Path = Path("/")) -> Path | None:
    """Return the first glvnd EGL vendor file under `root` whose driver is `library` (e.g. libEGL_nvidia.so.0)."""
    for folder in VENDOR_DIRS:
        for path in sorted((root / folder).glob("*.json")):
            try:
                driver = json.loads(path.read_text())["ICD"]["library_path"]
            except (OSError, ValueError, KeyError, TypeError):
                continue  # not a vendor file glvnd could use either
            if Path(driver).name.startswith(library):
                return path
    return None


def nvidia_egl_problem(environ: Mapping[str, str], root: Path = Path("/")) -> str | None:
    """Return why NVIDIA's EGL cannot render here (no vendor file, no GPU, GPUs hidden), or None when it can."""
    if vendor_file(NVIDIA_LIBRARY, root) is None:
        return f"no NVIDIA EGL vendor file ({NVIDIA_LIBRARY}) in {', '.join(f'/{folder}' for folder in VENDOR_DIRS)}"
    nodes = [path for path in (root / "dev").glob("nvidia*") if path.name.removeprefix("nvidia").isdigit()]
    gpus = root / "proc/driver/nvidia/gpus"
    if not nodes and not (gpus.is_dir() and any(gpus.iterdir())):
        return "no NVIDIA GPU visible (no /dev/nvidia<N>, nothing in /proc/driver/nvidia/gpus)"
    visible = environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None and visible.split(",")[0].strip() in ("", "-1"):
        return f"CUDA_VISIBLE_DEVICES={visible!r} hides the GPUs"
    return None


def renderer_environment(environ: Mapping[str, str], renderer: str = "auto", root: Path = Path("/")) -> dict[str, str]:
    """Return the variables to set so that MuJoCo renders with `renderer`, given the process's `environ`.

    auto: EGL (`MUJOCO_GL=egl`) unless MUJOCO_GL is set; on EGL, NVIDIA's vendor file alone when NVIDIA's EGL can
    render (`nvidia_egl_problem`), else glvnd's default; a glvnd variable already set is kept. gpu / software: EGL on
    NVIDIA's / Mesa's vendor file alone, whatever `environ` holds; RuntimeError when that driver is missing.
    """
    if renderer not in RENDERERS:
        raise ValueError(f"renderer {renderer!r}: expected one of {list(RENDERERS)}")
    if renderer == "software":
        mesa = vendor_file(MESA_LIBRARY, root)
        if mesa is None:
            raise RuntimeError(f"software renderer: no Mesa EGL vendor file ({MESA_LIBRARY}) in "
                               f"{', '.join(f'/{folder}' for folder in VENDOR_DIRS)}; install libegl-mesa0")
        return {MUJOCO_GL: "egl", VENDOR_FILES: str(mesa)}
    problem = nvidia_egl_problem(environ, root)
    if renderer == "gpu":
        if problem:
            raise RuntimeError(f"GPU renderer: {problem}")
        return {MUJOCO_GL: "egl", VENDOR_FILES: str(vendor_file(NVIDIA_LIBRARY, root))}
    chosen = {} if environ.get(MUJOCO_GL) else {MUJOCO_GL: "egl"}
    if (environ.get(MUJOCO_GL) or "egl") != "egl" or VENDOR_FILES in environ or VENDOR_FOLDERS in environ:
        return chosen  # the user chose
    if problem is None:
        chosen[VENDOR_FILES] = str(vendor_file(NVIDIA_LIBRARY, root))
    return chosen


def choose_renderer(renderer: str = "auto") -> dict[str, str]:
    """Set `renderer_environment(os.environ, renderer)` in os.environ; return the variables it changed. Call it
    before MuJoCo is imported (EGL reads them when it loads)."""
    chosen = {name: value for name, value in renderer_environment(os.environ, renderer).items()
              if os.environ.get(name) != value}
    if chosen and "OpenGL.EGL" in sys.modules:
        logger.warning("renderer %s chosen after EGL was loaded: %s takes no effect in this process", renderer, chosen)
    os.environ.update(chosen)
    return chosen


@contextlib.contextmanager
def _current_context_kept() -> Iterator[None]:
    """Make the thread's current EGL context current again after the block: robosuite renders with whichever
    context is current and never makes its own current again."""
    if os.environ.get(MUJOCO_GL) != "egl":
        yield
        return
    from mujoco.egl import egl_ext as EGL

    EGL.eglBindAPI(EGL.EGL_OPENGL_API)
    current = (EGL.eglGetCurrentDisplay(), EGL.eglGetCurrentSurface(EGL.EGL_DRAW),
               EGL.eglGetCurrentSurface(EGL.EGL_READ), EGL.eglGetCurrentContext())
    try:
        yield
    finally:
        if current[-1]:
            EGL.eglBindAPI(EGL.EGL_OPENGL_API)  # freeing a context releases the thread, which resets the API
            EGL.eglMakeCurrent(*current)


def _gl_strings() -> str:
    """Return "GL_RENDERER, GL_VENDOR" of the current OpenGL context."""
    from OpenGL import GL

    renderer, vendor = GL.glGetString(GL.GL_RENDERER), GL.glGetString(GL.GL_VENDOR)
    if not renderer:
        return "unknown (no current OpenGL context)"
    return f"{renderer.decode()}, {(vendor or b'?').decode()}"


def gl_renderer(env: Any | None = None) -> str:
    """Return the OpenGL renderer and vendor drawing `env`'s cameras (a `libero_env.make_env` env), or else a fresh
    offscreen context's, made as LIBERO's envs make theirs: "llvmpipe (LLVM 15.0.6, 256 bits), Mesa/X.org" here.

    Never raises: "unknown (<error>)" when it cannot tell. The thread's current context is kept.
    """
    try:
        if env is None:
            choose_renderer()  # a no-op after prepare_libero
        with _current_context_kept():
            if env is not None:
                env.env.sim._render_context_offscreen.gl_ctx.make_current()
                return _gl_strings()
            from robosuite.utils.binding_utils import GLContext  # robosuite's, by MUJOCO_GL (EGL: its device choice)

            context = GLContext(max_width=1, max_height=1, device_id=-1)  # -1: as LIBERO's render_gpu_device_id
            try:
                context.make_current()
                return _gl_strings()
            finally:
                context.free()
    except Exception as error:  # a diagnostic: any failure is reported, not raised
        return f"unknown ({type(error).__name__}: {error})"


@functools.cache
def describe_renderer() -> str:
    """Return the line a simulation process logs once, e.g. "rendering with EGL on llvmpipe (LLVM 15.0.6, 256 bits),
    Mesa/X.org" (queried once per process, on a fresh context: `gl_renderer()`)."""
    renderer = gl_renderer()
    backend = os.environ.get(MUJOCO_GL) or "?"
    return f"rendering with {'EGL' if backend == 'egl' else f'MUJOCO_GL={backend}'} on {renderer}"
