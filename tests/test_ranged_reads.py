"""Shards left in the bucket are read by ranges: slices and SAE training rows equal a local run's, bytes bounded."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from steering_core.capture import shards
from steering_core.capture.slice_copy import _spans
from steering_core.capture.slicing import SliceSettings, slice_concepts
from steering_core.data.concept_map import ConceptMap, ConceptRow, write_concept_map
from steering_core.remote import filesystems, publish, reads
from steering_core.sae.training.rows import RowSource
from steering_core.storage import mirrors
from steering_core.tensor_files import tensor_locations

WIDTH, LAYER, FRAMES, TOKENS, EPISODES = 64, 3, 6, 4, 8  # episodes 0-3 and 4-7 share a shard each
ROW_BYTES = WIDTH * 4


def build_run(run_dir) -> None:
    """Write a run of two 4-episode shards whose rows are random."""
    spec = shards.RunSpec(token_type="instructions", layers=(LAYER,), width=WIDTH, episodes_per_shard=4,
                          inputs={"checkpoint": "tiny"})
    shards.write_run_spec(run_dir, spec)
    generator = torch.Generator().manual_seed(0)
    for key, members in shards.group_episodes(range(EPISODES), 4).items():
        episode = torch.tensor(members).repeat_interleave(FRAMES * TOKENS)
        frame = torch.arange(FRAMES).repeat_interleave(TOKENS).repeat(len(members))
        position = torch.arange(TOKENS).repeat(FRAMES * len(members)) + 513
        rows = shards.ShardRows(residuals=torch.randn(len(episode), WIDTH, generator=generator),
                                index=episode * FRAMES + frame, episode_index=episode, frame_index=frame,
                                token_position=position, token_id=position % 97)
        shards.write_shard(run_dir, spec, LAYER, key, rows, episodes=members, inputs="x")
    shards.write_run_metadata(run_dir)


def write_map(path, concepts: dict[str, list[tuple[int, int, int]]]):
    """Write a concept map of (episode, first frame, last frame) segments."""
    rows = {name: tuple(ConceptRow(segment_id=n, episode_index=e, frame_start=a, frame_end=b, observed_frame_start=a,
                                   observed_frame_end=b, start_index=e * FRAMES + a, end_index=e * FRAMES + b,
                                   length=b - a + 1) for n, (e, a, b) in enumerate(segments))
            for name, segments in concepts.items()}
    return write_concept_map(ConceptMap(manifest="test", lerobot_root="none", repo_id="test",
                                        concept_count={name: len(r) for name, r in rows.items()},
                                        sample_count=EPISODES * FRAMES, concepts=rows), path)


# in the first shard: the first and the last episode's frames, two-thirds of the shard between them unselected
CONCEPTS = {"open": [(0, 1, 4), (5, 0, 2)], "close": [(3, 2, 5)]}


@pytest.fixture
def run(bucket, tmp_path):
    """A run under a mounted bucket root: (run folder in the mirror, its shard files)."""
    run_dir = mirrors.mount(bucket) / "runs" / "r"
    build_run(run_dir)
    return run_dir, sorted(run_dir.rglob("shard-*.safetensors"))


def leave_in_bucket(run_dir, files, per_file=False) -> None:
    """Publish the run (whole, or file by file as capture's tasks do), then delete its shards here: they are read
    from the bucket from now on."""
    for unit in sorted(p for p in run_dir.rglob("*") if p.is_file()) if per_file else [run_dir]:
        publish.publish(unit)
    for file in files:
        file.unlink()


def slice_files(folder) -> dict[str, bytes]:
    return {path.name: path.read_bytes() for path in sorted((folder / f"layer{LAYER:02d}").iterdir())}


@pytest.mark.parametrize("reduce", ["token", "frame"])
def test_slices_from_the_bucket_equal_local_ones_and_fetch_only_the_selected_rows(run, tmp_path, reduce):
    run_dir, files = run
    concept_map = write_map(tmp_path / "map.json", CONCEPTS)
    settings = SliceSettings(layers=(LAYER,), reduce=reduce)
    slice_concepts(run_dir, concept_map, tmp_path / "local", settings)
    headers = sum(tensor_locations(file)[shards.RESIDUALS].offset for file in files)  # length, header, row columns
    leave_in_bucket(run_dir, files)
    before = reads.Fetched.total
    slice_concepts(run_dir, concept_map, tmp_path / "remote", settings)
    fetched = reads.Fetched.total - before
    assert slice_files(tmp_path / "remote") == slice_files(tmp_path / "local")
    assert not any(file.exists() for file in files)  # never downloaded
    selected = ROW_BYTES * TOKENS * sum(b - a + 1 for segments in CONCEPTS.values() for _, a, b in segments)
    span = ROW_BYTES * TOKENS * (4 * FRAMES - 1 + 3)  # episode 0 frame 1 to episode 3's end, and episode 5's
    assert selected + headers <= fetched <= 1.2 * (selected + headers) < span + headers


def test_runs_of_selected_rows_are_joined_across_the_smallest_gaps_within_a_tenth_of_the_rows():
    rows = np.array([0, 1, 2, 4, 5, 9, *range(20, 40)])  # 26 rows; gaps of 1, 3 and 10 rows: 2.6 may be read
    assert _spans(rows) == [(0, 6), (9, 10), (20, 40)]
    assert _spans(np.arange(5, 9)) == [(5, 9)] and _spans(np.array([], dtype=np.int64)) == []


def test_a_shard_changed_in_the_bucket_is_named_in_one_line(run, tmp_path):
    run_dir, files = run
    concept_map = write_map(tmp_path / "map.json", CONCEPTS)
    leave_in_bucket(run_dir, files)
    url = mirrors.url_of(files[1])
    fs, key = filesystems.object_path(url)
    data = bytearray(fs.cat_file(key))
    data[-1] ^= 1  # one bit of the last row
    fs.pipe_file(key, bytes(data))
    with pytest.raises(ValueError) as err:
        slice_concepts(run_dir, concept_map, tmp_path / "out", SliceSettings(layers=(LAYER,)))
    assert str(err.value).startswith(f"{url}: size ") and "changed after it was published" in str(err.value)
    assert "\n" not in str(err.value)


def test_run_metadata_is_rebuilt_where_the_shards_are_only_in_the_bucket(run):
    run_dir, files = run
    metadata = run_dir / shards.METADATA_FILE
    expected = metadata.read_bytes()
    leave_in_bucket(run_dir, files, per_file=True)
    metadata.unlink()
    shards.write_run_metadata(run_dir)
    assert metadata.read_bytes() == expected
    fs, key = filesystems.object_path(mirrors.url_of(files[0]))
    fs.rm_file(key)  # gone from the bucket, still listed by its publication record
    with pytest.raises(ValueError, match=f"its shard {files[0].relative_to(run_dir)} is missing; re-run capture"):
        shards.write_run_metadata(run_dir)


def test_sae_training_rows_from_the_bucket_equal_local_ones(run):
    run_dir, files = run
    local = RowSource(run_dir, LAYER, episodes=[0, 3, 5])
    sequential = list(local.sequential(7))
    shuffled = local.shuffled(8, seed=1, buffer_rows=40)
    first_batches = [next(shuffled) for _ in range(12)]
    headers = sum(tensor_locations(file)[shards.RESIDUALS].offset for file in files)
    leave_in_bucket(run_dir, files, per_file=True)
    before = reads.Fetched.total
    remote = RowSource(run_dir, LAYER, episodes=[0, 3, 5])
    remote_sequential = list(remote.sequential(7))
    fetched = reads.Fetched.total - before
    assert remote.identity() == local.identity() and remote.rows == 3 * FRAMES * TOKENS
    assert len(remote_sequential) == len(sequential)
    for (rows, columns), (expected_rows, expected_columns) in zip(remote_sequential, sequential):
        assert torch.equal(rows, expected_rows)
        assert columns.keys() == expected_columns.keys()
        assert all((columns[name] == expected_columns[name]).all() for name in columns)
    # the episodes' rows, and each shard's header and row columns twice (choosing the rows, then reading them)
    selected = remote.rows * ROW_BYTES
    assert selected < fetched <= 1.2 * (selected + 2 * headers)
    shuffled = remote.shuffled(8, seed=1, buffer_rows=40)
    assert all(torch.equal(next(shuffled), expected) for expected in first_batches)
    assert not any(file.exists() for file in files)


@pytest.mark.slow
def test_the_remote_slicing_benchmark_runs_at_quick_size(tmp_path):
    """bench.slicing_remote in its own process (it starts its own S3 endpoint): equal slices, bytes bounded."""
    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, "-m", "bench.slicing_remote", "--quick", f"--cache-dir={tmp_path}",
                           f"--json={tmp_path / 'result.json'}"], cwd=root, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-4000:]
    result = json.loads((tmp_path / "result.json").read_text())
    assert [row["selection"] for row in result["table"]] == [f"{size} shards, {selection}" for size in (
        "1-episode", "8-episode") for selection in ("fixed pair", "every row")]
    assert result["checks"]["same_slices"] and 1 <= result["checks"]["bytes_ratio"] <= 1.2
    assert result["ratio"] > 0 and result["command"] == "uv run python -m bench.slicing_remote --quick"
