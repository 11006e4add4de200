"""LIBERO setup in a fresh process: the config is written, libero imports without its stdin question."""

import os
import subprocess
import sys

import yaml

SCRIPT = """
import os
from steering_core.rollout import libero_env
try:
    libero_env.find_task("libero_goal", 0)
except RuntimeError as error:
    print(error)
libero_env.prepare_libero(None)
import libero.libero
print(os.environ["LIBERO_CONFIG_PATH"], os.environ["MUJOCO_GL"], libero.libero._assets_path_cache)
print(libero_env.find_task("libero_goal", 7).language)
"""


def test_prepare_libero_writes_a_config_and_imports_without_a_question(tmp_path):
    environment = {key: value for key, value in os.environ.items() if key not in ("LIBERO_CONFIG_PATH", "MUJOCO_GL")}
    environment |= {"XDG_CACHE_HOME": str(tmp_path / "cache"), "HOME": str(tmp_path / "home")}
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        env=environment,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    config_dir = tmp_path / "cache" / "latent-steering" / "libero"
    lines = [line for line in done.stdout.splitlines() if not line.startswith("[info]")]
    assert lines == [
        "LIBERO is not set up: call prepare_libero(resolve_assets(...)) first",
        f"{config_dir} egl None",
        "turn on the stove",
    ]
    config = yaml.safe_load((config_dir / "config.yaml").read_text())
    assert sorted(config) == ["assets", "bddl_files", "benchmark_root", "datasets", "init_states"]
    assert config["bddl_files"] == os.path.join(config["benchmark_root"], "bddl_files")
    assert config["benchmark_root"].endswith(os.path.join("libero", "libero"))
    assert not (tmp_path / "home" / ".libero" / "config.yaml").exists()
