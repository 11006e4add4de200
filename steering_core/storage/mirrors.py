"""Object-storage roots (`s3://`, `gs://`, `file://`): each mounted as a local mirror folder of this machine.

Every step keeps working on local paths. A URL root given to a run config or the CLI is *mounted*: it gets a
mirror folder on this machine (`$LATENT_STEERING_MIRROR`, else `~/.cache/latent-steering/roots`, then
`<protocol>/<bucket>/<prefix>`), and `steering_core.remote.publish` moves outputs between mirror and bucket:
a step pulls the published outputs it reads, and publishes what it wrote. Shards are never pulled: readers
open them from the bucket with ranged reads (`remote_file`).

Endpoints and credentials come only from the standard environment and configuration files, as boto and s3fs
read them (`AWS_ENDPOINT_URL`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_PROFILE`, `~/.aws/config`;
for gs, gcsfs's `GOOGLE_APPLICATION_CREDENTIALS`), never from a run config: MinIO or any S3-compatible store
works by setting `AWS_ENDPOINT_URL`. Nothing here is used when no URL is mounted.
"""

from __future__ import annotations

import os
import re
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

MIRROR_ENV = "LATENT_STEERING_MIRROR"  # folder of this machine's mirrors of URL roots
PROTOCOLS = ("s3", "gs", "file")
_URL = re.compile(r"^(?P<protocol>[A-Za-z][A-Za-z0-9+.-]+)://(?P<rest>.*)$")


@dataclass(frozen=True)
class Root:
    """A mounted URL root: its URL (no trailing `/`), its mirror folder here, and whether steps write under it."""

    url: str
    mirror: Path
    role: str  # "output": published by our steps (records required) | "input": objects a user put there


_ROOTS: dict[str, Root] = {}  # url -> root, in this process
_LOCK = threading.Lock()


def is_url(value: Any) -> bool:
    """Return True if `value` is a `scheme://...` text (a URL root), not a local path."""
    return isinstance(value, (str, os.PathLike)) and _URL.match(os.fspath(value)) is not None


def split_url(url: str) -> tuple[str, str]:
    """Return (protocol, path without protocol and trailing `/`) of a URL; ValueError naming what is accepted."""
    match = _URL.match(url)
    protocol = match.group("protocol").lower() if match else ""
    path = match.group("rest").rstrip("/") if match else ""
    if protocol not in PROTOCOLS:
        raise ValueError(f"{url!r}: unsupported storage URL; expected a local path, file://, s3:// or gs://")
    parts = PurePosixPath(path).parts if protocol != "file" else ()
    if protocol != "file" and (not path or any(p in (".", "..") for p in parts) or "//" in path):
        raise ValueError(f"{url!r}: unsupported storage URL; expected {protocol}://<bucket>[/<prefix>] without empty, "
                         "`.` or `..` parts")
    return protocol, path


def mirror_base() -> Path:
    """Return the folder holding this machine's mirrors: $LATENT_STEERING_MIRROR or the user cache."""
    if folder := os.environ.get(MIRROR_ENV):
        return Path(folder).expanduser().absolute()
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "latent-steering" / "roots"


def mount(url: str, role: str = "output") -> Path:
    """Return the local folder standing for `url` on this machine, registering the root in this process.

    `file://` URLs are plain local paths (returned as such). An output root mounted again as an input stays
    an output root (its objects are then read only through publication records).
    """
    protocol, path = split_url(url)
    if protocol == "file":
        return Path("/" + path.lstrip("/"))
    url = f"{protocol}://{path}"
    with _LOCK:
        root = _ROOTS.get(url)
        if root is None or (role == "output" and root.role == "input"):
            root = Root(url, mirror_base() / protocol / path, role)
            _ROOTS[url] = root
    return root.mirror


def roots() -> tuple[Root, ...]:
    """Return the roots mounted in this process."""
    with _LOCK:
        return tuple(_ROOTS.values())


def unmount_all() -> None:
    """Forget every mounted root (tests; a process serving runs of several roots keeps them)."""
    with _LOCK:
        _ROOTS.clear()


def root_of(path: str | os.PathLike) -> tuple[Root, str] | None:
    """Return (root, key relative to it, `` for the root itself) of a local path under a mounted mirror, else None."""
    path = Path(os.path.abspath(path))
    best = None
    for root in roots():
        if path == root.mirror or root.mirror in path.parents:
            if best is None or len(root.mirror.parts) > len(best.mirror.parts):
                best = root
    if best is None:
        return None
    return best, path.relative_to(best.mirror).as_posix() if path != best.mirror else ""


def url_of(path: str | os.PathLike) -> str | None:
    """Return the URL of a local path under a mounted mirror, else None."""
    found = root_of(path)
    if found is None:
        return None
    root, key = found
    return f"{root.url}/{key}" if key else root.url


def portable(value: Any) -> Any:
    """Return `value` with every mirror path in its texts replaced by its URL (nested in lists, tuples, dicts)."""
    return _mapped(value, [(str(r.mirror), r.url) for r in roots()])


def localize(value: Any) -> Any:
    """Return `value` with every text naming a mounted URL replaced by its mirror path: `portable` undone."""
    return _mapped(value, [(r.url, str(r.mirror)) for r in roots()])


def _mapped(value: Any, prefixes: list[tuple[str, str]]) -> Any:
    if not prefixes:
        return value
    if isinstance(value, str):  # wherever they stand in the text: `trained (<path>)` too; nested roots first
        for old, new in sorted(prefixes, key=lambda p: -len(p[0])):
            value = value.replace(old, new)
        return value
    if isinstance(value, Path):
        mapped = _mapped(str(value), prefixes)
        return value if mapped == str(value) else mapped
    if isinstance(value, Mapping):
        return {k: _mapped(v, prefixes) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return type(value)(_mapped(v, prefixes) for v in value) if isinstance(value, list) else tuple(
            _mapped(v, prefixes) for v in value)
    return value
