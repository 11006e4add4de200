"""Ranged reads of published objects: a shard stays in the bucket and is read one range per read, after its size
and ETag are checked against its publication record (`remote_file`)."""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from steering_core.remote.filesystems import object_path
from steering_core.remote.publish import REDO_HINT, covering_record, url_at
from steering_core.storage.mirrors import root_of


class Fetched:
    """Bytes fetched by ranged reads in this process (the slicing benchmark reads it)."""

    _lock = threading.Lock()
    total = 0

    @classmethod
    def add(cls, count: int) -> None:
        with cls._lock:
            cls.total += count


@dataclass(frozen=True)
class RemoteFile:
    """A published object read by ranges: its URL and size, checked against its record."""

    url: str
    size: int
    sha256: str | None = None  # from the publication record (None for an input's object, which has none)

    def open(self) -> BinaryIO:
        """Return a binary file reading the object with one ranged GET per read (no read-ahead)."""
        fs, path = object_path(self.url)
        return _Counted(fs.open(path, "rb", cache_type="none", block_size=1 << 20, size=self.size))


class _Counted:
    """A file object counting the bytes it reads into `Fetched` (seek, tell, read, readinto, close)."""

    def __init__(self, handle: Any) -> None:
        self._handle = handle

    def read(self, size: int = -1) -> bytes:
        data = self._handle.read(size)
        Fetched.add(len(data))
        return data

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        data = self._handle.read(len(view))
        view[: len(data)] = data
        Fetched.add(len(data))
        return len(data)

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._handle.seek(offset, whence)

    def tell(self) -> int:
        return self._handle.tell()

    def close(self) -> None:
        self._handle.close()

    def __enter__(self) -> _Counted:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def remote_file(path: str | os.PathLike) -> RemoteFile | None:
    """Return the published object standing for a local path that is absent from the mirror, else None.

    ValueError naming the object when it is missing, or its size or ETag differs from its publication record.
    """
    path = Path(os.path.abspath(path))
    found = root_of(path)
    if found is None or path.exists():
        return None
    root, key = found
    url = url_at(root, key)
    covering = covering_record(url) if root.role == "output" else None
    fs, object_key = object_path(url)
    try:
        info = fs.info(object_key)
    except FileNotFoundError:
        if covering is None:
            return None
        raise FileNotFoundError(f"{url}: listed by its publication record but missing from the bucket; {REDO_HINT}"
                                ) from None
    if covering is not None:
        parent_url, record = covering
        entry = record["files"].get(url[len(parent_url) + 1:])
        if entry is None:
            return None
        if info["size"] != entry["size"] or info.get("ETag") != entry.get("etag"):
            raise ValueError(f"{url}: size {info['size']}, ETag {info.get('ETag')} differ from its publication record "
                             f"(size {entry['size']}, ETag {entry.get('etag')}); the object changed after it was "
                             f"published; {REDO_HINT}")
    elif root.role == "output":
        return None  # written but never published: invisible
    return RemoteFile(url, int(info["size"]), entry["sha256"] if covering is not None else None)
