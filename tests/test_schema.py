"""Settings models are strict and hash canonically; JSON records are read with one clear error."""

import json

import pytest
from pydantic import ValidationError

from steering_core.storage.schema import StrictModel, read_model


class Inner(StrictModel):
    size: int


class Record(StrictModel):
    format_version: int = 2
    name: str
    inner: Inner


def test_strict_model_refuses_unknown_keys_and_hashes_canonically():
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        Record(name="a", inner={"size": 1}, extra=1)
    a = Record(name="a", inner={"size": 1})
    assert a.fingerprint() == Record.model_validate_json(a.model_dump_json()).fingerprint()
    assert a.fingerprint() != Record(name="a", inner={"size": 2}).fingerprint()


def test_read_model_checks_version_then_lists_every_problem(tmp_path):
    path = tmp_path / "record.json"
    path.write_text(json.dumps({"format_version": 2, "name": "x", "inner": {"size": 3}}))
    assert read_model(path, Record, what="record", format_version=2) == Record(name="x", inner={"size": 3})

    path.write_text(json.dumps({"format_version": 1, "name": "x"}))
    with pytest.raises(ValueError) as err:
        read_model(path, Record, what="record", fix="re-run it", format_version=2)
    assert str(err.value) == f"{path}: `format_version` is 1, expected 2; re-run it"

    path.write_text(json.dumps({"format_version": 2, "inner": {"size": "big"}, "typo": 1}))
    with pytest.raises(ValueError) as err:
        read_model(path, Record, what="record", fix="re-run it")
    assert str(err.value) == (
        f"{path}: not a valid record: name: Field required; "
        "inner.size: Input should be a valid integer, found a str; "
        "typo: Extra inputs are not permitted; re-run it"
    )


class Batch(StrictModel):
    records: list[Inner]


def test_the_same_problem_at_many_list_positions_is_one_line(tmp_path):
    """A field wrong in every shard record of a large run reads as one line, not one per shard."""
    path = tmp_path / "batch.json"
    records = [{"size": 1, "x": 1}, {"size": 2, "x": 1}, {"size": 3, "x": 1}, {"size": "big"}, {"size": 5, "x": 1}]
    path.write_text(json.dumps({"records": records}))
    with pytest.raises(ValueError) as err:
        read_model(path, Batch, what="batch")
    assert str(err.value) == (
        f"{path}: not a valid batch: records.<0-2, 4>.x (4 entries): Extra inputs are not permitted; "
        "records.3.size: Input should be a valid integer, found a str"
    )
