"""Atomic writes leave either the old or the new content, never a partial file or a stray temp."""

import hashlib
import json
import os
import stat
import zlib
from pathlib import Path

import pytest

from steering_core.storage.fileio import (
    Crc32,
    atomic_dir,
    atomic_path,
    feed_file,
    read_json,
    remove_stale_staging,
    sha256_file,
    sha256_json,
    write_json,
)


def test_atomic_path_replaces_only_on_success(tmp_path):
    target = tmp_path / "out.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]
    with atomic_path(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]


def test_atomic_files_get_umask_mode(tmp_path):
    old = os.umask(0o022)
    try:
        write_json(tmp_path / "a.json", {"x": 1})
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o644


def test_atomic_dir_builds_aside_then_swaps(tmp_path):
    target = tmp_path / "dataset"
    with atomic_dir(target) as build:
        assert not build.exists()
        build.mkdir()
        (build / "f.txt").write_text("v1")
    assert (target / "f.txt").read_text() == "v1"
    with pytest.raises(FileExistsError, match="already exists"):
        with atomic_dir(target):
            pass
    with pytest.raises(RuntimeError):
        with atomic_dir(target, overwrite=True) as build:
            build.mkdir()
            (build / "f.txt").write_text("v2-partial")
            raise RuntimeError("crash")
    assert (target / "f.txt").read_text() == "v1"
    with atomic_dir(target, overwrite=True) as build:
        build.mkdir()
        (build / "f.txt").write_text("v2")
    assert (target / "f.txt").read_text() == "v2"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dataset"]


def test_read_json_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.json: file not found"):
        read_json(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"a": 1,\n}')
    with pytest.raises(ValueError, match=r"bad.json: not valid JSON \(line 2, column 1"):
        read_json(bad)
    write_json(tmp_path / "ok.json", {"ü": [1, 2]})
    assert read_json(tmp_path / "ok.json") == {"ü": [1, 2]}


def test_read_json_refuses_binary_files_and_keys_given_twice(tmp_path):
    binary = tmp_path / "binary.json"
    binary.write_bytes(b'{"a": "\xff"}')
    with pytest.raises(ValueError, match=r"binary.json: not a text file \(byte 7 is not UTF-8\); expected a JSON file"):
        read_json(binary)
    twice = tmp_path / "twice.json"
    twice.write_text('{"a": {"b": 1, "b": 2}}')
    with pytest.raises(ValueError, match=r"twice.json: key 'b' appears twice in one object; keep one"):
        read_json(twice)


def test_hashes_match_hashlib(tmp_path):
    blob = os.urandom(3 * (1 << 20) + 17)  # spans several read chunks
    (tmp_path / "blob").write_bytes(blob)
    assert sha256_file(tmp_path / "blob") == hashlib.sha256(blob).hexdigest()
    sha, crc = hashlib.sha256(), Crc32()
    feed_file(tmp_path / "blob", sha, crc)  # one read feeds both
    assert sha.hexdigest() == hashlib.sha256(blob).hexdigest()
    assert crc.value == zlib.crc32(blob) and crc.hexdigest() == f"{zlib.crc32(blob):08x}"
    assert sha256_json({"b": 1, "a": [1, 2]}) == sha256_json({"a": [1, 2], "b": 1})
    assert sha256_json({"a": 1}) == hashlib.sha256(json.dumps({"a": 1}).replace(" ", "").encode()).hexdigest()


@pytest.fixture
def group_umask():
    """A group-sharing umask (002) for one test; the previous one is restored."""
    previous = os.umask(0o002)
    yield
    os.umask(previous)


def test_outputs_follow_the_umask_without_changing_it(tmp_path, group_umask, monkeypatch):
    import torch
    from safetensors.torch import save_file

    def no_umask(mask):
        raise AssertionError("os.umask called: it is process-wide and races with threads creating files")

    monkeypatch.setattr(os, "umask", no_umask)
    with atomic_path(tmp_path / "a.safetensors") as tmp:  # safetensors creates its file 0600 by itself
        save_file({"x": torch.zeros(2)}, tmp)
    with atomic_dir(tmp_path / "folder") as tmp:
        (tmp / "inner").mkdir(parents=True)
        save_file({"x": torch.zeros(2)}, tmp / "inner" / "b.safetensors")
        (tmp / "c.json").write_text("{}")
    monkeypatch.undo()
    assert stat.S_IMODE((tmp_path / "a.safetensors").stat().st_mode) == 0o664
    for path in (tmp_path / "folder" / "inner" / "b.safetensors", tmp_path / "folder" / "c.json"):
        assert stat.S_IMODE(path.stat().st_mode) == 0o664, path
    for path in (tmp_path / "folder", tmp_path / "folder" / "inner"):
        assert stat.S_IMODE(path.stat().st_mode) == 0o775, path


def dead_pid() -> int:
    """Return the id of a process that has exited."""
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def staging_of(target, pid):
    import socket

    return target.parent / f".{target.name}.{socket.gethostname()}-{pid}.abc123.tmp"


def test_stale_staging_of_dead_processes_is_removed_on_the_next_run(tmp_path):
    target = tmp_path / "layer01"
    stale_dir, live_dir = staging_of(target, dead_pid()), staging_of(target, os.getppid())
    for folder in (stale_dir, live_dir):
        (folder / "layer01").mkdir(parents=True)
        (folder / "layer01" / "half.safetensors").write_bytes(b"x" * 10)
    stale_file = staging_of(tmp_path / "index.json", dead_pid())
    stale_file.write_text("{half")
    with atomic_dir(target) as tmp:  # a killed slice left its staging folder; the next one cleans it
        tmp.mkdir()
    with atomic_path(tmp_path / "index.json") as tmp:
        tmp.write_text("{}")
    assert not stale_dir.exists() and not stale_file.exists()
    assert live_dir.exists()  # a running process's staging is never touched


def test_a_swap_interrupted_between_its_renames_is_finished_by_the_next_run(tmp_path):
    target = tmp_path / "dataset"
    crashed = staging_of(target, dead_pid())
    (crashed / "dataset.old").mkdir(parents=True)  # the old copy moved aside, the new one never arrived
    (crashed / "dataset.old" / "data.parquet").write_text("old")
    assert remove_stale_staging(target) == [crashed]
    assert (target / "data.parquet").read_text() == "old"


@pytest.mark.parametrize("exchange", [True, False])
def test_overwrite_never_loses_the_old_copy(tmp_path, monkeypatch, exchange):
    from steering_core.storage import fileio

    target = tmp_path / "out"
    target.mkdir()
    (target / "a").write_text("old")
    if not exchange:  # a file system without renameat2's exchange: two renames
        monkeypatch.setattr(fileio, "_exchange", lambda new, old: False)
    with atomic_dir(target, overwrite=True) as tmp:
        tmp.mkdir()
        (tmp / "a").write_text("new")
    assert (target / "a").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]

    real_replace = os.replace

    def second_rename_fails(src, dst):
        if Path(src).name == "out" and Path(dst).name == "out":  # the new folder moving into place
            raise OSError("injected: rename failed")
        return real_replace(src, dst)

    monkeypatch.setattr(fileio, "_exchange", lambda new, old: False)
    monkeypatch.setattr(fileio.os, "replace", second_rename_fails)
    with pytest.raises(OSError, match="injected"):
        with atomic_dir(target, overwrite=True) as tmp:
            tmp.mkdir()
            (tmp / "a").write_text("newer")
    monkeypatch.undo()
    assert (target / "a").read_text() == "new"  # put back, not deleted with the staging folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
