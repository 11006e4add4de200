"""The library stands alone: importing any steering_core subpackage loads neither Prefect nor the flows."""

import subprocess
import sys

import pytest

SUBPACKAGES = (
    "steering_core",
    "steering_core.data",
    "steering_core.pi05",
    "steering_core.capture",
    "steering_core.sae",
    "steering_core.sae.training.loop",
    "steering_core.sae.judge_run",
    "steering_core.synthetic",
    "steering_core.evaluate",
    "steering_core.evaluate.run",
    "steering_core.config",
    "steering_core.demo",
    "steering_core.refresh",
    "steering_core.storage.fingerprints",
    "steering_core.preflight",
    "steering_core.storage",
    "steering_core.storage.tensor_files",
    "steering_core.reporting",
    "steering_core.serve",
)


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_library_imports_without_prefect_or_flows(name):
    code = (
        f"import importlib, sys; importlib.import_module({name!r}); "
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('prefect', 'flows', 'tasks', 'latent_steering_cli')); "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"{name} pulled in {result.stdout.strip()} {result.stderr[-500:]}"
