"""Object-storage roots: publication by record, pulls checked by sha256, ranged reads, locks by conditional create."""

from __future__ import annotations

import json
import threading
import time

import pytest

from steering_core.remote import filesystems, locks, publish, reads
from steering_core.storage import mirrors


def _fs():
    return filesystems.filesystem("s3")


def test_paths_and_urls_map_both_ways(bucket, tmp_path):
    mirror = mirrors.mount(f"{bucket}/runs/")
    assert mirror == tmp_path / "mirror" / "s3" / bucket[5:] / "runs"
    assert mirrors.url_of(mirror / "a" / "b.json") == f"{bucket}/runs/a/b.json"
    assert mirrors.url_of(tmp_path / "elsewhere") is None
    value = {"x": [str(mirror / "a"), "other"], "y": (str(mirror),)}
    assert mirrors.portable(value) == {"x": [f"{bucket}/runs/a", "other"], "y": (f"{bucket}/runs",)}
    assert mirrors.localize(mirrors.portable(value)) == value
    assert mirrors.mount("file:///tmp/x") == mirrors.Path("/tmp/x")


@pytest.mark.parametrize("url", ["ftp://host/x", "s3://", "s3://b/../c", "s3://b//c"])
def test_bad_urls_are_refused_in_one_line(url):
    with pytest.raises(ValueError, match="s3://|unsupported") as err:
        mirrors.split_url(url)
    assert "\n" not in str(err.value)


def test_a_folder_is_invisible_until_its_record_is_written(bucket):
    mirror = mirrors.mount(bucket)
    out = mirror / "steps" / "layer01"
    (out / "pair").mkdir(parents=True)
    (out / "pair" / "a.json").write_text('{"a": 1}')
    (out / "summary.md").write_text("# s\n")
    (out / ".x.lock").write_text("")  # a lock file is never published
    record = publish.publish(out)
    assert sorted(record["files"]) == ["layer01/pair/a.json", "layer01/summary.md"]
    keys = sorted(p.split("/", 1)[1] for p in _fs().find(bucket[5:]))
    assert keys == ["steps/.layer01.published.json", "steps/layer01/pair/a.json", "steps/layer01/summary.md"]
    assert publish.staging_files(bucket) == []
    # another machine: an empty mirror pulls the whole folder, bytes checked
    import shutil
    shutil.rmtree(mirror)
    fetched = publish.pull(out / "pair")
    assert [p.name for p in fetched] == ["a.json"] and (out / "pair" / "a.json").read_text() == '{"a": 1}'
    assert sorted(p.name for p in publish.pull(mirror)) == ["summary.md"]
    assert publish.pull(mirror) == []  # nothing new


def test_objects_without_a_record_are_not_pulled(bucket):
    mirror = mirrors.mount(bucket)
    _fs().pipe_file(f"{bucket[5:]}/half/x.json", b"{}")  # a writer died before its record
    assert publish.pull(mirror / "half") == [] and not (mirror / "half").exists()
    assert reads.remote_file(mirror / "half" / "x.json") is None


def test_an_object_changed_after_publication_is_named(bucket):
    mirror = mirrors.mount(bucket)
    (mirror / "m.json").parent.mkdir(parents=True, exist_ok=True)
    (mirror / "m.json").write_text('{"v": 1}')
    publish.publish(mirror / "m.json")
    _fs().pipe_file(f"{bucket[5:]}/m.json", b'{"v": 2}')
    (mirror / "m.json").unlink()
    with pytest.raises(ValueError) as err:
        publish.pull(mirror / "m.json")
    assert str(err.value).startswith(f"{bucket}/m.json: sha256 is ") and "\n" not in str(err.value)
    assert not (mirror / "m.json").exists()


def test_republishing_replaces_files_and_drops_stale_ones(bucket):
    mirror = mirrors.mount(bucket)
    out = mirror / "f"
    out.mkdir(parents=True)
    (out / "old.txt").write_text("old")
    publish.publish(out)
    (out / "old.txt").unlink()
    (out / "new.txt").write_text("new")
    publish.publish(out)
    assert sorted(p.rsplit("/", 1)[1] for p in _fs().find(f"{bucket[5:]}/f")) == ["new.txt"]


def test_ranged_reads_fetch_only_what_is_read(bucket):
    mirror = mirrors.mount(bucket)
    shard = mirror / "run" / "shard-00000.safetensors"
    shard.parent.mkdir(parents=True)
    shard.write_bytes(bytes(range(256)) * 4096)  # 1 MiB
    publish.publish(shard)
    assert publish.pull(mirror) == []  # shards stay in the bucket
    shard.unlink()
    remote = reads.remote_file(shard)
    assert remote.size == 1 << 20
    before = reads.Fetched.total
    with remote.open() as handle:
        handle.seek(1000)
        buffer = bytearray(300)
        assert handle.readinto(buffer) == 300
    assert bytes(buffer) == (bytes(range(256)) * 8)[1000 % 256: 1000 % 256 + 300]
    assert reads.Fetched.total - before == 300
    _fs().pipe_file(f"{bucket[5:]}/run/shard-00000.safetensors", b"x" * 10)
    with pytest.raises(ValueError, match=r"shard-00000.safetensors: size 10, ETag .* differ from its publication"):
        reads.remote_file(shard)


def test_staging_left_by_a_dead_writer_is_cleaned_by_the_next_publication(bucket):
    mirror = mirrors.mount(bucket)
    _fs().pipe_file(f"{bucket[5:]}/.staging/out.json.deadhost-1-abc/out.json", b"half")
    (mirror / "out.json").parent.mkdir(parents=True, exist_ok=True)
    (mirror / "out.json").write_text("{}")
    assert publish.staging_files(bucket) != []
    publish.publish(mirror / "out.json")
    assert publish.staging_files(bucket) == []


def test_an_input_root_is_pulled_as_it_is_and_refetched_when_changed(bucket):
    _fs().pipe_file(f"{bucket[5:]}/ckpt/model.safetensors", b"weights")
    local = mirrors.mount(f"{bucket}/ckpt", role="input")
    assert [p.name for p in publish.pull(local)] == ["model.safetensors"]
    assert publish.pull(local) == []
    _fs().pipe_file(f"{bucket[5:]}/ckpt/model.safetensors", b"weights2")
    _fs().invalidate_cache()
    assert [p.name for p in publish.pull(local)] == ["model.safetensors"]
    assert (local / "model.safetensors").read_bytes() == b"weights2"


def test_the_bucket_lock_excludes_and_is_taken_over_from_a_dead_holder(bucket, monkeypatch):
    monkeypatch.setenv(locks.LEASE_ENV, "2")
    mirror = mirrors.mount(bucket)
    events = []

    def hold(name):
        with locks.bucket_lock(mirror / "out"):
            events.append(f"{name} in")
            time.sleep(1.0)
            events.append(f"{name} out")

    threads = [threading.Thread(target=hold, args=(n,)) for n in "ab"]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert [e.split()[1] for e in events] == ["in", "out", "in", "out"]
    assert events[0].split()[0] == events[1].split()[0]
    # a holder that died: its lock object stays, never renewed
    _fs().pipe_file(f"{bucket[5:]}/.locks/out.lock", json.dumps({"holder": "dead"}).encode())
    started = time.monotonic()
    with locks.bucket_lock(mirror / "out"):
        waited = time.monotonic() - started
    assert 2.0 <= waited < 8
    assert not _fs().exists(f"{bucket[5:]}/.locks/out.lock")
