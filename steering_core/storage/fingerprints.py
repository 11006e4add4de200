"""Identity of a step's output: content fingerprints of its inputs and the version of the code that computes it.

Equal identity, equal outputs. A step's code version is the hash of the source of the `steering_core`
modules it calls, followed through their imports (read, never imported); its inputs count by content
(file hashes, settings by their JSON). `tasks.cache` turns these into Prefect cache keys.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import json
import logging
import os
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from steering_core.storage.fileio import sha256_file, sha256_json, write_json
from steering_core.storage.publish import pulled_etag

PROJECT_PACKAGES = ("steering_core",)  # imports followed when versioning code
_PROJECT_ROOT = Path(__file__).resolve().parents[2]  # the folder holding steering_core/

logger = logging.getLogger(__name__)


DIGEST_CACHE_ENV = "LATENT_STEERING_DIGEST_CACHE"  # folder remembering large files' digests across processes
STORED_DIGEST_MIN_SIZE = 16 << 20  # smaller files are re-hashed faster than a stored digest is looked up
_DIGESTS: dict[tuple, str] = {}
_HEX = frozenset("0123456789abcdef")


def file_digest(path: str | os.PathLike) -> str:
    """Return the sha256 of a file's whole content, computed once per file version.

    A version is (path, size, mtime_ns, ctime_ns, device, inode): a rewrite in place moves mtime/ctime,
    a rename into place moves the inode. Digests of large files (a 7 GB checkpoint) are also stored in
    `digest_cache_dir()`, so each version is read once, not once per process.
    """
    path = Path(path).resolve()
    stat = path.stat()
    version = (str(path), stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_dev, stat.st_ino)
    if version not in _DIGESTS:
        stored = _stored_digest(version) if stat.st_size >= STORED_DIGEST_MIN_SIZE else None
        _DIGESTS[version] = stored or sha256_file(path)
        if stored is None and stat.st_size >= STORED_DIGEST_MIN_SIZE:
            _store_digest(version, _DIGESTS[version])
    return _DIGESTS[version]


def digest_cache_dir() -> Path:
    """Return where large files' digests are remembered: $LATENT_STEERING_DIGEST_CACHE or the user cache."""
    if folder := os.environ.get(DIGEST_CACHE_ENV):
        return Path(folder)
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "latent-steering" / "digests"


def _digest_entry(version: tuple) -> Path:
    return digest_cache_dir() / f"{sha256_json(list(version))}.json"


def _stored_digest(version: tuple) -> str | None:
    """Return the stored digest of a file version, or None (absent, unreadable or not for this version)."""
    try:
        entry = json.loads(_digest_entry(version).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    digest = entry.get("sha256") if isinstance(entry, dict) else None
    if entry.get("version") != list(version) or not isinstance(digest, str) or len(digest) != 64 or set(digest) - _HEX:
        return None
    return digest


def _store_digest(version: tuple, digest: str) -> None:
    """Remember a file version's digest; a cache folder that cannot be written only costs a re-hash later."""
    try:
        write_json(_digest_entry(version), {"version": list(version), "sha256": digest})
    except OSError as err:
        logger.debug("digest of %s not stored (%s)", version[0], err)


def tree_listing(folders: Iterable[str | os.PathLike], pattern: str = "*.hdf5") -> list[tuple[str, int, int | str]]:
    """Return (path, size, mtime_ns) of each file matching `pattern` directly in the folders: a cheap fingerprint.

    Used where hashing every candidate would be costly and a later step hashes what it selects. A file pulled
    from object storage counts by its object's ETag instead of its mtime, which differs on every machine.
    """
    listing = []
    for folder in folders:
        for path in sorted(Path(folder).glob(pattern)):
            stat = path.stat()
            listing.append((str(path.resolve()), stat.st_size, pulled_etag(path) or stat.st_mtime_ns))
    return listing


def plain(value: Any) -> Any:
    """Return `value` as JSON-ready data for hashing: settings models by content, paths as text."""
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


@functools.cache
def _module_file(name: str) -> Path | None:
    """Return the source file of project module `name` (found by path, never imported), or None if not a module."""
    top = name.split(".")[0]
    if top not in PROJECT_PACKAGES:
        return None
    base = _PROJECT_ROOT.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _project_imports(name: str, path: Path) -> set[str]:
    """Return the project modules imported by the module `name` stored at `path`."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            found.add(base)
            # `from pkg import submodule` imports a module too
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return {m for m in found if _module_file(m) is not None}


_AST_LOCK = threading.Lock()  # CPython 3.11's ast.parse is not safe in concurrent threads (recursion-depth check)


@functools.cache
def code_version(*modules: str) -> str:
    """Return the sha256 of the source of `modules` and every project module they import, transitively."""
    return sha256_json(code_modules(*modules))


def code_modules(*modules: str) -> dict[str, str]:
    """Return module name -> sha256 of its source for `modules` and every project module they import."""
    with _AST_LOCK:
        return _code_modules(modules)


def _code_modules(modules: tuple[str, ...]) -> dict[str, str]:
    seen: dict[str, str] = {}
    pending = list(modules)
    while pending:
        name = pending.pop()
        if name in seen:
            continue
        path = _module_file(name)
        if path is None:
            raise ValueError(f"code_version: module {name!r} has no Python source file; expected a steering_core module")
        seen[name] = hashlib.sha256(path.read_bytes()).hexdigest()
        pending.extend(_project_imports(name, path) - seen.keys())
    return dict(sorted(seen.items()))
