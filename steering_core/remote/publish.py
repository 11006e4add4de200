"""Publication on object storage, where there is no rename: staging prefix, copy, commit record last.

`publish(path)` uploads a step's output (a file or a folder of the mirror) under a unique staging prefix
(`<parent>/.staging/<name>.<host>-<pid>-<id>/`), copies it server-side to its final keys, then writes its
*publication record* `<parent>/.<name>.published.json` (every file's size, sha256 and ETag). The record is
the commit point: readers (`pull`, `remote_file`) see an output only through its record, so a half-written
output is invisible. Republishing first deletes the record, so readers never mix two versions; shards absent
from the mirror (streamed, never pulled: a run resumed on another machine) stay published as they were. Staging
left by a dead writer is removed by the next publication of the same output (it holds the output's lock).

`pull(path)` brings the published outputs at, under or around `path` into the mirror, checking each file's
sha256 against its record; shards (`shard-*.safetensors`) stay in the bucket and are read by ranges
(`remote_file`), after their size and ETag are checked against the record. Input roots (a checkpoint a user
uploaded) have no records: their objects are pulled as they are, and skipped when the local copy has the
object's size and ETag.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import logging
import os
import socket
import uuid
from pathlib import Path, PurePosixPath
from typing import Any

from steering_core.remote.filesystems import object_path
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import atomic_path, sha256_file
from steering_core.storage.mirrors import Root, root_of

logger = logging.getLogger(__name__)

RECORD = ".{name}.published.json"
STAGING_DIR = ".staging"
STREAMED = ("shard-*.safetensors",)  # read by ranges from the bucket, never pulled
INPUT_STATE = ".{name}.etag"  # beside a pulled input file in the mirror: the object's ETag it was pulled at
REDO_HINT = ("delete the publication record of the output holding it (`.<name>.published.json` beside that output), "
         "and the step that wrote it runs again")
_SKIPPED_LOCAL = (".*.lock", ".*.tmp", ".*.etag")  # lock files, staging files, input states: never published


def url_at(root: Root, key: str) -> str:
    """Return the URL of `key` under `root` (the root itself for ``)."""
    return f"{root.url}/{key}" if key else root.url


def _record_url(url: str) -> str:
    parent, name = url.rsplit("/", 1)
    return f"{parent}/{RECORD.format(name=name)}"


def _local_files(path: Path) -> list[Path]:
    if path.is_file():
        return [path]
    return sorted(p for p in path.rglob("*") if p.is_file() and not any(
        fnmatch.fnmatch(p.name, pattern) for pattern in _SKIPPED_LOCAL))


def publish(path: str | os.PathLike) -> dict[str, Any] | None:
    """Publish the local file or folder `path` of a mounted output root; return its record (None if not mounted)."""
    path = Path(os.path.abspath(path))
    found = root_of(path)
    if found is None or found[1] == "":
        return None
    root, key = found
    url = url_at(root, key)
    fs, _ = object_path(url)
    parent_url, name = url.rsplit("/", 1)
    files = _local_files(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: nothing to publish to {url}")
    clean_staging(url)
    staging = f"{parent_url}/{STAGING_DIR}/{name}.{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:12]}"
    entries: dict[str, dict[str, Any]] = {}
    try:
        for file in files:
            relative = file.relative_to(path.parent).as_posix()
            _, staged = object_path(f"{staging}/{relative}")
            fs.put_file(str(file), staged)
            entries[relative] = {"size": file.stat().st_size, "sha256": sha256_file(file)}
        _, record_path = object_path(_record_url(url))
        kept = _streamed_elsewhere(url, path.parent, entries)
        with contextlib.suppress(FileNotFoundError):
            fs.rm_file(record_path)  # from here until the new record, the output is invisible
        stale = _published_files(fs, parent_url, url) - set(entries) - set(kept)
        for relative, entry in entries.items():
            _, staged = object_path(f"{staging}/{relative}")
            _, final = object_path(f"{parent_url}/{relative}")
            fs.copy(staged, final)
            entry["etag"] = fs.info(final).get("ETag")
        for relative in sorted(stale):
            with contextlib.suppress(FileNotFoundError):
                fs.rm_file(object_path(f"{parent_url}/{relative}")[1])
        record = {"format": 1, "kind": "folder" if path.is_dir() else "file", "files": {**kept, **entries}}
        fs.pipe_file(record_path, json.dumps(record, indent=1, sort_keys=True).encode())
        fs.invalidate_cache()
    finally:
        _remove_prefix(fs, staging)
    logger.info("published %s (%d files)", url, len(entries))
    return record


def _streamed_elsewhere(url: str, parent: Path, entries: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Return the entries of the current record of `url` for streamed files absent from this mirror.

    Shards are never pulled, so a folder republished from a machine that did not write them (a run resumed
    there) lacks them locally: they stay published as they are, not deleted as stale.
    """
    previous = read_record(url)
    return {relative: entry for relative, entry in (previous or {}).get("files", {}).items()
            if relative not in entries and not (parent / relative).exists()
            and any(fnmatch.fnmatch(PurePosixPath(relative).name, p) for p in STREAMED)}


def _published_files(fs: Any, parent_url: str, url: str) -> set[str]:
    """Return the files (relative to the parent) of the objects now at `url`: what a republication replaces."""
    _, path = object_path(url)
    _, parent = object_path(parent_url)
    with contextlib.suppress(FileNotFoundError):
        if fs.isfile(path):
            return {PurePosixPath(path).name}
        return {PurePosixPath(p).relative_to(parent).as_posix() for p in fs.find(path)}
    return set()


def _remove_prefix(fs: Any, url: str) -> None:
    _, path = object_path(url)
    with contextlib.suppress(FileNotFoundError):
        for item in fs.find(path):
            fs.rm_file(item)
    fs.invalidate_cache()


def clean_staging(url: str) -> list[str]:
    """Remove every staging prefix of the output `url` (left by dead writers; call while holding its lock)."""
    parent_url, name = url.rsplit("/", 1)
    fs, staging = object_path(f"{parent_url}/{STAGING_DIR}")
    with contextlib.suppress(FileNotFoundError):
        leftovers = [p for p in fs.ls(staging, detail=False) if PurePosixPath(p).name.startswith(f"{name}.")]
        for prefix in leftovers:
            logger.info("removing the staging objects %s left by an interrupted publication", prefix)
            _remove_prefix(fs, f"{parent_url.split('://')[0]}://{prefix}")
        return leftovers
    return []


def read_record(url: str) -> dict[str, Any] | None:
    """Return the publication record of the output `url`, or None when it is not published."""
    fs, record_path = object_path(_record_url(url))
    try:
        data = fs.cat_file(record_path)
    except FileNotFoundError:
        return None
    try:
        record = json.loads(data)
        assert isinstance(record, dict) and isinstance(record.get("files"), dict)
    except (ValueError, AssertionError):
        raise ValueError(f"{_record_url(url)}: not a publication record (JSON with `files`); republish the step "
                         "that wrote it") from None
    return record


def covering_record(url: str) -> tuple[str, dict[str, Any]] | None:
    """Return (parent URL, record) of the published output that is `url` or holds it, else None."""
    protocol, _, rest = url.partition("://")
    parts = rest.split("/")
    for depth in range(len(parts), 1, -1):  # never the bucket itself
        candidate = f"{protocol}://{'/'.join(parts[:depth])}"
        record = read_record(candidate)
        if record is not None:
            return candidate.rsplit("/", 1)[0], record
    return None


def is_published(url: str) -> bool:
    """Return True when the file or folder `url` is a published output or lies in one."""
    found = covering_record(url)
    if found is None:
        return False
    parent_url, record = found
    relative = url[len(parent_url) + 1:]
    return any(name == relative or name.startswith(relative + "/") for name in record["files"])


def records_under(url: str) -> list[tuple[str, dict[str, Any]]]:
    """Return (parent URL, record) of every published output strictly under the folder `url`."""
    fs, path = object_path(url)
    try:
        found = fs.find(path)
    except FileNotFoundError:
        return []
    protocol = url.split("://")[0]
    records = []
    for item in found:
        name = PurePosixPath(item).name
        if name.startswith(".") and name.endswith(".published.json") and f"/{STAGING_DIR}/" not in item:
            parent_url = f"{protocol}://{PurePosixPath(item).parent}"
            record = read_record(f"{parent_url}/{name[1:-len('.published.json')]}")
            if record is not None:
                records.append((parent_url, record))
    return records


def pull(path: str | os.PathLike) -> list[Path]:
    """Bring the published outputs at, under or holding `path` into the mirror; return the files fetched.

    Files already in the mirror with the record's size and sha256 are kept; shards are left in the bucket.
    ValueError naming the object when a fetched file's sha256 differs from its record.
    """
    found = root_of(path)
    if found is None:
        return []
    root, key = found
    if root.role == "input":
        return _pull_input(root, key)
    records = []
    if (covering := covering_record(url_at(root, key))) is not None:  # never the bucket itself
        records.append(covering)
    else:
        records.extend(records_under(url_at(root, key)))
    fetched = []
    for parent_url, record in records:  # a covering record may lie above the root (a root inside a published folder)
        for relative, entry in sorted(record["files"].items()):
            file_url = f"{parent_url}/{relative}"
            if not file_url.startswith(root.url + "/"):
                continue
            file_key = file_url[len(root.url) + 1:]
            if key and not (file_key == key or file_key.startswith(key + "/")):
                continue
            if any(fnmatch.fnmatch(PurePosixPath(relative).name, p) for p in STREAMED):
                continue
            local = root.mirror / file_key
            if _local_matches(local, entry):
                continue
            _download(f"{parent_url}/{relative}", local, entry)
            fetched.append(local)
    return fetched


def pulled(path: str | os.PathLike) -> Path:
    """Return `path` after pulling what is published there (a mirror path); any other path as it is."""
    pull(path)
    return Path(path)


def _local_matches(local: Path, entry: dict[str, Any]) -> bool:
    if not local.is_file() or local.stat().st_size != entry["size"]:
        return False
    return file_digest(local) == entry["sha256"]


def _download(url: str, local: Path, entry: dict[str, Any]) -> None:
    """Fetch one published object to `local` atomically; ValueError naming it when its bytes are not the record's."""
    fs, path = object_path(url)
    with atomic_path(local) as tmp:
        fs.get_file(path, str(tmp))
        digest = sha256_file(tmp)
        if digest != entry["sha256"]:
            raise ValueError(f"{url}: sha256 is {digest}, expected {entry['sha256']} from its publication record; "
                             f"the object changed after it was published; {REDO_HINT}")


def pulled_etag(path: str | os.PathLike) -> str | None:
    """Return the ETag of the object a file of an input mirror was pulled from, or None (not pulled)."""
    path = Path(path)
    state = path.parent / INPUT_STATE.format(name=path.name)
    return state.read_text() if root_of(path) is not None and state.is_file() else None


def _pull_input(root: Root, key: str) -> list[Path]:
    """Fetch the objects of an input root at or under `key` (no records: size and ETag decide what is new)."""
    fs, path = object_path(url_at(root, key))
    try:
        listing = fs.find(path, detail=True) if not fs.isfile(path) else {path: fs.info(path)}
    except FileNotFoundError:
        return []
    _, base = object_path(root.url)
    fetched = []
    for item, info in sorted(listing.items()):
        local = root.mirror / PurePosixPath(item).relative_to(base)
        state = local.parent / INPUT_STATE.format(name=local.name)
        etag = str(info.get("ETag") or info.get("etag") or info.get("md5Hash") or "")
        if local.is_file() and local.stat().st_size == info["size"] and state.is_file() and state.read_text() == etag:
            continue
        with atomic_path(local) as tmp:
            fs.get_file(item, str(tmp))
        with atomic_path(state) as tmp:
            tmp.write_text(etag)
        fetched.append(local)
    return fetched


def staging_files(url: str) -> list[str]:
    """Return every object under staging prefixes below the root `url` (for tests and the run's end check)."""
    fs, path = object_path(url)
    try:
        return sorted(p for p in fs.find(path) if f"/{STAGING_DIR}/" in f"/{p}")
    except FileNotFoundError:
        return []
