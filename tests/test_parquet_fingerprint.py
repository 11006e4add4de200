"""The footer rewrite that gives lerobot's data parquet a content fingerprint, against `datasets` and pyarrow."""

from __future__ import annotations

import hashlib
import json

import datasets
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image

from steering_core.data.parquet_fingerprint import content_fingerprint


def write_like_lerobot(folder, name="file.parquet"):
    """Write a parquet as lerobot 0.4 does: `datasets` rows from staged PNG paths, embedded, ParquetWriter."""
    images = folder / "images"
    images.mkdir(parents=True)
    paths = []
    for i in range(3):
        paths.append(str(images / f"frame_{i:06d}.png"))
        Image.fromarray(np.full((4, 4, 3), 40 * i, np.uint8)).save(paths[-1])
    features = datasets.Features({"image": datasets.Image(), "index": datasets.Value("int64")})
    dataset = datasets.Dataset.from_dict({"image": paths, "index": [0, 1, 2]}, features=features, split="train")
    dataset = dataset.with_format("arrow").map(datasets.table.embed_table_storage, batched=False)
    table = dataset.with_format("arrow")[:]
    path = folder / name
    with pq.ParquetWriter(path, schema=table.schema, compression="snappy", use_dictionary=True) as writer:
        writer.write_table(table)
    return path


def fingerprint_of(path):
    return json.loads(pq.read_metadata(path).metadata[b"huggingface"])["fingerprint"]


def test_fingerprint_becomes_the_hash_of_the_data_bytes(tmp_path):
    path = write_like_lerobot(tmp_path / "a")
    before_bytes, before_table = path.read_bytes(), pq.read_table(path)
    old = fingerprint_of(path)

    new = content_fingerprint(path)

    after = path.read_bytes()
    footer = pq.read_metadata(path).serialized_size  # thrift footer, without the 8-byte tail
    assert new == fingerprint_of(path) == hashlib.sha256(after[: len(after) - 8 - footer]).hexdigest()[: len(old)]
    assert new != old and len(after) == len(before_bytes)
    changed = [i for i in range(len(after)) if after[i] != before_bytes[i]]
    assert changed and min(changed) >= len(after) - 8 - footer  # only the footer was touched
    assert pq.read_table(path).equals(before_table)
    # the Arrow schema pyarrow rebuilds from the footer says the same, and `datasets` loads the file
    assert json.loads(pq.read_schema(path).metadata[b"huggingface"])["fingerprint"] == new
    loaded = datasets.Dataset.from_parquet(str(path), cache_dir=str(tmp_path / "cache"))
    assert loaded["index"] == [0, 1, 2]
    assert np.asarray(loaded[2]["image"]).tolist() == np.full((4, 4, 3), 80, np.uint8).tolist()
    assert content_fingerprint(path) == new and path.read_bytes() == after  # idempotent


def test_same_rows_from_other_staging_paths_give_the_same_bytes(tmp_path):
    one, two = write_like_lerobot(tmp_path / "x"), write_like_lerobot(tmp_path / "y" / "deeper")
    assert one.read_bytes() != two.read_bytes()  # the fingerprint `datasets` stamps hashes the PNG paths
    content_fingerprint(one)
    content_fingerprint(two)
    assert one.read_bytes() == two.read_bytes()


def test_files_without_a_fingerprint_are_left_alone(tmp_path):
    plain = tmp_path / "plain.parquet"
    pq.write_table(pa.table({"x": [1, 2]}), plain)
    tagged = tmp_path / "tagged.parquet"
    pq.write_table(pa.table({"x": [1, 2]}).replace_schema_metadata({"huggingface": '{"info": {}}'}), tagged)
    for path in (plain, tagged):
        before = path.read_bytes()
        assert content_fingerprint(path) is None
        assert path.read_bytes() == before


def test_unexpected_footers_are_refused(tmp_path):
    odd = tmp_path / "odd.parquet"
    metadata = {"huggingface": json.dumps({"fingerprint": "abc123", "again": "abc123"})}
    pq.write_table(pa.table({"x": [1]}).replace_schema_metadata(metadata), odd)
    with pytest.raises(ValueError, match=r"odd.parquet: fingerprint abc123 appears 2 times"):
        content_fingerprint(odd)
    bad = tmp_path / "bad.parquet"
    pq.write_table(pa.table({"x": [1]}).replace_schema_metadata({"huggingface": '{"fingerprint": "../x"}'}), bad)
    with pytest.raises(ValueError, match=r"bad.parquet: `datasets` fingerprint '../x'.*expected 1-64 hex digits"):
        content_fingerprint(bad)
