"""The renderer choice on fake machines (vendor files and NVIDIA devices under tmp_path), and the renderer this
machine really draws with, in fresh processes (Mesa's llvmpipe on the CPU test machine)."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from steering_core.rollout.renderer import (
    MESA_LIBRARY,
    MUJOCO_GL,
    NVIDIA_LIBRARY,
    VENDOR_FILES,
    VENDOR_FOLDERS,
    choose_renderer,
    gl_renderer,
    nvidia_egl_problem,
    renderer_environment,
    vendor_file,
)

REPO_ROOT = Path(__file__).resolve().parent.parent
GL_VARIABLES = (MUJOCO_GL, VENDOR_FILES, VENDOR_FOLDERS, "MUJOCO_EGL_DEVICE_ID", "PYOPENGL_PLATFORM")


def make_machine(root: Path, vendors: tuple[str, ...] = ("nvidia", "mesa"), gpu: str | None = "dev") -> Path:
    """Return `root` laid out as a machine: glvnd vendor files (10_nvidia.json, 50_mesa.json) in /usr/share, and an
    NVIDIA GPU as a device node (`gpu="dev"`), as a /proc/driver/nvidia/gpus entry (`"proc"`), or none."""
    folder = root / "usr/share/glvnd/egl_vendor.d"
    folder.mkdir(parents=True)
    for vendor in vendors:
        number, library = (10, NVIDIA_LIBRARY) if vendor == "nvidia" else (50, MESA_LIBRARY)
        vendor_json = {"file_format_version": "1.0.0", "ICD": {"library_path": f"{library}.so.0"}}
        (folder / f"{number}_{vendor}.json").write_text(json.dumps(vendor_json))
    (root / "dev").mkdir()
    if gpu == "dev":
        for name in ("nvidiactl", "nvidia-uvm", "nvidia0"):
            (root / "dev" / name).touch()
    elif gpu == "proc":
        (root / "proc/driver/nvidia/gpus/0000:01:00.0").mkdir(parents=True)
    return root


def nvidia(root: Path) -> str:
    return str(root / "usr/share/glvnd/egl_vendor.d/10_nvidia.json")


def mesa(root: Path) -> str:
    return str(root / "usr/share/glvnd/egl_vendor.d/50_mesa.json")


# ----------------------------------------------------------------------------- the choice


@pytest.mark.parametrize("gpu", ["dev", "proc"])
def test_nvidia_is_chosen_with_its_vendor_file_and_a_visible_gpu(tmp_path, gpu):
    root = make_machine(tmp_path, gpu=gpu)
    assert nvidia_egl_problem({}, root) is None
    assert renderer_environment({}, root=root) == {MUJOCO_GL: "egl", VENDOR_FILES: nvidia(root)}
    assert renderer_environment({"CUDA_VISIBLE_DEVICES": "1"}, root=root)[VENDOR_FILES] == nvidia(root)


def test_without_the_vendor_file_or_a_gpu_glvnd_keeps_its_default(tmp_path):
    no_vendor = make_machine(tmp_path / "a", vendors=("mesa",))
    no_gpu = make_machine(tmp_path / "b", gpu=None)
    control_nodes_only = make_machine(tmp_path / "c", gpu=None)
    (control_nodes_only / "dev/nvidiactl").touch()  # present without a GPU node: not a GPU
    for root in (no_vendor, no_gpu, control_nodes_only):
        assert renderer_environment({}, root=root) == {MUJOCO_GL: "egl"}
    assert nvidia_egl_problem({}, no_vendor) == (
        "no NVIDIA EGL vendor file (libEGL_nvidia) in /etc/glvnd/egl_vendor.d, /usr/share/glvnd/egl_vendor.d")
    assert nvidia_egl_problem({}, no_gpu) == (
        "no NVIDIA GPU visible (no /dev/nvidia<N>, nothing in /proc/driver/nvidia/gpus)")


@pytest.mark.parametrize("hidden", ["", "-1", " -1,0"])
def test_gpus_hidden_from_cuda_are_not_rendered_on(tmp_path, hidden):
    root = make_machine(tmp_path)
    environ = {"CUDA_VISIBLE_DEVICES": hidden}
    assert renderer_environment(environ, root=root) == {MUJOCO_GL: "egl"}
    assert nvidia_egl_problem(environ, root) == f"CUDA_VISIBLE_DEVICES={hidden!r} hides the GPUs"


def test_the_users_settings_are_kept(tmp_path):
    root = make_machine(tmp_path)
    assert renderer_environment({MUJOCO_GL: "osmesa"}, root=root) == {}
    assert renderer_environment({MUJOCO_GL: ""}, root=root) == {MUJOCO_GL: "egl", VENDOR_FILES: nvidia(root)}
    assert renderer_environment({MUJOCO_GL: "egl"}, root=root) == {VENDOR_FILES: nvidia(root)}
    assert renderer_environment({VENDOR_FILES: "/x/50_mesa.json"}, root=root) == {MUJOCO_GL: "egl"}
    assert renderer_environment({VENDOR_FOLDERS: "/x"}, root=root) == {MUJOCO_GL: "egl"}
    assert renderer_environment({MUJOCO_GL: "egl", VENDOR_FILES: "/x/10_nvidia.json"}, root=root) == {}


def test_software_and_gpu_are_forced_over_the_users_settings(tmp_path):
    root = make_machine(tmp_path)
    user = {MUJOCO_GL: "osmesa", VENDOR_FILES: "/x/10_nvidia.json"}
    assert renderer_environment(user, "software", root) == {MUJOCO_GL: "egl", VENDOR_FILES: mesa(root)}
    assert renderer_environment(user, "gpu", root) == {MUJOCO_GL: "egl", VENDOR_FILES: nvidia(root)}


def test_a_forced_renderer_that_is_missing_is_refused(tmp_path):
    no_mesa = make_machine(tmp_path / "a", vendors=("nvidia",))
    with pytest.raises(RuntimeError) as error:
        renderer_environment({}, "software", no_mesa)
    assert str(error.value) == ("software renderer: no Mesa EGL vendor file (libEGL_mesa) in /etc/glvnd/egl_vendor.d, "
                                "/usr/share/glvnd/egl_vendor.d; install libegl-mesa0")
    with pytest.raises(RuntimeError) as error:
        renderer_environment({}, "gpu", make_machine(tmp_path / "b", gpu=None))
    assert str(error.value) == ("GPU renderer: no NVIDIA GPU visible (no /dev/nvidia<N>, nothing in "
                                "/proc/driver/nvidia/gpus)")
    with pytest.raises(ValueError) as error:
        renderer_environment({}, "cuda", no_mesa)
    assert str(error.value) == "renderer 'cuda': expected one of ['auto', 'gpu', 'software']"


def test_vendor_files_are_found_by_driver_in_glvnd_order(tmp_path):
    root = make_machine(tmp_path, vendors=("mesa",))
    etc = root / "etc/glvnd/egl_vendor.d"
    etc.mkdir(parents=True)
    (etc / "05_broken.json").write_text("{not json")
    (etc / "20_mesa.json").write_text(json.dumps({"ICD": {"library_path": "/opt/mesa/libEGL_mesa.so.0"}}))
    assert vendor_file(MESA_LIBRARY, root) == etc / "20_mesa.json"  # /etc before /usr/share, the broken one skipped
    assert vendor_file(NVIDIA_LIBRARY, root) is None


def test_choose_renderer_sets_only_what_the_user_left_unset(monkeypatch):
    for name in GL_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv(VENDOR_FILES, "/x/50_mesa.json")
    assert choose_renderer() == {MUJOCO_GL: "egl"}
    assert (os.environ[MUJOCO_GL], os.environ[VENDOR_FILES]) == ("egl", "/x/50_mesa.json")
    assert choose_renderer() == {}  # every later call (each prepare_libero) changes nothing
    monkeypatch.setenv(MUJOCO_GL, "osmesa")
    assert choose_renderer() == {} and os.environ[MUJOCO_GL] == "osmesa"


# ----------------------------------------------------------------------------- this machine's renderer


def test_a_renderer_that_cannot_be_queried_is_unknown(monkeypatch):
    monkeypatch.delenv(MUJOCO_GL, raising=False)
    assert gl_renderer(object()) == "unknown (AttributeError: 'object' object has no attribute 'env')"


def run_fresh(code: str) -> list[str]:
    """Return the stdout lines of `code` run in a fresh process without the user's GL settings."""
    environment = {name: value for name, value in os.environ.items() if name not in GL_VARIABLES}
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO_ROOT, env=environment,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return [line for line in done.stdout.splitlines() if not line.startswith("[info]")]


def test_describe_renderer_names_the_software_renderer_here():
    if nvidia_egl_problem(os.environ) is None:
        pytest.skip("NVIDIA's EGL renders on this machine")
    lines = run_fresh("""
        import os
        from steering_core.rollout.renderer import describe_renderer
        print(describe_renderer())
        print(os.environ["MUJOCO_GL"], os.environ.get("__EGL_VENDOR_LIBRARY_FILENAMES"))
    """)
    assert lines[0].startswith("rendering with EGL on ")
    assert "llvmpipe" in lines[0] or "Mesa" in lines[0]
    assert lines[1] == "egl None"  # no NVIDIA here: glvnd's default vendor


def test_an_envs_renderer_is_named_and_its_cameras_still_render(tmp_path):
    # robosuite renders with whichever EGL context is current: querying a fresh one must put the env's back
    lines = run_fresh(f"""
        import numpy as np
        from steering_core.rollout.assets import resolve_assets
        from steering_core.rollout.libero_env import (CAMERAS, find_task, initial_states, make_env, prepare_libero,
                                                      task_index)
        from steering_core.rollout.renderer import gl_renderer

        prepare_libero(resolve_assets("installed"), {str(tmp_path)!r})
        index = task_index("libero_goal", "turn on the stove")
        env = make_env(find_task("libero_goal", index))
        env.reset()
        env.set_init_state(initial_states("libero_goal", index)[0])

        def images():  # as robosuite's camera sensors render, on whichever context is current
            return np.stack([env.env.sim.render(camera_name=camera, width=256, height=256) for camera in CAMERAS])

        before = images()
        print(gl_renderer(env))
        print(gl_renderer())
        print(before.mean(), np.array_equal(images(), before))
    """)
    assert lines[0] == lines[1] and ("llvmpipe" in lines[0] or "Mesa" in lines[0])
    level, same = lines[2].split()
    assert float(level) > 50 and same == "True"  # black (level ~0) had the env's context not been made current again
