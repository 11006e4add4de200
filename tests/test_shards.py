"""Residual shard format: round trips, validation messages, checksums, run metadata assembly."""

from __future__ import annotations

import hashlib
import json
import zlib

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from steering_core.capture import shards
from steering_core.storage.fileio import sha256_file

WIDTH = 8


def make_spec(**overrides) -> shards.RunSpec:
    fields = dict(token_type="instructions", layers=(1, 3), width=WIDTH, inputs={"checkpoint": "abc"})
    fields.update(overrides)
    return shards.RunSpec(**fields)


def make_rows(episode: int, frames: int = 3, tokens: int = 2, seed: int = 0) -> shards.ShardRows:
    """Rows of one episode, deliberately written in reverse order to exercise sorting."""
    generator = torch.Generator().manual_seed(seed + episode)
    n = frames * tokens
    frame = torch.arange(frames).repeat_interleave(tokens)
    position = torch.tensor([770, 771] * frames)[:n]
    rows = shards.ShardRows(
        residuals=torch.randn(n, WIDTH, generator=generator),
        index=frame + 100 * episode,
        episode_index=torch.full((n,), episode),
        frame_index=frame,
        token_position=position,
        token_id=torch.arange(n) + 5,
    )
    flip = torch.arange(n - 1, -1, -1)
    return shards.ShardRows(**{k: getattr(rows, k)[flip] for k in ("residuals", *shards.ROW_COLUMNS)})


def test_round_trip_sorts_rows_and_records_sidecar(tmp_path):
    spec = make_spec()
    rows = make_rows(episode=2)
    record = shards.write_shard(tmp_path, spec, 3, "00002", rows, episodes=[2], inputs="in", tasks={"t": {"a": 1}})

    path = tmp_path / "instructions" / "layer03" / "shard-00002.safetensors"
    assert record.file == "instructions/layer03/shard-00002.safetensors"
    assert record.sha256 == sha256_file(path)
    assert (record.rows, record.width, record.dtype, record.episodes) == (6, WIDTH, "float32", (2,))
    assert shards.read_shard_record(path.with_suffix(".json")) == record

    with shards.open_shard(path, width=WIDTH, dtype="float32", rows=6, sha256=record.sha256) as reader:
        columns = reader.columns()
        some = reader.columns(["token_id", "episode_index"])
        residuals = reader.residuals()
        middle = reader.residuals(2, 4)
    expected_order = sorted(range(6), key=lambda i: (int(rows.index[i]), int(rows.token_position[i])))
    assert columns["index"].tolist() == [int(rows.index[i]) for i in expected_order]
    assert columns["token_id"].tolist() == [int(rows.token_id[i]) for i in expected_order]
    assert torch.equal(residuals, rows.residuals[expected_order])
    assert torch.equal(middle, residuals[2:4])
    assert all(c.dtype == np.int64 for c in columns.values())
    assert list(some) == ["token_id", "episode_index"]
    assert all(np.array_equal(some[name], columns[name]) for name in some)
    assert columns["episode_index"].tolist() == [2] * 6


def test_bfloat16_storage_and_deterministic_bytes(tmp_path):
    spec = make_spec(storage_dtype="bfloat16")
    rows = make_rows(episode=0)
    first = shards.write_shard(tmp_path / "a", spec, 1, "00000", rows, episodes=[0], inputs="in")
    second = shards.write_shard(tmp_path / "b", spec, 1, "00000", rows, episodes=[0], inputs="in")
    assert first.sha256 == second.sha256
    with shards.open_shard(tmp_path / "a" / first.file, dtype="bfloat16") as reader:
        stored = reader.residuals()
    assert stored.dtype == torch.bfloat16
    order = torch.arange(5, -1, -1)
    assert torch.equal(stored, rows.residuals[order].to(torch.bfloat16))


def test_bad_shards_give_one_message_each(tmp_path):
    path = tmp_path / "shard-00003.safetensors"
    columns = {name: torch.zeros(4, dtype=torch.int64) for name in shards.ROW_COLUMNS}
    header = {"latent_steering": json.dumps({"layer": 12, "format_version": 1})}
    save_file({"residuals": torch.zeros(4, 6), **columns}, str(path), metadata=header)
    with pytest.raises(ValueError) as err:
        with shards.open_shard(path, width=WIDTH, dtype="bfloat16"):
            pass
    assert str(err.value) == (
        f"{path}: `residuals` is (4, 6) float32, expected (*, {WIDTH}) bfloat16; re-run capture for layer 12"
    )

    del columns["token_id"]
    columns["frame_index"] = torch.zeros(3, dtype=torch.int32)
    save_file({"residuals": torch.zeros(4, WIDTH), "extra": torch.zeros(1), **columns}, str(path))
    with pytest.raises(ValueError) as err:
        with shards.open_shard(path):
            pass
    message = str(err.value)
    assert "header `format_version` is None, expected 1" in message
    assert "tensors missing ['token_id'], unexpected ['extra']" in message
    assert "`frame_index` is (3,) I32, expected (4,) I64" in message

    path.write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="not a readable safetensors file"):
        with shards.open_shard(path):
            pass
    with pytest.raises(FileNotFoundError, match="shard not found"):
        with shards.open_shard(tmp_path / "missing.safetensors"):
            pass


def test_checksum_mismatch_is_detected(tmp_path):
    spec = make_spec()
    record = shards.write_shard(tmp_path, spec, 1, "00000", make_rows(0), episodes=[0], inputs="in")
    path = tmp_path / record.file
    assert record.crc32 == zlib.crc32(path.read_bytes()) and record.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert shards.find_complete_shard(tmp_path, spec, 1, "00000", "in") == record
    assert shards.find_complete_shard(tmp_path, spec, 1, "00000", "other inputs") is None

    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF  # flip bits in the last residual value: still a valid file
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"sha256 is [0-9a-f]{64}, expected " + record.sha256):
        with shards.open_shard(path, sha256=record.sha256):
            pass
    assert shards.find_complete_shard(tmp_path, spec, 1, "00000", "in") is None
    path.unlink()
    assert shards.find_complete_shard(tmp_path, spec, 1, "00000", "in") is None


def test_write_rejects_bad_rows(tmp_path):
    rows = make_rows(0)
    bad = shards.ShardRows(**{**rows.__dict__, "residuals": rows.residuals[:, :3], "token_id": rows.token_id[:2]})
    with pytest.raises(ValueError) as err:
        shards.write_shard(tmp_path, make_spec(), 2, "00000", bad, episodes=[0], inputs="in")
    assert str(err.value) == (
        "shard-00000.safetensors (layer 2): layer 2 is not one of the run's layers [1, 3]; "
        f"`residuals` is (6, 3) torch.float32, expected (*, {WIDTH}) floating point; "
        "`token_id` is (2,) torch.int64, expected (6,) integer"
    )
    assert not (tmp_path / "instructions").exists()


def test_run_metadata_assembles_sidecars_of_several_workers(tmp_path):
    spec = make_spec(sources={"dataset_root": "/data/a"})
    shards.write_run_spec(tmp_path, spec)
    # a second worker with the same identity but another source path is accepted
    shards.write_run_spec(tmp_path, make_spec(sources={"dataset_root": "/mnt/a"}))
    for episode in (1, 0):
        for layer in spec.layers:
            if (episode, layer) != (1, 3):  # episode 1 of layer 3 still missing
                tasks = {f"task {episode}": {"token_ids": [episode]}}
                shards.write_shard(tmp_path, spec, layer, shards.shard_key(episode), make_rows(episode),
                                   episodes=[episode], inputs=f"in{episode}", tasks=tasks)
    shards.write_run_metadata(tmp_path)
    metadata = shards.read_run_metadata(tmp_path)
    assert [(r.layer, r.episodes) for r in metadata.shards] == [(1, (0,)), (1, (1,)), (3, (0,))]
    assert metadata.episodes == (0,)
    assert metadata.run.sources == {"dataset_root": "/mnt/a"}
    assert metadata.tasks == {"task 0": {"token_ids": [0]}, "task 1": {"token_ids": [1]}}
    assert [r.key for r in metadata.layer_shards(1)] == ["00000", "00001"]

    shards.write_shard(tmp_path, spec, 3, "00001", make_rows(1), episodes=[1], inputs="in1")
    shards.write_run_metadata(tmp_path)
    updated = shards.read_run_metadata(tmp_path)
    assert updated.episodes == (0, 1)
    assert updated.run_fingerprint != metadata.run_fingerprint

    with pytest.raises(ValueError, match=r"other settings \(differs in layers, width\); choose a new output"):
        shards.write_run_spec(tmp_path, make_spec(layers=(1,), width=16))


def test_format_version_is_checked(tmp_path):
    shards.write_run_spec(tmp_path, make_spec())
    shards.write_run_metadata(tmp_path)
    payload = json.loads((tmp_path / "metadata.json").read_text())
    payload["format_version"] = 99
    (tmp_path / "metadata.json").write_text(json.dumps(payload))
    with pytest.raises(ValueError, match=r"`format_version` is 99, expected 1; .* re-run capture"):
        shards.read_run_metadata(tmp_path)
    with pytest.raises(FileNotFoundError, match="run metadata not found"):
        shards.read_run_metadata(tmp_path / "nothing")


def test_group_episodes():
    assert shards.group_episodes([5, 0, 1, 4, 1], 1) == {"00000": (0,), "00001": (1,), "00004": (4,), "00005": (5,)}
    assert shards.group_episodes(range(7), 3) == {"00000": (0, 1, 2), "00001": (3, 4, 5), "00002": (6,)}
    with pytest.raises(ValueError, match="episodes_per_shard is 0, expected a positive integer"):
        shards.group_episodes([0], 0)
