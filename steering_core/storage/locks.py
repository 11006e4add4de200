"""Locks on outputs: two runs sharing an output root never compute the same thing at once.

Every step locks the output it writes (`local_output_lock`: a dataset folder, a slices layer folder, a steering
layer folder, a statistics file, an evaluation folder) through a lock file beside it (`.<name>.lock`, beside
and not inside, because a finished output folder is swapped in by rename and a lock inside would lock the
old copy). Capture locks each shard group of a run folder (`local_group_locks`): one lock file per group
(`.capture-<group>.lock` in the run folder). The caller then re-checks, under the lock, whether the work is
already done, so a second run waits and then skips.

Each lock is a `flock` on its own open lock file. It belongs to that open file, not to the process: it
excludes threads as well as processes, and the kernel never refuses a wait with EDEADLK. (POSIX record
locks, `fcntl.lockf`, belong to the process, so two processes whose threads waited on each other's locks
looked like a cycle and one wait failed with "Resource deadlock avoided".) Nothing detects a real cycle
either, so none can form: locks are taken in one global order, by output path (a folder before what it
holds, a run folder's groups by number), a call taking several takes them in that order, and a thread
asking for a lock that does not come after every lock it holds gets a RuntimeError instead of a wait.

Steps take these through `steering_core.remote.locks`, whose `output_lock` and `group_locks` add, on an output
root in object storage, the bucket-wide lock object of the output after the local one, so machines without a
shared disk exclude each other too.

A lock ends when its file is closed, at the latest with the process (forked children close their copies),
so a killed step never leaves a stale lock. Group lock files, and an output's lock file when the block
wrote no output, are removed by their holder before it lets go; a process that was waiting on the removed
file sees that the path no longer names it and locks the path afresh.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from steering_core.storage.fileio import staging_extra
from steering_core.storage.os_limits import check_path_parts

logger = logging.getLogger(__name__)

GROUP_LOCK = ".capture-{group}.lock"
OUTPUT_LOCK = ".{name}.lock"

Order = tuple[tuple[str, ...], int]  # (output path parts, group or -1): the global order of locks

_local = threading.local()  # `held`: this thread's locks, [(order, description)], in ascending order
_descriptors: set[int] = set()  # every descriptor holding a lock, closed in a forked child


def _close_in_child() -> None:
    """In a forked child: close the copies of the parent's lock descriptors (the parent keeps its locks)."""
    global _local
    for fd in _descriptors:
        with contextlib.suppress(OSError):
            os.close(fd)
    _descriptors.clear()
    _local = threading.local()


os.register_at_fork(after_in_child=_close_in_child)


def order(output: str | os.PathLike, group: int = -1) -> Order:
    """Return the place of the lock on `output` (or on one of its shard groups) in the global lock order."""
    return Path(os.path.abspath(output)).parts, group


@contextlib.contextmanager
def local_group_locks(run_dir: str | os.PathLike, groups: Iterable[int]) -> Iterator[None]:
    """Hold an exclusive lock on each shard group of `run_dir`, in ascending order; the lock files go on exit."""
    run_dir = Path(run_dir)
    made = _missing_folders(run_dir)
    locks = [(order(run_dir, group), run_dir / GROUP_LOCK.format(group=group), f"{run_dir}: shard group {group}")
             for group in set(groups)]
    try:
        with _holding(locks, keep=lambda: False):
            yield
    finally:  # a capture that wrote nothing (it failed at once, e.g. on a full disk) leaves no empty run folder
        _remove_empty(made)


@contextlib.contextmanager
def local_output_lock(output: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive lock on the output file or folder `output` (its lock file sits beside it).

    If the block leaves no `output` (a step that failed, e.g. on bad input), the lock file and the folders
    made for it are removed again, so nothing is left behind.
    """
    output = check_path_parts(output, "output", extra=staging_extra())  # before any folder is made for it
    folder = output.parent
    made = _missing_folders(folder)
    lock = (order(output), folder / OUTPUT_LOCK.format(name=output.name), f"{folder}: output {output.name}")
    try:
        with _holding([lock], keep=lambda: output.exists() or output.is_symlink()):
            yield
    finally:
        if not output.exists() and not output.is_symlink():
            _remove_empty(made)


def _missing_folders(folder: Path) -> list[Path]:
    """Return `folder` and those of its parents that do not exist yet, deepest first."""
    return [path for path in (folder, *folder.parents) if not path.exists()]


def _remove_empty(folders: list[Path]) -> None:
    """Remove each of `folders` (deepest first) that is empty."""
    for path in folders:
        with contextlib.suppress(OSError):  # not empty: a step wrote there meanwhile
            path.rmdir()


@contextlib.contextmanager
def _holding(locks: list[tuple[Order, Path, str]], keep: Callable[[], bool]) -> Iterator[None]:
    """Hold every lock (order, lock file, description) in ascending order; on exit remove the lock files
    unless `keep()`, then let go."""
    held = _local.__dict__.setdefault("held", [])
    locks = sorted(locks)
    if held and locks and locks[0][0] <= held[-1][0]:
        raise RuntimeError(f"lock order: {locks[0][2]} requested while holding {held[-1][1]}, which does not come "
                           "before it; take locks in path order (a folder before what it holds), several in one call")
    taken: list[tuple[int, Path]] = []
    try:
        for key, path, what in locks:
            taken.append((_acquire(path, what), path))
            held.append((key, what))
        yield
    finally:
        remove = not keep()
        for fd, path in reversed(taken):
            held.pop()
            try:
                if remove:  # while still held: a process waiting on this file then sees it is gone
                    path.unlink(missing_ok=True)
            finally:
                _descriptors.discard(fd)
                os.close(fd)  # the lock ends with its last descriptor


def _acquire(path: Path, what: str) -> int:
    """Return a descriptor holding an exclusive flock on the lock file `path` (made, with its folders, if missing)."""
    while True:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except FileNotFoundError:  # its folder was removed meanwhile by a holder that wrote nothing
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                logger.info("%s is being written by another process; waiting", what)
                fcntl.flock(fd, fcntl.LOCK_EX)
            if _names(path, fd):
                _descriptors.add(fd)
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)  # its holder removed the file: lock the path afresh


def _names(path: Path, fd: int) -> bool:
    """Return True if `path` still names the file open as `fd`."""
    try:
        current = os.stat(path)
    except FileNotFoundError:
        return False
    opened = os.fstat(fd)
    return (current.st_dev, current.st_ino) == (opened.st_dev, opened.st_ino)
