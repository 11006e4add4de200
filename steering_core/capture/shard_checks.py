"""Checking the shards a slicing reads against their records, so that no damaged shard feeds a slice.

The copy reads each checked shard whole, front to back, once, and feeds its bytes to a digest
(`ShardChecks.digest`): the check then costs a CRC-32 of bytes already in the cache, not a second read.
A shard the copy did not finish (it failed to open, say) is hashed from its file when the check is
asked for, so a damaged shard is named as changed whatever error its damage caused first.
A shard read by ranges from a bucket (absent here under a mounted URL root) is not checked here: a
CRC-32 would fetch all of it. Its identity check is its object's size and ETag against its publication
record, made when slicing's first pass opens it (`tensor_files.readable`).
"""

from __future__ import annotations

import contextlib
import hashlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Protocol

from steering_core.capture.shards import ShardRecord, checksum_mismatch
from steering_core.storage.fileio import Crc32, feed_file
from steering_core.storage.mirrors import url_of


class Digest(Protocol):
    """What a shard check feeds bytes to: hashlib's `update` / `hexdigest`."""

    def update(self, data: bytes | memoryview, /) -> None: ...

    def hexdigest(self) -> str: ...


def record_check(record: ShardRecord) -> tuple[str, Callable[[], Digest], str]:
    """Return (name, new digest, expected hex digest) of a record's check: its CRC-32, or its sha256 for
    records written before CRC-32s were kept (about 10x slower)."""
    if record.crc32 is not None:
        return "CRC-32", Crc32, f"{record.crc32:08x}"
    return "sha256", hashlib.sha256, record.sha256


class ShardChecks:
    """The checks of the local shards at `positions` of `records` (none when not `enabled`)."""

    def __init__(self, run_dir: Path, records: Sequence[ShardRecord], positions: Sequence[int], enabled: bool) -> None:
        paths = {p: run_dir / records[p].file for p in positions} if enabled else {}
        self._paths = {p: path for p, path in paths.items() if not _in_bucket(path)}
        self._checks = {p: record_check(records[p]) for p in self._paths}
        self._found: dict[int, str] = {}

    def digest(self, position: int) -> Digest | None:
        """Return a new digest for the shard at `position` to be fed its whole file, or None if it is not checked."""
        return self._checks[position][1]() if position in self._checks else None

    def found(self, position: int, digest: Digest) -> None:
        """Keep the digest of the shard at `position`, fed every byte of its file."""
        self._found[position] = digest.hexdigest()

    def mismatches(self) -> list[str]:
        """Return one message per checked shard whose bytes differ from its record; unfed shards are hashed here."""
        problems = []
        for position, path in self._paths.items():
            kind, new_digest, expected = self._checks[position]
            with contextlib.suppress(OSError):  # a missing shard: the read that needed it says so
                found = self._found.get(position) or _file_digest(path, new_digest())
                if found != expected:
                    problems.append(checksum_mismatch(path, kind, found, expected))
        return problems

    def check(self) -> None:
        """Raise a ValueError listing every changed shard."""
        if problems := self.mismatches():
            raise ValueError("\n".join(problems))

    @contextlib.contextmanager
    def blame(self) -> Iterator[None]:
        """Report an error in the block caused by a changed shard (a damaged header, say) as the mismatch it is."""
        try:
            yield
        except Exception:
            if problems := self.mismatches():
                raise ValueError("\n".join(problems)) from None
            raise


def _in_bucket(path: Path) -> bool:
    """Return whether a shard is read by ranges from a bucket: absent here, under a mounted URL root."""
    return url_of(path) is not None and not path.exists()


def _file_digest(path: Path, digest: Digest) -> str:
    """Return the hex digest of a file's bytes."""
    feed_file(path, digest)
    return digest.hexdigest()
