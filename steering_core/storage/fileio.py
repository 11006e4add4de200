"""Atomic writes, hashing and strict JSON reading shared by every step.

Every output is written to a sibling temporary name and renamed into place, so a
crash never leaves a half-written file where a reader (or a resume) would trust it.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import glob
import hashlib
import json
import math
import os
import shutil
import socket
import stat
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from isal.isal_zlib import crc32  # zlib's CRC-32, same values, by carry-less multiply: ~8x zlib's speed

from steering_core.storage.mirrors import localize, portable
from steering_core.storage.os_limits import check_path_parts, reraise_disk_full

_HASH_CHUNK = 1 << 20  # 1 MiB reads keep hashing fast without holding whole files


def _umask() -> int:
    """Return the process umask without setting it: `os.umask` changes it process-wide, racing threads that create files."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():  # Linux 4.7+
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    with tempfile.TemporaryDirectory() as folder:  # elsewhere: the mode a new file gets is the answer
        probe = os.path.join(folder, "probe")
        os.close(os.open(probe, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o777))
        return 0o777 & ~os.stat(probe).st_mode & 0o777


def _share(path: Path, umask: int) -> None:
    """Give `path` the mode a plain `open()`/`mkdir()` would (0666/0777 less the umask; executables keep x)."""
    mode = os.lstat(path).st_mode
    if stat.S_ISLNK(mode):
        return
    full = 0o777 if stat.S_ISDIR(mode) or mode & 0o111 else 0o666
    os.chmod(path, full & ~umask)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling path; rename it onto `path` only if the block succeeds."""
    path = check_path_parts(path, "output", extra=staging_extra())
    with reraise_disk_full(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_staging(path)
        fd, tmp = tempfile.mkstemp(prefix=_staging_prefix(path), suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        with reraise_disk_full(path, tmp_path):
            yield tmp_path
        _share(tmp_path, _umask())  # mkstemp (and some writers, like safetensors) make 0600; outputs are shared
        os.replace(tmp_path, path)
    finally:
        tmp_path.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling folder; move it to `path` only if the block succeeds.

    The yielded folder does not exist yet (some writers, like LeRobotDataset.create,
    insist on creating it themselves). With `overwrite`, an existing `path` is replaced
    only after the new folder is complete, by one atomic exchange where the file system
    supports it (Linux renameat2); elsewhere by two renames, undone if the second fails
    and finished by the next call if the process dies between them.
    """
    path = check_path_parts(path, "output", extra=staging_extra())
    remove_stale_staging(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists; remove it or pass overwrite=True")
    with reraise_disk_full(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=_staging_prefix(path), suffix=".tmp", dir=path.parent))
    tmp_path = staging / path.name
    try:
        with reraise_disk_full(path, tmp_path):
            yield tmp_path
        umask = _umask()
        for folder, _, names in os.walk(tmp_path):
            _share(Path(folder), umask)
            for name in names:
                _share(Path(folder) / name, umask)
        if not path.exists() or not _exchange(tmp_path, path):  # after an exchange, tmp_path holds the old copy
            _swap_by_renames(tmp_path, path, staging / f"{path.name}{_OLD}")
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@contextlib.contextmanager
def atomic_files(folder: str | os.PathLike) -> Iterator[Path]:
    """Yield a staging folder for the files of one output in `folder`; move them all there only if the block succeeds.

    A failure at any file (a full disk at the third of four) leaves none of them: the moves at the end are renames
    within one file system, which need no space. A full disk is reported naming `folder`.
    """
    folder = check_path_parts(folder, "output", extra=staging_extra())
    made = not folder.exists()
    with reraise_disk_full(folder):
        folder.mkdir(parents=True, exist_ok=True)
        remove_stale_staging(folder / _FILES)
        staging = Path(tempfile.mkdtemp(prefix=_staging_prefix(folder / _FILES), suffix=".tmp", dir=folder))
    try:
        with reraise_disk_full(folder, staging, rename=True):
            yield staging
        umask = _umask()
        for name in sorted(os.listdir(staging)):
            _share(staging / name, umask)
            os.replace(staging / name, folder / name)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if made:
            with contextlib.suppress(OSError):  # the folder made for these files: not left empty
                folder.rmdir()
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)


@contextlib.contextmanager
def restored_on_failure(folder: str | os.PathLike) -> Iterator[None]:
    """Run the block; if it fails, put `folder` back as it was before (gone when it did not exist), so a step that
    writes many files into it keeps none of them.

    The previous copy is a tree of hard links (no data copied) in a staging folder beside `folder`; the writers
    replace files by renames, never in place, so the links keep the previous bytes.
    """
    folder = Path(folder)
    remove_stale_staging(folder)
    backup = None
    if folder.is_dir():
        staging = Path(tempfile.mkdtemp(prefix=_staging_prefix(folder), suffix=".tmp", dir=folder.parent))
        backup = Path(shutil.copytree(folder, staging / f"{folder.name}{_OLD}", symlinks=True, copy_function=_link))
    try:
        yield
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        if backup is not None:
            os.replace(backup, folder)
        raise
    finally:
        if backup is not None:
            shutil.rmtree(backup.parent, ignore_errors=True)


def _link(source: str, target: str) -> None:
    """Hard-link `source` at `target` (a copy where the file system has no hard links)."""
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


_FILES = ".files"  # the name of `atomic_files`' staging folders in the folder they fill
_OLD = ".old"  # inside a staging folder: the previous copy of the target while two renames swap them
_RENAME_EXCHANGE, _AT_FDCWD = 2, -100  # linux/fs.h, fcntl.h
_LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None


def _exchange(new: Path, target: Path) -> bool:
    """Swap two existing paths atomically (renameat2 RENAME_EXCHANGE); False where unsupported."""
    renameat2 = getattr(_LIBC, "renameat2", None)
    if renameat2 is None:
        return False
    if renameat2(_AT_FDCWD, os.fsencode(new), _AT_FDCWD, os.fsencode(target), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):  # file system or kernel without exchange
        return False
    raise OSError(code, os.strerror(code), str(target))


def _swap_by_renames(new: Path, target: Path, old: Path) -> None:
    """Move `target` aside to `old`, then `new` into place; put `target` back if the second rename fails."""
    if target.exists():
        os.replace(target, old)
    try:
        os.replace(new, target)
    except BaseException:
        if old.exists():
            os.replace(old, target)
        raise


def staging_extra() -> int:
    """Return the bytes a staging name adds to its target's: the prefix's, mkstemp's 8 random characters, `.tmp`."""
    return len(os.fsencode(_staging_prefix(Path()))) + 8 + len(".tmp")


def _staging_prefix(path: Path) -> str:
    """Return the name prefix of a staging file or folder for `path`: it names this host and process."""
    return f".{path.name}.{socket.gethostname()}-{os.getpid()}."


def remove_stale_staging(path: str | os.PathLike) -> list[Path]:
    """Remove the staging files and folders for `path` left by dead processes of this host; return them.

    A staging folder holding the previous copy (`<name>.old`) while the target is missing is a swap
    interrupted between its two renames: the previous copy is put back first. Staging of live processes,
    or of other hosts (whose processes cannot be checked from here), is left alone.
    """
    path = Path(path)
    host = socket.gethostname()
    removed = []
    for candidate in path.parent.glob(f".{glob.escape(path.name)}.{glob.escape(host)}-*.tmp"):
        pid = candidate.name[len(f".{path.name}.{host}-"):].split(".")[0]
        if not pid.isdigit() or _alive(int(pid)):
            continue
        if candidate.is_dir() and not candidate.is_symlink():
            old = candidate / f"{path.name}{_OLD}"
            if old.exists() and not path.exists():
                os.replace(old, path)
            shutil.rmtree(candidate, ignore_errors=True)
        else:
            candidate.unlink(missing_ok=True)
        removed.append(candidate)
    return removed


def _alive(pid: int) -> bool:
    """Return True if a process with this id runs on this host (or cannot be checked)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # e.g. another user's process
        return True
    return True


def check_output_dir(path: str | os.PathLike, what: str = "output folder") -> Path:
    """Return `path` after checking that a folder can be made or used there; ValueError naming the culprit.

    Refused: `path` or one of its parents is a file, or the deepest existing parent is not writable.
    Nothing is created, so a check before hours of work leaves no trace.
    """
    path = check_path_parts(Path(path).absolute(), f"the {what}", extra=staging_extra())
    for candidate in (path, *path.parents):
        if candidate.exists() or candidate.is_symlink():
            if not candidate.is_dir():
                where = "" if candidate == path else f" (a parent of the {what} {path})"
                raise ValueError(f"{candidate}: is a file{where}; expected a folder, or nothing there")
            if not os.access(candidate, os.W_OK | os.X_OK):
                raise ValueError(f"{candidate}: folder not writable; the {what} {path} cannot be written there")
            return path
    return path


def write_json(path: str | os.PathLike, payload: Any) -> Path:
    """Write `payload` as indented JSON atomically; return the path. Mirror paths are written as URLs.

    NaN and Inf are refused (JSON has neither; Python would write bare `NaN`), naming the key; nothing is written.
    """
    path = Path(path)
    text = json_text(payload, path)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def json_text(payload: Any, path: str | os.PathLike) -> str:
    """Return the text `write_json` writes for `payload`; ValueError naming `path` and the key of a NaN or Inf."""
    payload = portable(payload)  # paths in object-storage mirrors are written as their URLs
    try:
        return json.dumps(payload, indent=2, ensure_ascii=False, allow_nan=False) + "\n"
    except ValueError:
        key = non_finite_key(payload)
        if key is None:
            raise
        raise ValueError(f"{path}: `{key}` is NaN or Inf, which JSON cannot hold; nothing was written") from None


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 `text` atomically (a report: Markdown, HTML); return the path. Mirror paths are written as URLs."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(portable(text), encoding="utf-8")
    return path


def non_finite_key(payload: Any, where: str = "") -> str | None:
    """Return the dotted key (list items by index) of the first NaN or Inf number in `payload`, else None."""
    if isinstance(payload, float) and not math.isfinite(payload):
        return where or "(the whole value)"
    items = payload.items() if isinstance(payload, dict) else enumerate(payload) if isinstance(payload, list | tuple) else ()
    for key, value in items:
        found = non_finite_key(value, f"{where}.{key}" if where else str(key))
        if found is not None:
            return found
    return None


def read_text(path: str | os.PathLike, what: str) -> str:
    """Return the UTF-8 text of `path`; ValueError naming the file when it is binary (`what`: what it should hold)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    data = path.read_bytes()
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not a text file (byte {err.start} is not UTF-8); expected {what}") from None


class DuplicateKeyError(ValueError):
    """A mapping that names one key twice (JSON or YAML would silently keep the last)."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """Return the JSON object of `pairs`; DuplicateKeyError when a key appears twice."""
    found: dict[str, Any] = {}
    for key, value in pairs:
        if key in found:
            raise DuplicateKeyError(f"key {key!r} appears twice in one object")
        found[key] = value
    return found


def read_json(path: str | os.PathLike) -> Any:
    """Return the parsed JSON of `path`, with errors that name the file (binary, malformed, a key given twice)."""
    return parse_json(read_text(path, "a JSON file"), str(path))


def parse_json(text: str, where: str) -> Any:
    """Return the parsed JSON `text`; ValueError starting with `where` when malformed or a key is given twice.

    URLs of mounted object-storage roots are read as their mirror paths on this machine (`write_json` undone).
    """
    try:
        return localize(json.loads(text, object_pairs_hook=_unique_keys))
    except json.JSONDecodeError as err:
        raise ValueError(f"{where}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    except DuplicateKeyError as err:
        raise ValueError(f"{where}: {err}; keep one") from None
    except RecursionError:  # the C decoder stops at Python's recursion limit (about 1,000 levels) by itself
        raise ValueError(f"{where}: values nested too deeply to read (past Python's recursion limit); expected JSON "
                         "nesting a few levels") from None


def sha256_file(path: str | os.PathLike) -> str:
    """Return the hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    feed_file(path, digest)
    return digest.hexdigest()


def feed_file(path: str | os.PathLike, *digests: Any) -> None:
    """Feed a file's bytes, in 1 MiB chunks read once, to each of `digests` (hashlib-like: `update`)."""
    with open(path, "rb") as handle:
        while chunk := handle.read(_HASH_CHUNK):
            for digest in digests:
                digest.update(chunk)


class Crc32:
    """A running CRC-32 (zlib's) with hashlib's `update` / `hexdigest`; `value` is the checksum so far."""

    def __init__(self) -> None:
        self.value = 0

    def update(self, data: bytes | memoryview, /) -> None:
        """Extend the checksum by `data`."""
        self.value = crc32(data, self.value)

    def hexdigest(self) -> str:
        """Return the checksum as 8 hex digits."""
        return f"{self.value:08x}"


def sha256_json(payload: Any) -> str:
    """Return the hex sha256 of `payload` serialised canonically (sorted keys, no spaces); mirror paths count by
    their URLs, so an identity is the same on every machine."""
    text = json.dumps(portable(payload), sort_keys=True, separators=(",", ":"), ensure_ascii=False, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()
