"""Where a task's results live: `rooted` puts them, and its cache records, under its run's output root.

Results (small JSON summaries) and their cache records live under `<output_root>/.prefect-cache/`,
not in `$PREFECT_HOME`: they travel with the outputs, every worker sharing the output folder sees
them, and deleting the outputs deletes the cache.
"""

from __future__ import annotations

import dataclasses
import os
from types import ModuleType, SimpleNamespace
from typing import Any

from prefect.tasks import Task
from prefect.utilities.callables import get_call_parameters

from steering_core.storage import mirrors
from tasks.buckets import result_block, through_bucket
from tasks.cache_keys import ContentKey
from tasks.cache_records import cache_store, read_record_bytes, record_location

# Every task persists a small JSON summary: cache hits need it, and JSON is never unpickled.
RESULTS: dict[str, Any] = {"persist_result": True, "result_serializer": "json"}


def is_cached(task: Task, output_root: str | os.PathLike, *args: Any, **kwargs: Any) -> bool:
    """Return True when `rooted(task, output_root)(*args, **kwargs)` would be `Cached`: its record is there and
    every output it lists exists (checked without starting a run, e.g. before launching a child run for it)."""
    return _would_be_cached(rooted(task, output_root), task, output_root, args, kwargs)


def _would_be_cached(rooted_task: Task, task: Task, output_root: str | os.PathLike, args: tuple, kwargs: dict) -> bool:
    """`is_cached` given the task already rooted under `output_root`."""
    policy = rooted_task.cache_policy
    if not isinstance(policy, ContentKey):
        return False
    key = policy.compute_key(SimpleNamespace(task=task), get_call_parameters(task.fn, args, kwargs), {})
    return read_record_bytes(record_location(cache_store(output_root), key)) is not None


def rooted(task: Task, output_root: str | os.PathLike) -> Task:
    """Return `task` with results and cache records under `<output_root>/.prefect-cache`.

    On a bucket root (`steering_core.storage.mirrors`) the records are objects there (a `RemoteFileSystem`
    result storage), the task pulls the published outputs it reads before its cache key is computed, publishes
    the outputs its summary lists, and its summary names outputs by URL, so it is the same on every machine.
    """
    store = cache_store(output_root)
    url = mirrors.url_of(store)
    policy = task.cache_policy
    if isinstance(policy, ContentKey):
        policy = dataclasses.replace(policy, store=store)
    if url is None:
        return task.with_options(result_storage=store, cache_policy=policy)
    bucket_task = task.with_options(result_storage=result_block(url), cache_policy=policy)
    bucket_task.fn = through_bucket(task.fn, pulls=not isinstance(policy, ContentKey))
    return bucket_task


class TaskSet:
    """The tasks of some task modules, each `rooted` under one output root, by name: `TaskSet(root, data).filter_demos`.

    A flow makes one when it starts, so where its tasks keep results (and, on a bucket root, the pulling before
    and the publishing after each) is decided once, not at every call.
    """

    def __init__(self, output_root: str | os.PathLike, *modules: ModuleType) -> None:
        self.output_root = output_root
        self._tasks: dict[str, Task] = {}
        for module in modules:
            for name, value in vars(module).items():
                if isinstance(value, Task) and value.fn.__module__ == module.__name__:
                    if name in self._tasks:
                        raise ValueError(f"task {name!r} is defined in two of {[m.__name__ for m in modules]}")
                    self._tasks[name] = value
        self._rooted: dict[str, Task] = {}

    def __getattr__(self, name: str) -> Task:
        if name.startswith("_"):
            raise AttributeError(name)
        if name not in self._rooted:
            self._rooted[name] = rooted(self._task(name), self.output_root)
        return self._rooted[name]

    def is_cached(self, name: str, *args: Any, **kwargs: Any) -> bool:
        """Return True when task `name` called with these arguments would be `Cached` (see `is_cached`)."""
        return _would_be_cached(getattr(self, name), self._task(name), self.output_root, args, kwargs)  # rooted once

    def _task(self, name: str) -> Task:
        if name not in self._tasks:
            raise AttributeError(f"no task {name!r} in this TaskSet (it has {sorted(self._tasks)})")
        return self._tasks[name]
