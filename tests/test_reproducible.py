"""Every output is the same bytes for the same inputs: two clean runs of every step, compared file by file."""

from __future__ import annotations

import shutil

import pytest
from helpers_pipeline import run_cli_steps

from steering_core.config import load_run_config
from steering_core.demo import build_demo

pytestmark = pytest.mark.slow

# lerobot's data parquet: `datasets` stamps it with a hash of the staging path, which convert replaces by one of
# the file's content, so it is compared byte for byte like every other file
DATASET_PARQUET = "libero_lerobot/*/data/**/*.parquet"


def files(root):
    return {p.relative_to(root): p for p in sorted(root.rglob("*")) if p.is_file()}


def test_two_clean_runs_write_equal_bytes(tmp_path):
    """Both runs write to the same folder (the first is moved aside), so the paths they record agree too."""
    config = load_run_config(build_demo(tmp_path / "demo", demos_per_task=2))
    out, first = tmp_path / "out", tmp_path / "first"
    run_cli_steps(config, out)
    shutil.move(out, first)
    run_cli_steps(config, out)

    ours, theirs = files(first), files(out)
    assert ours.keys() == theirs.keys()
    assert list(first.glob(DATASET_PARQUET))
    differ = sorted(str(k) for k in ours if ours[k].read_bytes() != theirs[k].read_bytes())
    assert differ == []
