"""Where a task's results live: `rooted` puts them, and its cache records, under its run's output root.

Results (small JSON summaries) and their cache records live under `<output_root>/.prefect-cache/`,
not in `$PREFECT_HOME`: they travel with the outputs, every worker sharing the output folder sees
them, and deleting the outputs deletes the cache.
"""

from __future__ import annotations

import dataclasses
import os
from types import SimpleNamespace
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
    policy = rooted(task, output_root).cache_policy
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
