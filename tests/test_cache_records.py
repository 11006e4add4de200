"""Cache records are data, never code: a tampered record in the shared output root is refused unread."""

from __future__ import annotations

import json
import pathlib
import types

import pytest
from prefect._internal.result_records import ResultRecord, ResultRecordMetadata
from prefect.serializers import JSONSerializer, PickleSerializer
from prefect.tasks import task

from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS, read_cache_record
from tasks.results import RESULTS, rooted


class Payload:
    """Unpickling this touches a marker file: proof that a record ran code."""

    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return (pathlib.Path.touch, (self.marker,))


@task(cache_policy=content_key("steering_core.layout"), **RESULTS)
def echo(value: int) -> dict:
    return {OUTPUTS: [], "value": value}


def record_path(tmp_path, value=1) -> pathlib.Path:
    """Return the record path the task `echo(value)` rooted at tmp_path would look up (the key is computed here)."""
    rooted_task = rooted(echo, tmp_path)
    key = rooted_task.cache_policy.compute_key(types.SimpleNamespace(task=rooted_task), {"value": value}, {})
    return tmp_path / ".prefect-cache" / key


def write_record(path, serializer, result, **metadata):
    record = ResultRecord(metadata=ResultRecordMetadata(storage_key=str(path), serializer=serializer, **metadata),
                          result=result)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(record.serialize())


def test_a_pickle_record_is_refused_without_running_it(tmp_path, caplog):
    path = record_path(tmp_path)
    marker = tmp_path / "ran"
    write_record(path, PickleSerializer(), Payload(marker))
    assert json.loads(path.read_bytes())["metadata"]["serializer"]["type"] == "pickle"
    record_path(tmp_path)  # the lookup Prefect makes before a task runs
    assert not marker.exists()
    assert not path.exists()  # dropped: the task will run and write a clean record
    assert "refused" in caplog.text and "pickle" in caplog.text


@pytest.mark.parametrize("tamper", [
    # Prefect's JSON decoder imports and builds any class a record names
    lambda p: write_record(p, JSONSerializer(), {"__class__": "pathlib.Path", "data": "x"}),
    # a JSON serializer whose decoder is another function
    lambda p: p.write_text(p.read_text().replace("prefect.serializers.prefect_json_object_decoder", "builtins.eval")),
    lambda p: p.write_text(p.read_text().replace('"storage_key":"', '"storage_key":"/etc/')),
    lambda p: p.write_bytes(b"\x80\x04not json"),
])
def test_other_tampering_is_refused(tmp_path, tamper):
    path = record_path(tmp_path)
    write_record(path, JSONSerializer(), {OUTPUTS: [], "value": 1})
    assert read_cache_record(path) == {OUTPUTS: [], "value": 1}
    tamper(path)
    with pytest.raises(ValueError, match=str(path)):
        read_cache_record(path)
    record_path(tmp_path)
    assert not path.exists()
