"""The cache key of a task run: its identity, from the content of its inputs.

A task's identity (`steering_core.identity`) is the content of its inputs (file hashes, settings
fingerprints), its own source, and the source of the `steering_core` modules it calls: equal
identity, equal outputs. `ContentKey` turns a task's parameters into that identity, so an
unchanged input gives a `Cached` task run and a changed one recomputes only what depends on it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from prefect.cache_policies import CachePolicy
from prefect.context import TaskRunContext

from steering_core.identity import code_version, plain
from steering_core.storage import mirrors
from steering_core.storage.fileio import sha256_json
from tasks.buckets import pulled_for_key
from tasks.cache_records import drop_if_outputs_missing

Fingerprint = Callable[[Any], Any]


@dataclasses.dataclass
class ContentKey(CachePolicy):
    """Cache key = task source + code version of `modules` + every parameter by content.

    `fingerprints` maps a parameter name to a function of its value (e.g. `file_digest` for a
    path); other parameters count by value (settings models by their JSON). `derived` adds
    fingerprints computed from all parameters (e.g. the shards a concept map's episodes live in).
    Names in `ignore` do not count (e.g. a label only used in the task run's name).
    """

    modules: tuple[str, ...] = ()
    fingerprints: Mapping[str, Fingerprint] = dataclasses.field(default_factory=dict)
    derived: Mapping[str, Callable[[dict[str, Any]], Any]] = dataclasses.field(default_factory=dict)
    ignore: tuple[str, ...] = ()
    store: Path | None = None  # where results live (set by `rooted`): stale records are dropped here

    def compute_key(
        self, task_ctx: TaskRunContext, inputs: dict[str, Any], flow_parameters: dict[str, Any], **kwargs: Any
    ) -> str:
        task_fn = task_ctx.task.fn
        if self.store is not None and mirrors.url_of(self.store):
            inputs = pulled_for_key(task_ctx, inputs)
        identity = {
            "task": f"{task_fn.__module__}.{task_fn.__qualname__}",
            "source": hashlib.sha256(inspect.getsource(task_fn).encode()).hexdigest(),
            "code": code_version(*self.modules) if self.modules else "",
            "inputs": {
                name: self.fingerprints.get(name, plain)(value)
                for name, value in sorted(inputs.items())
                if name not in self.ignore
            },
            "derived": {name: fingerprint(inputs) for name, fingerprint in sorted(self.derived.items())},
        }
        key = sha256_json(mirrors.portable(identity))  # equal on every machine mirroring the same bucket
        if self.store is not None:
            drop_if_outputs_missing(self.store, key)
        return key


def content_key(
    *modules: str,
    derived: Mapping[str, Callable[[dict[str, Any]], Any]] | None = None,
    ignore: tuple[str, ...] = (),
    **fingerprints: Fingerprint,
) -> ContentKey:
    """Return a `ContentKey` over the given steering_core modules and per-parameter fingerprints."""
    return ContentKey(modules=modules, fingerprints=fingerprints, derived=dict(derived or {}), ignore=ignore)
