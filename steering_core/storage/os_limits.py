"""What the file system refuses, said in one line: a path part over its 255 bytes, a disk that fills up mid-write,
a read-only file system, a file over the process's size limit (`ulimit -f`), a folder this user may not write.

Names are checked before anything is written (`check_path_parts`); a write that meets a full disk (or a read-only
file system, or the file-size limit) is re-raised as `DiskFullError` naming the output it was writing, what it had
written and what the disk has free (`reraise_disk_full`), while `atomic_path` / `atomic_dir` remove the partial copy.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

NAME_MAX = 255  # bytes of one path part on Linux file systems (ext4, xfs, tmpfs, NFS)
DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
# errno of a write the device refuses -> what it refused, and what to do
WRITE_REFUSALS = {
    errno.ENOSPC: ("no space left on the device", "free some space or write elsewhere"),
    errno.EDQUOT: ("no space left on the device (disk quota exceeded)", "free some space or write elsewhere"),
    errno.EFBIG: ("file too large: over this process's file-size limit (ulimit -f) or the file system's",
                  "raise the limit (ulimit -f unlimited) or write elsewhere"),
    errno.EROFS: ("the file system is read-only", "write elsewhere, or remount it writable"),
}
_PERMISSION_ERRNOS = frozenset({errno.EACCES, errno.EPERM})
# how writers in Rust and C++ report a full disk without an OSError: safetensors' `(os error 28)`, torch.save's
# "file write failed" (PytorchStreamWriter), and the C library's text
_DISK_FULL_TEXT = re.compile(r"\(os error (28|122)\)|No space left on device|Disk quota exceeded|file write failed")
# ... and the same writers meeting the file-size limit or a read-only file system
_REFUSED_TEXT = {errno.EFBIG: re.compile(r"\(os error 27\)|File too large"),
                 errno.EROFS: re.compile(r"\(os error 30\)|Read-only file system")}
_LOW_FREE = 1 << 20  # a write failing with no errno on a file system with less than this free: the disk is full


class DiskFullError(OSError):
    """A write that ran out of disk space (or that the device refused otherwise: `number`, a key of WRITE_REFUSALS);
    str() is one line naming the output and the space."""

    def __init__(self, message: str, path: Path, number: int = errno.ENOSPC):
        super().__init__(number, message, str(path))
        self.message = message

    def __str__(self) -> str:
        return self.message


def check_path_parts(path: str | os.PathLike, what: str, *, extra: int = 0) -> Path:
    """Return `path` when each of its parts fits a file system's name (the last part with `extra` bytes added, as a
    staging name adds); ValueError naming the part, its size and the limit otherwise."""
    path = Path(path)
    parts = path.parts
    for position, part in enumerate(parts):
        size = len(os.fsencode(part))
        added = extra if position == len(parts) - 1 else 0
        if size + added > NAME_MAX:
            staged = f" ({size + added} with the {added} its staging name adds)" if added else ""
            raise ValueError(f"{what} {path}: its part {part[:40]!r}... is {size} bytes{staged}; a file system takes "
                             f"at most {NAME_MAX} bytes per name: choose a shorter name")
    return path


def check_writable_folder(path: str | os.PathLike, what: str, remedy: str) -> Path:
    """Return `path` when a file can be created in it (or, while it is missing, in its deepest existing parent, where
    it would be made); ValueError naming `what`, the folder, why and `remedy` otherwise (a read-only mount, a file in
    the way, no permission). Nothing is left behind."""
    path = Path(path)
    existing = next(p for p in (path, *path.parents) if p.exists() or p == p.parent)
    try:
        if not existing.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, f"{existing} is not a folder")
        with tempfile.TemporaryFile(dir=existing, prefix=".write-check-"):
            pass
    except OSError as err:
        raise ValueError(f"{what} {path}: not a writable folder ({err.strerror or err}); {remedy}") from None
    return path


def machine_error_line(err: BaseException) -> str | None:
    """Return one line for an error of the machine rather than of the code (a full disk, a read-only file system,
    the file-size limit, a permission refused, a name too long for the file system, memory exhausted, input nested
    past Python's recursion limit), or None for any other error."""
    if isinstance(err, DiskFullError):
        return str(err)
    if isinstance(err, OSError) and err.errno in WRITE_REFUSALS:
        where = Path(os.fsdecode(err.filename)) if err.filename else Path.cwd()
        refused, remedy = WRITE_REFUSALS[err.errno]
        free = free_bytes(where) if err.errno in DISK_FULL_ERRNOS else -1
        return f"{err.filename or 'a write'}: {refused}{'' if free < 0 else f' ({human(free)} free there)'}; {remedy}"
    if isinstance(err, OSError) and err.errno in _PERMISSION_ERRNOS and err.filename:
        return (f"{err.filename}: permission denied (this user may not open or write it); change its permissions "
                "or choose another path")
    if isinstance(err, OSError) and err.errno == errno.ENAMETOOLONG and err.filename:
        part = max(Path(os.fsdecode(err.filename)).parts, key=lambda p: len(os.fsencode(p)))
        return (f"{err.filename}: its part {part[:40]!r}... is {len(os.fsencode(part))} bytes; a file system takes "
                f"at most {NAME_MAX} bytes per name: choose a shorter name")
    if isinstance(err, MemoryError):
        detail = f" ({err})" if str(err) else ""
        return (f"out of memory{detail}: the counts or sizes given need more memory than this machine has; lower "
                "them (frames, episodes, α values, seeds, batch sizes)")
    if isinstance(err, RecursionError):
        return f"input nested too deeply to read ({err}); a config or JSON file nests its values a few levels deep"
    return None


def write_refusal(err: BaseException, where: Path) -> int | None:
    """Return the errno (a key of WRITE_REFUSALS) of the device's refusal `err` means (raised while writing under
    `where`): a full disk, the file-size limit, a read-only file system; None for any other error."""
    if isinstance(err, OSError) and err.errno is not None:
        return err.errno if err.errno in WRITE_REFUSALS else None
    if isinstance(err, (OSError, RuntimeError)) or type(err).__name__ == "SafetensorError":
        for number, text in _REFUSED_TEXT.items():
            if text.search(str(err)):
                return number
        return errno.ENOSPC if _DISK_FULL_TEXT.search(str(err)) or free_bytes(where) < _LOW_FREE else None
    return None


def free_bytes(where: Path) -> int:
    """Return the bytes free to this user on the file system of `where` (its deepest existing parent); -1 unknown."""
    for candidate in (where, *where.parents):
        if candidate.exists():
            try:
                return shutil.disk_usage(candidate).free
            except OSError:
                return -1
    return -1


def size_of(path: Path) -> int:
    """Return the bytes held by a file, or by every file under a folder (0 when gone; files vanishing meanwhile skipped)."""
    files = [path] if path.is_file() else list(path.rglob("*")) if path.is_dir() else []
    total = 0
    for file in files:
        with contextlib.suppress(OSError):
            total += file.stat().st_size if file.is_file() else 0
    return total


def human(size: int) -> str:
    """Return a byte count as `812 bytes` or `1.9 MiB`."""
    if size < 1024:
        return f"{size} bytes"
    value, units = size / 1024, ["KiB", "MiB", "GiB", "TiB"]
    while value >= 1024 and len(units) > 1:
        value, units = value / 1024, units[1:]
    return f"{value:.1f} {units[0]}"


@contextlib.contextmanager
def reraise_disk_full(path: Path, staging: Path | None = None, *, rename: bool = False) -> Iterator[None]:
    """Re-raise a full disk (or the file-size limit, or a read-only file system: `write_refusal`) met while writing
    `staging` (the partial copy of `path`; None: while preparing to write it) as `DiskFullError`; with `rename`, also
    one already raised naming a file inside `staging`."""
    try:
        yield
    except Exception as err:
        where = (staging or path).parent
        refusal = None if isinstance(err, DiskFullError) and not rename else write_refusal(err, where)
        if refusal is None:
            raise
        refused, remedy = WRITE_REFUSALS[refusal]
        if refusal in DISK_FULL_ERRNOS:
            written, free = (size_of(staging) if staging else 0), free_bytes(where)
            needed = "more space than was free" if free < 0 else f"more than the {human(free + written)} free there"
            refused = f"{refused}: writing it needs {needed}"
        raise DiskFullError(f"{path}: {refused}; nothing was kept: {remedy}", path, refusal) from None
