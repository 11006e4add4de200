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
    config, out = cli_steps_run  # the first clean run, shared with other tests: put back as it was, whatever happens
    first = tmp_path / "first"
    shutil.move(out, first)
    try:
        run_cli_steps(config, out)  # the same paths, so recorded paths agree too

        def files(root):
            return {p.relative_to(root): p for p in sorted(root.rglob("*")) if p.is_file()}

        ours, theirs = files(first), files(out)
        assert ours.keys() == theirs.keys()
        assert list(first.glob(DATASET_PARQUET))
        differ = sorted(str(k) for k in ours if ours[k].read_bytes() != theirs[k].read_bytes())
        assert differ == []
    finally:
        shutil.rmtree(out, ignore_errors=True)
        shutil.move(first, out)
