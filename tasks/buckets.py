"""A task on a bucket output root: its inputs pulled before it runs, its outputs published after.

Tasks read and write mirror paths (`steering_core.storage.mirrors`); the wrapper `through_bucket` pulls the
published objects a task's parameters name, runs it, and publishes what its summary lists, naming outputs by
URL so the summary is the same on every machine. Its results are kept in a saved `RemoteFileSystem` block.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from prefect.context import TaskRunContext
from pydantic import BaseModel

from steering_core.remote import publish
from steering_core.storage import mirrors
from tasks.cache_records import OUTPUTS

# Task run id -> the error met pulling its inputs for its cache key. Prefect logs an error raised by a cache
# policy and runs the task without a key, so the task's own run raises it (see `through_bucket`).
_PULL_ERRORS: dict[Any, Exception] = {}


def pulled_for_key(task_ctx: Any, inputs: dict[str, Any]) -> dict[str, Any]:
    """Return `inputs` pulled for a cache key; an error is kept for the task run to raise (`through_bucket`)."""
    try:
        return pull_inputs(inputs)
    except Exception as err:
        if (task_run := getattr(task_ctx, "task_run", None)) is not None:
            _PULL_ERRORS[task_run.id] = err
        raise


RESULT_BLOCK = "latent-steering-results-{digest}"  # a RemoteFileSystem block per bucket cache folder


@functools.cache
def result_block(url: str) -> str:
    """Return the slug of the saved `RemoteFileSystem` block whose base path is `url` (saved once per process:
    Prefect keeps task results only in storage saved on its server)."""
    from prefect.filesystems import RemoteFileSystem

    name = RESULT_BLOCK.format(digest=hashlib.sha256(url.encode()).hexdigest()[:12])
    RemoteFileSystem(basepath=url).save(name, overwrite=True)
    return f"remote-file-system/{name}"


def pull_inputs(inputs: dict[str, Any]) -> dict[str, Any]:
    """Return `inputs` with URLs named as mirror paths, after pulling every published output they name."""
    inputs = mirrors.localize(inputs)
    for path in sorted(set(_mirror_paths(inputs))):
        publish.pull(path)
    return inputs


def _mirror_paths(value: Any) -> list[str]:
    """Return every text in `value` (nested, settings models included) that names a path under a mounted mirror."""
    if isinstance(value, BaseModel):
        return _mirror_paths(value.model_dump(mode="json"))
    if isinstance(value, str | Path):
        return [str(value)] if mirrors.url_of(value) is not None else []
    items = value.values() if isinstance(value, Mapping) else value if isinstance(value, list | tuple) else ()
    return [path for item in items for path in _mirror_paths(item)]


def through_bucket(fn: Callable[..., Any], *, pulls: bool) -> Callable[..., Any]:
    """Return `fn` run on mirror paths (pulled first when no cache key pulled them), its outputs published after.

    When pulling for the cache key failed (an object changed after its publication), Prefect only logged it and
    runs the task without a key: the task fails with that error here, naming the object, before reading anything.
    """

    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        context = TaskRunContext.get()
        if context is not None and (error := _PULL_ERRORS.pop(context.task_run.id, None)) is not None:
            raise error
        args, kwargs = mirrors.localize(args), mirrors.localize(kwargs)
        if pulls:
            pull_inputs({"args": args, "kwargs": kwargs})
        summary = fn(*args, **kwargs)
        for path in publish_units(summary):
            if path.exists():  # else written on another machine (a group captured there): published already
                publish.publish(path)
        return mirrors.portable(summary)

    return run


def publish_units(summary: Any) -> list[Path]:
    """Return what a task's summary says it wrote, as units to publish: its `folder` whole, else each output."""
    if not isinstance(summary, dict):
        return []
    folder = summary.get("folder")
    units = [Path(folder)] if isinstance(folder, str) else []
    for output in summary.get(OUTPUTS, []):
        path = Path(output)
        if not any(path == unit or unit in path.parents for unit in units):
            units.append(path)
    return units
