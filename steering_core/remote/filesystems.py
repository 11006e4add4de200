"""The buckets themselves: one fsspec filesystem per protocol, object paths, write probes and single-object copies."""

from __future__ import annotations

import os
import socket
import tempfile
import threading
import uuid
from pathlib import Path, PurePosixPath
from typing import Any

from steering_core.storage.mirrors import split_url

_FILESYSTEMS: dict[str, Any] = {}
_LOCK = threading.Lock()


def filesystem(protocol: str) -> Any:
    """Return this process's fsspec filesystem for `protocol` (s3fs / gcsfs read their credentials themselves)."""
    with _LOCK:
        if protocol not in _FILESYSTEMS:
            import fsspec  # imported on first use: local runs never pay for it

            # no listings cache: other machines publish all the time, and a stale listing would hide their objects
            options = {"use_listings_cache": False} if protocol != "file" else {}
            _FILESYSTEMS[protocol] = fsspec.filesystem(protocol, **options)
        return _FILESYSTEMS[protocol]


def object_path(url: str) -> tuple[Any, str]:
    """Return (filesystem, path as that filesystem names it) of an object URL."""
    protocol, path = split_url(url)
    return filesystem(protocol), path


def check_writable(url: str) -> str:
    """Return `url` once a probe object was written and deleted under it from this machine; ValueError in one
    line naming the URL otherwise (no bucket, no credentials, no endpoint: whatever the cause, runs could not write)."""
    fs, probe = object_path(f"{url}/.probe-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex}")
    try:
        fs.pipe_file(probe, b"latent-steering: write probe\n")
        fs.rm_file(probe)
    except Exception as err:  # noqa: BLE001  reported in one line
        reason = " ".join(f"{type(err).__name__}: {err}".split())
        raise ValueError(f"{url}: not writable from this machine ({reason}); check the URL and the AWS_* / "
                         "GOOGLE_APPLICATION_CREDENTIALS settings of this environment") from None
    return url


def temporary_copy(url: str) -> Path:
    """Return a local temporary copy of the single object `url` (a run config handed to another machine)."""
    fs, path = object_path(url)
    folder = Path(tempfile.mkdtemp(prefix="latent-steering-"))
    local = folder / PurePosixPath(path).name
    fs.get_file(path, str(local))
    return local
