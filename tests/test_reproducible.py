"""Every output is the same bytes for the same inputs: two clean runs of every step, compared file by file."""

from __future__ import annotations

import shutil

import pytest
from helpers_pipeline import run_cli_steps

pytestmark = pytest.mark.slow

# lerobot's data parquet: `datasets` stamps it with a hash of the staging path, which convert replaces by one of
# the file's content, so it is compared byte for byte like every other file
DATASET_PARQUET = "libero_lerobot/*/data/**/*.parquet"


def test_two_clean_runs_write_equal_bytes(cli_steps_run, tmp_path):
    config, out = cli_steps_run  # the first clean run, shared with test_flows
    first = tmp_path / "first"
    shutil.move(out, first)
    run_cli_steps(config, out)  # the same paths, so recorded paths agree too; `out` then holds the same bytes again

    def files(root):
        return {p.relative_to(root): p for p in sorted(root.rglob("*")) if p.is_file()}

    ours, theirs = files(first), files(out)
    assert ours.keys() == theirs.keys()
    assert list(first.glob(DATASET_PARQUET))
    differ = sorted(str(k) for k in ours if ours[k].read_bytes() != theirs[k].read_bytes())
    assert differ == []
