"""Digests of whole files, computed once per file version and, for large files, remembered across processes."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from steering_core.storage.fileio import sha256_file, sha256_json, write_json

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
