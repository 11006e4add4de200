"""Shard-group locks: two captures into one run folder never compute the same episode group at once.

One lock file per run folder (`.capture.lock`); each shard group is one byte of it, locked with POSIX
record locks (`fcntl.lockf`), so one open file serves any number of groups and the locks hold across
processes and hosts sharing the folder (NFS with lockd). A second capture of the same groups waits,
then finds them complete and skips them. The locks end with the process, so a killed capture never
leaves a stale lock behind.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
from collections.abc import Iterable, Iterator
from pathlib import Path

logger = logging.getLogger(__name__)

LOCK_FILE = ".capture.lock"


@contextlib.contextmanager
def group_locks(run_dir: str | os.PathLike, groups: Iterable[int]) -> Iterator[None]:
    """Hold an exclusive lock on each shard group (in ascending order, so two callers never deadlock)."""
    path = Path(run_dir) / LOCK_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as handle:  # one descriptor: closing another one on this file would drop the locks
        for group in sorted(set(groups)):
            try:
                fcntl.lockf(handle, fcntl.LOCK_EX | fcntl.LOCK_NB, 1, group)
            except OSError:
                logger.info("%s: shard group %d is being captured by another process; waiting", run_dir, group)
                fcntl.lockf(handle, fcntl.LOCK_EX, 1, group)
        try:
            yield
        finally:
            fcntl.lockf(handle, fcntl.LOCK_UN, 0, 0)
