"""RowSource: every selected row in shard order, shuffled streams that resume at a sample, flat memory, errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from steering_core.capture import shards
from steering_core.sae.training.rows import RowSource
from steering_core.synthetic.residual_run import LAYER, write_rows_run
from steering_core.tensor_files import tensor_locations

WIDTH = 8


def rows_of(n: int, width: int = WIDTH, seed: int = 0) -> torch.Tensor:
    """Return (n, width) rows whose first column is the row number, so any order can be traced back."""
    x = torch.randn(n, width, generator=torch.Generator().manual_seed(seed))
    x[:, 0] = torch.arange(n, dtype=torch.float32)
    return x


def take(stream, batches: int) -> list[torch.Tensor]:
    return [next(stream) for _ in range(batches)]


def test_sequential_gives_every_row_in_shard_order_with_its_columns(tmp_path):
    x = rows_of(600)
    write_rows_run(tmp_path, x, episodes=6, episodes_per_shard=2, storage_dtype="bfloat16")
    source = RowSource(tmp_path, LAYER)
    batches = list(source.sequential(64))
    assert (source.rows, source.width, source.token_type) == (600, WIDTH, "instructions")
    assert all(rows.dtype == torch.float32 and rows.shape[0] <= 64 for rows, _ in batches)
    assert torch.equal(torch.cat([rows for rows, _ in batches]), x.bfloat16().float())
    token_ids = torch.cat([torch.from_numpy(columns["token_id"]) for _, columns in batches])
    assert torch.equal(token_ids, torch.arange(600))
    assert set(batches[0][1]) == set(shards.ROW_COLUMNS)


def test_episode_selection_keeps_exactly_the_rows_of_the_chosen_episodes(tmp_path):
    x = rows_of(800)
    write_rows_run(tmp_path, x, episodes=8, episodes_per_shard=3)  # shards hold episodes 0-2, 3-5, 6-7
    source = RowSource(tmp_path, LAYER, episodes=[1, 2, 4, 7], exclude=[2])
    got = torch.cat([rows for rows, _ in source.sequential(50)])
    expected = torch.cat([x[100 * e : 100 * (e + 1)] for e in (1, 4, 7)])
    assert source.episodes == (1, 4, 7) and source.rows == 300
    assert torch.equal(got, expected)
    assert source.identity() != RowSource(tmp_path, LAYER).identity()
    assert source.identity() == RowSource(tmp_path, LAYER, episodes=[1, 4, 7]).identity()


def test_the_identity_follows_the_selected_shards_only(tmp_path):
    x = rows_of(400)
    write_rows_run(tmp_path / "a", x, episodes=4)
    write_rows_run(tmp_path / "b", torch.cat([x[:300], x[300:] + 1]), episodes=4)  # episode 3 differs
    for episodes, same in (([0, 1, 2], True), ([1, 3], False)):
        a, b = (RowSource(tmp_path / run, LAYER, episodes=episodes).identity() for run in "ab")
        assert (a == b) is same


def test_shuffled_epochs_are_permutations_that_mix_shards_and_depend_on_the_seed(tmp_path):
    x = rows_of(1024)
    write_rows_run(tmp_path, x, episodes=16)  # 64 rows per shard
    source = RowSource(tmp_path, LAYER)
    first = take(source.shuffled(64, seed=3, buffer_rows=256), 32)  # two epochs
    for epoch in (torch.cat(first[:16]), torch.cat(first[16:])):
        assert torch.equal(epoch[epoch[:, 0].argsort()], x)
    assert not torch.equal(first[0], first[16])  # each epoch in a new order
    shards_in_first_batch = set((first[0][:, 0] // 64).tolist())
    assert len(shards_in_first_batch) >= 3  # one buffer mixes pieces of many shards
    assert all(torch.equal(a, b) for a, b in zip(first, take(source.shuffled(64, seed=3, buffer_rows=256), 32)))
    assert not torch.equal(first[0], next(source.shuffled(64, seed=4, buffer_rows=256)))


@pytest.mark.parametrize("start_batch", [0, 1, 5, 7, 12, 23])  # 7 crosses an epoch boundary mid-batch
def test_a_stream_started_at_a_sample_gives_the_uninterrupted_stream_from_there(tmp_path, start_batch):
    write_rows_run(tmp_path, rows_of(700), episodes=7)  # 700 rows: batches of 96 straddle epochs
    source = RowSource(tmp_path, LAYER)
    reference = take(source.shuffled(96, seed=1, buffer_rows=160), 30)
    resumed = take(source.shuffled(96, seed=1, buffer_rows=160, start_sample=96 * start_batch), 30 - start_batch)
    assert all(torch.equal(a, b) for a, b in zip(reference[start_batch:], resumed, strict=True))


STREAM_CHILD = """
import json, sys
from pathlib import Path
from steering_core.sae.training.rows import RowSource

def status_kib(field):
    line = next(l for l in Path("/proc/self/status").read_text().splitlines() if l.startswith(field + ":"))
    return int(line.split()[1])

growth = []
for run in sys.argv[2:]:
    source = RowSource(run, int(sys.argv[1]))
    stream = source.shuffled(512, seed=0, buffer_rows=8192)
    before = status_kib("VmRSS")
    Path("/proc/self/clear_refs").write_text("5")  # the peak so far is forgotten: VmHWM restarts here
    for _ in range(source.rows // 512):
        next(stream)
    del stream
    growth.append(status_kib("VmHWM") - before)
print(json.dumps(growth))
"""


@pytest.mark.slow
def test_streaming_peak_memory_stays_flat_from_1x_to_50x_rows(tmp_path):
    """The stream's own peak (above the memory after imports, 0.5 GB of unrelated libraries) is flat."""
    width, base_rows = 64, 12_288
    episodes = {1: 4, 50: 40}
    runs = [write_rows_run(tmp_path / f"x{scale}", rows_of(base_rows * scale, width), episodes=count,
                           storage_dtype="bfloat16") for scale, count in episodes.items()]
    done = subprocess.run([sys.executable, "-c", STREAM_CHILD, str(LAYER), *map(str, runs)], capture_output=True,
                          text=True, cwd=Path(__file__).resolve().parents[1], timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    growth_1x, growth_50x = (kib * 1024 for kib in json.loads(done.stdout.strip().splitlines()[-1]))
    whole_run = base_rows * 50 * width * 4  # the 50x run as float32 rows: holding it would break the bound
    assert whole_run > 2 * growth_1x
    assert growth_50x <= 1.5 * growth_1x, (growth_1x, growth_50x)


def write_other_width_shard(run_dir: Path) -> None:
    """Add a shard of width WIDTH - 2 to a run of width WIDTH (as a capture with other settings would)."""
    other = shards.RunSpec(token_type="instructions", layers=(LAYER,), width=WIDTH - 2, inputs={"checkpoint": "x"})
    rows = shards.ShardRows(residuals=torch.zeros(2, WIDTH - 2), index=torch.tensor([900, 900]),
                            episode_index=torch.tensor([9, 9]), frame_index=torch.tensor([0, 0]),
                            token_position=torch.tensor([5, 6]), token_id=torch.tensor([1, 2]))
    shards.write_shard(run_dir, other, LAYER, shards.shard_key(9), rows, episodes=[9], inputs="x")
    shards.write_run_metadata(run_dir)


def write_nan_row(run_dir: Path, row: int = 5) -> Path:
    """Overwrite one residual of one row of the first shard with NaN (bytes changed after capture); return it."""
    path = run_dir / shards.read_run_metadata(run_dir).layer_shards(LAYER)[0].file
    location = tensor_locations(path)[shards.RESIDUALS]
    with open(path, "r+b") as handle:
        handle.seek(location.offset + row * location.row_bytes)
        handle.write(torch.tensor([float("nan")]).numpy().tobytes())
    return path


@pytest.mark.parametrize(
    "case, make, expected",
    [
        ("no metadata", lambda run: None, "metadata.json: run metadata not found"),
        ("layer not captured", lambda run: {"layer": 4}, "`run.layers` is [3], layer 4 was not captured"),
        ("episodes not captured", lambda run: {"episodes": [1, 7, 8]}, "episodes 7-8 have no rows of layer 3"),
        ("nothing left", lambda run: {"exclude": range(4)}, "no rows of layer 3 left after the selection"),
        ("other width", write_other_width_shard, "shard-00009.safetensors: `width` is 6, expected 8 from run.json"),
    ],
)
def test_bad_runs_are_refused_in_one_line_naming_the_file(tmp_path, case, make, expected):
    run = tmp_path / "run"
    if case != "no metadata":
        write_rows_run(run, rows_of(400), episodes=4)
    options = make(run) or {}
    with pytest.raises(ValueError) as error:
        RowSource(run, options.pop("layer", LAYER), **options)
    assert expected in str(error.value) and "\n" not in str(error.value)
    assert str(run) in str(error.value)


def test_nan_rows_stop_both_streams_in_one_line_naming_the_shard(tmp_path):
    write_rows_run(tmp_path, rows_of(400), episodes=4)
    path = write_nan_row(tmp_path)
    source = RowSource(tmp_path, LAYER)
    for stream in (source.sequential(64), source.shuffled(64, seed=0, buffer_rows=400)):
        with pytest.raises(ValueError) as error:
            list(zip(range(10), stream))
        assert f"{path}: tensor `residuals` holds NaN or Inf (nan at (5, 0))" in str(error.value)
        assert "\n" not in str(error.value)
