"""Identity of a step's output: content fingerprints of its inputs and the version of the code that computes it.

Equal identity, equal outputs. A step's code version is the hash of the source of the `steering_core`
modules it calls, followed through their imports (read, never imported); its inputs count by content
(file hashes, settings by their JSON). `tasks.cache_keys` turns these into Prefect cache keys.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import os
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from steering_core.remote.publish import pulled_etag
from steering_core.storage.fileio import sha256_json

PROJECT_PACKAGES = ("steering_core",)  # imports followed when versioning code
_PROJECT_ROOT = Path(__file__).resolve().parents[1]  # the folder holding steering_core/


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


def _project_imports(name: str, path: Path, source: bytes) -> set[str]:
    """Return the project modules imported by the module `name`, stored at `path` with text `source`."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
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
# (module, sha256 of its source) -> its project imports: each source is parsed once per process (a pipeline run
# versions a dozen module sets sharing most of the package; parsing them all again was 11% of two tiny runs' time)
_IMPORTS: dict[tuple[str, str], set[str]] = {}


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
        source = path.read_bytes()
        key = (name, hashlib.sha256(source).hexdigest())
        seen[name] = key[1]
        if key not in _IMPORTS:
            _IMPORTS[key] = _project_imports(name, path, source)
        pending.extend(_IMPORTS[key] - seen.keys())
    return dict(sorted(seen.items()))
