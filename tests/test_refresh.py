"""Demo-source change detection: added, changed, removed files; quick check; record round trip."""

import hashlib
import os
import shutil
from pathlib import Path

import pytest

from steering_core import refresh
from steering_core.data.dataset import dataset_fingerprint
from steering_core.refresh import diff_sources, read_sources_record, scan_dataset, scan_sources

V21_DATASET = Path(__file__).parent / "fixtures" / "lerobot_v21_video"


def _write(path, data: bytes):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path.resolve()


@pytest.fixture
def sources(tmp_path):
    a = _write(tmp_path / "src1" / "A_demo.hdf5", b"alpha")
    b = _write(tmp_path / "src2" / "B_demo.hdf5", b"beta")
    _write(tmp_path / "src1" / "notes.txt", b"not a demo")
    _write(tmp_path / "src1" / "nested" / "C_demo.hdf5", b"not looked at, like the filter step")
    return [tmp_path / "src1", tmp_path / "src2"], a, b


def test_scan_hashes_every_demo_file(sources):
    folders, a, b = sources
    record = scan_sources(folders)
    assert sorted(record.files) == sorted([str(a), str(b)])
    assert record.files[str(a)].sha256 == hashlib.sha256(b"alpha").hexdigest()
    assert record.files[str(b)].size == 4


def test_diff_reports_added_changed_removed(sources, tmp_path):
    folders, a, b = sources
    before = scan_sources(folders)
    assert not diff_sources(before, scan_sources(folders, previous=before))

    c = _write(tmp_path / "src1" / "C_demo.hdf5", b"gamma")
    a.write_bytes(b"alpha, re-recorded")
    b.unlink()
    changes = diff_sources(before, scan_sources(folders, previous=before))
    assert changes.added == (str(c),)
    assert changes.changed == (str(a),)
    assert changes.removed == (str(b),)
    assert changes.describe() == "1 added (C_demo.hdf5), 1 changed (A_demo.hdf5), 1 removed (B_demo.hdf5)"


def test_quick_check_reuses_hash_only_when_size_and_mtime_match(sources):
    folders, a, _ = sources
    before = scan_sources(folders)
    stat = a.stat()
    # Same size and mtime but different bytes: the quick check cannot see it, a rehash can.
    a.write_bytes(b"ALPHA")
    os.utime(a, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert not diff_sources(before, scan_sources(folders, previous=before))
    assert diff_sources(before, scan_sources(folders, previous=before, rehash=True)).changed == (str(a),)


def test_first_run_and_config_change_trigger_a_run(sources):
    folders, _, _ = sources
    record = scan_sources(folders).with_config("cfg-1")
    first = diff_sources(None, record)
    assert first and first.first_run
    assert not diff_sources(record, record, config_fingerprint="cfg-1")
    changed = diff_sources(record, record, config_fingerprint="cfg-2")
    assert changed and changed.config_changed
    assert changed.describe().endswith("run config changed")


def test_record_round_trip_and_missing(tmp_path, sources):
    folders, _, _ = sources
    path = tmp_path / "out" / refresh.SOURCES_RECORD_FILE
    assert read_sources_record(path) is None
    record = scan_sources(folders).with_config("abc")
    refresh.write_sources_record(path, record)
    assert read_sources_record(path) == record


def test_bad_record_and_missing_folder_errors(tmp_path):
    bad = tmp_path / "last_success.json"
    bad.write_text('{"format_version": 7, "files": {}}')
    with pytest.raises(ValueError, match=r"`format_version` is 7, expected 1; delete the file"):
        read_sources_record(bad)
    with pytest.raises(FileNotFoundError, match=r"demo source folder\(s\) not found: .*nowhere"):
        scan_sources([tmp_path / "nowhere"])


def test_existing_dataset_is_keyed_on_its_content_fingerprint(tmp_path):
    dataset = tmp_path / "ds"
    shutil.copytree(V21_DATASET, dataset)
    before = scan_dataset(dataset).with_config("cfg")
    assert (before.dataset_root, before.dataset_fingerprint) == (str(dataset.resolve()), dataset_fingerprint(dataset))
    assert before.files == {}
    unchanged = diff_sources(before, scan_dataset(dataset), config_fingerprint="cfg")
    assert not unchanged and unchanged.describe() == f"dataset {dataset.resolve()}: content unchanged"
    os.utime(dataset / "meta/tasks.jsonl")  # touched, same bytes: still unchanged
    assert not diff_sources(before, scan_dataset(dataset), config_fingerprint="cfg")

    (dataset / "meta/tasks.jsonl").write_text('{"task_index": 0, "task": "a relabelled task"}\n')
    changed = diff_sources(before, scan_dataset(dataset), config_fingerprint="cfg")
    assert changed and changed.dataset_changed and changed.describe().endswith("content changed")
    moved = tmp_path / "moved"
    shutil.copytree(V21_DATASET, moved)  # same content somewhere else: a different input
    assert diff_sources(before, scan_dataset(moved), config_fingerprint="cfg").dataset_changed
    path = tmp_path / "out" / refresh.SOURCES_RECORD_FILE
    refresh.write_sources_record(path, before)
    assert read_sources_record(path) == before
