"""Locks on outputs: two runs sharing an output root never compute the same thing at once.

Capture locks each shard group of a run folder (`group_locks`): one lock file per run folder
(`.capture.lock`), each group one byte of it. Every other step locks the output it writes
(`output_lock`: a dataset folder, a slices layer folder, a steering layer folder, a manifest file),
through byte 0 of a lock file beside it (`.<name>.lock`, beside and not inside, because a finished
output folder is swapped in by rename and a lock inside would lock the old copy). The caller then
re-checks, under the lock, whether the work is already done, so a second run waits and then skips.

The locks are POSIX record locks (`fcntl.lockf`): one open file serves any number of bytes, they hold
across processes and hosts sharing the folder (NFS with lockd), and they end with the process, so a
killed step never leaves a stale lock behind. They do not exclude threads of one process.
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
OUTPUT_LOCK = ".{name}.lock"


@contextlib.contextmanager
def group_locks(run_dir: str | os.PathLike, groups: Iterable[int], lock_file: str = LOCK_FILE,
                what: str = "shard group") -> Iterator[None]:
    """Hold an exclusive lock on each group (byte) of `run_dir/lock_file`, in ascending order, so two callers never deadlock."""
    path = Path(run_dir) / lock_file
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+b") as handle:  # one descriptor: closing another one on this file would drop the locks
        for group in sorted(set(groups)):
            try:
                fcntl.lockf(handle, fcntl.LOCK_EX | fcntl.LOCK_NB, 1, group)
            except OSError:
                logger.info("%s: %s %d is being written by another process; waiting", run_dir, what, group)
                fcntl.lockf(handle, fcntl.LOCK_EX, 1, group)
        try:
            yield
        finally:
            fcntl.lockf(handle, fcntl.LOCK_UN, 0, 0)


@contextlib.contextmanager
def output_lock(output: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive lock on the output file or folder `output` (its lock file sits beside it).

    If the block leaves no `output` (a step that failed, e.g. on bad input), the lock file and the folders
    made for it are removed again, so nothing is left behind. (A process already waiting on that lock then
    holds a removed file: a third one could run beside it; the outputs stay whole, written by renames.)
    """
    output = Path(output)
    folder = output.parent
    made = [p for p in (folder, *folder.parents) if not p.exists()]  # deepest first
    lock = folder / OUTPUT_LOCK.format(name=output.name)
    try:
        with group_locks(folder, [0], lock.name, what=f"output {output.name}, lock"):
            yield
    finally:
        if not output.exists() and not output.is_symlink():
            lock.unlink(missing_ok=True)
            for path in made:
                with contextlib.suppress(OSError):  # not empty: another step wrote there meanwhile
                    path.rmdir()
