"""URLs given to the path options of any command: mounted as local mirrors, pulled before, published after.

`latent-steering slice --run-dir s3://bucket/data/residuals/demo ...` works like the local command on the
option's mirror folder (`steering_core.storage.mirrors`): what is published there is pulled first (shards
stay in the bucket and are read by ranges), and each mirror folder or file the command changed is published
when it succeeds. A prefix that holds no publication record is a user's input (a checkpoint uploaded by
hand): its objects are pulled as they are.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from steering_core.remote.filesystems import object_path
from steering_core.remote.publish import covering_record, publish, pull, records_under
from steering_core.storage.mirrors import is_url, mount, split_url

Snapshot = dict[Path, dict[str, tuple[int, int]]]


def mount_urls(paths: set[str], args: Sequence[str]) -> tuple[list[str], list[Path]]:
    """Return `args` with each URL given to an option of `paths` replaced by its pulled mirror path, and those paths."""
    out, mounted = list(args), []
    for position, word in enumerate(args):
        if word == "--":
            break
        name, equals, value = word.partition("=")
        if name not in paths or not (equals or position + 1 < len(args)):
            continue
        value = value if equals else args[position + 1]
        if not is_url(value):
            continue
        try:
            local = _mounted(value)
        except ValueError as err:
            raise ValueError(f"{name}: {err}") from None
        mounted.append(local)
        if equals:
            out[position] = f"{name}={local}"
        else:
            out[position + 1] = str(local)
    return out, mounted


def _mounted(url: str) -> Path:
    """Return the mirror path of `url`, pulled: an output when it is, holds or lies in published outputs (or is
    nothing yet), else an input root of its own (objects a user put there).

    An output is mounted under its parent URL as the root, so the file or folder the command writes is published
    with its record beside it (a root itself is never published). A bucket alone is mounted as it is.
    """
    protocol, path = split_url(url)  # refused in one line, as given, before any request
    url = f"{protocol}://{path}"
    published = covering_record(url) is not None or bool(records_under(url))  # a file of a published folder too
    if not published and _exists(url):
        local = mount(url, "input")
    else:
        parent, _, name = path.rpartition("/")
        local = mount(f"{protocol}://{parent}", "output") / name if parent else mount(url, "output")
        if not published:
            return local  # a new output: nothing to pull
    pull(local)
    return local


def _exists(url: str) -> bool:
    fs, path = object_path(url)
    return fs.exists(path)


def snapshot(paths: Sequence[Path]) -> Snapshot:
    """Return (size, mtime_ns) of every file under each path, to tell afterwards which ones a command changed."""
    def files(path: Path) -> dict[str, tuple[int, int]]:
        found = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
        return {os.fspath(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in found}
    return {path: files(path) for path in paths}


def publish_changed(before: Snapshot) -> list[Path]:
    """Publish each mounted path whose files changed since `before`; return them."""
    changed = [path for path, files in before.items() if path.exists() and snapshot([path])[path] != files]
    for path in changed:
        publish(path)
    return changed
