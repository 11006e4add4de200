"""Cache keys built from input content, and task results kept beside the outputs they describe.

A task's identity (`steering_core.identity`) is the content of its inputs (file hashes, settings
fingerprints), its own source, and the source of the `steering_core` modules it calls: equal
identity, equal outputs. `ContentKey` turns a task's parameters into that identity, so an
unchanged input gives a `Cached` task run and a changed one recomputes only what depends on it.

Results (small JSON summaries) and their cache records live under `<output_root>/.prefect-cache/`,
not in `$PREFECT_HOME`: they travel with the outputs, every worker sharing the output folder sees
them, and deleting the outputs deletes the cache. A task's summary lists the files it wrote under
`outputs`; a record whose outputs are gone is dropped before lookup, so the task runs again.
The output root may be shared, so records are checked as plain JSON before Prefect reads them
(`read_cache_record`): one naming pickle or any other serializer is refused and recomputed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import hashlib
import inspect
import json
import logging
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from prefect.cache_policies import CachePolicy
from prefect.context import TaskRunContext
from prefect.states import State
from prefect.tasks import Task
from prefect.utilities.callables import get_call_parameters
from pydantic import BaseModel
from safetensors import SafetensorError

from steering_core.identity import code_version, plain
from steering_core.remote import filesystems, publish
from steering_core.storage import mirrors
from steering_core.storage.fileio import sha256_json

logger = logging.getLogger(__name__)

CACHE_DIR = ".prefect-cache"  # under the output root: one record per finished task run
OUTPUTS = "outputs"           # key of a task summary that lists the files the task wrote

Fingerprint = Callable[[Any], Any]

# Every task persists a small JSON summary: cache hits need it, and JSON is never unpickled.
RESULTS: dict[str, Any] = {"persist_result": True, "result_serializer": "json"}
# Retries only where a second attempt can succeed: file systems (network mounts, a full disk being
# cleared) and GPUs (memory held by a neighbour). Bad content, missing files and bugs fail at once.
IO_RETRIES, IO_RETRY_DELAYS = 2, [2, 30]            # seconds
GPU_RETRIES, GPU_RETRY_DELAYS = 2, [30, 120]        # seconds: give a crashed neighbour time to free memory
TRANSIENT_ERRNOS = frozenset({errno.EIO, errno.EAGAIN, errno.EBUSY, errno.EINTR, errno.ETIMEDOUT, errno.ESTALE,
                              errno.ENOSPC, errno.ECONNRESET, errno.ECONNABORTED, errno.ENETUNREACH,
                              errno.EHOSTUNREACH})
_RUST_OS_ERROR = re.compile(r"\(os error (\d+)\)")  # how Rust's std::io::Error names its errno


# ----------------------------------------------------------------------------- retries

def transient_io(err: BaseException) -> bool:
    """Return True for an I/O error a later attempt may not meet: a network or disk hiccup, not a bad path.

    safetensors reports I/O errors as SafetensorError (not an OSError) holding Rust's `(os error N)`: classified
    by that number, so a full disk while writing a shard is retried like any other.
    """
    if isinstance(err, SafetensorError):
        found = _RUST_OS_ERROR.search(str(err))
        return found is not None and int(found.group(1)) in TRANSIENT_ERRNOS
    return isinstance(err, (ConnectionError, TimeoutError)) or (
        isinstance(err, OSError) and err.errno in TRANSIENT_ERRNOS)


def transient_gpu(err: BaseException) -> bool:
    """Return True for a transient I/O error or CUDA out-of-memory at one frame per pass (another process's memory).

    Capture halves its batch on out-of-memory by itself; only when one frame does not fit is waiting worth it.
    """
    return transient_io(err) or isinstance(err, torch.cuda.OutOfMemoryError)


def retry_if(transient: Callable[[BaseException], bool]) -> Callable[[Task, Any, State], bool]:
    """Return a `retry_condition_fn` that retries only when the task's exception satisfies `transient`."""

    def condition(task: Task, task_run: Any, state: State) -> bool:
        try:
            state.result()
        except Exception as err:  # noqa: BLE001  classified, not handled
            return transient(err)
        return False

    condition.__qualname__ = f"retry_if({transient.__name__})"
    return condition


# ----------------------------------------------------------------------------- the cache policy

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
            inputs = _pulled_for_key(task_ctx, inputs)
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
            _drop_if_outputs_missing(self.store, key)
        return key


def content_key(
    *modules: str,
    derived: Mapping[str, Callable[[dict[str, Any]], Any]] | None = None,
    ignore: tuple[str, ...] = (),
    **fingerprints: Fingerprint,
) -> ContentKey:
    """Return a `ContentKey` over the given steering_core modules and per-parameter fingerprints."""
    return ContentKey(modules=modules, fingerprints=fingerprints, derived=dict(derived or {}), ignore=ignore)


# Task run id -> the error met pulling its inputs for its cache key. Prefect logs an error raised by a cache
# policy and runs the task without a key, so the task's own run raises it (see `_through_bucket`).
_PULL_ERRORS: dict[Any, Exception] = {}


def _pulled_for_key(task_ctx: Any, inputs: dict[str, Any]) -> dict[str, Any]:
    try:
        return pull_inputs(inputs)
    except Exception as err:
        if (task_run := getattr(task_ctx, "task_run", None)) is not None:
            _PULL_ERRORS[task_run.id] = err
        raise


def _drop_if_outputs_missing(store: Path, key: str) -> None:
    """Delete a cache record that is not plain JSON of our schema, or whose summary lists a vanished output.

    Runs before Prefect looks the key up, so Prefect only ever reads records checked here. On a bucket root the
    record is an object beside the outputs, and an output counts as there when it is published.
    """
    location = record_location(store, key)
    data = read_record_bytes(location)
    if data is None:
        return
    try:
        result = parse_cache_record(location, data)
    except ValueError as err:  # tampered or damaged: never handed to Prefect's deserializers; recompute instead
        logger.warning("refused cache record: %s; the task will run again", err)
        _delete_record(location)
        return
    outputs = result.get(OUTPUTS, []) if isinstance(result, dict) else []
    missing = [p for p in outputs if not (publish.is_published(p) if mirrors.is_url(p) else Path(p).exists())]
    if missing:
        logger.info("%s: cached outputs are gone (%s); the task will run again", key, ", ".join(missing[:3]))
        _delete_record(location)


def record_location(store: Path, key: str) -> Path | str:
    """Return where the cache record `key` lives: a file of `store`, or its object when `store` mirrors a bucket."""
    url = mirrors.url_of(store)
    return store / key if url is None else f"{url}/{key}"


def read_record_bytes(location: Path | str) -> bytes | None:
    """Return the bytes of a cache record (a file, or an object URL), or None when there is none."""
    if not mirrors.is_url(location):
        return Path(location).read_bytes() if Path(location).is_file() else None
    fs, path = filesystems.object_path(location)
    try:
        return fs.cat_file(path)
    except FileNotFoundError:
        return None


def _delete_record(location: Path | str) -> None:
    if isinstance(location, Path):
        location.unlink(missing_ok=True)
        return
    fs, path = filesystems.object_path(location)
    with contextlib.suppress(FileNotFoundError):
        fs.rm_file(path)
    fs.invalidate_cache()


# The only serializer a record may name: Prefect's JSON serializer exactly as `RESULTS` writes it. Any
# other (pickle, or JSON with another library, encoder or decoder) would import and run named code.
_JSON_SERIALIZER = {
    "type": "json", "jsonlib": "json", "object_encoder": "prefect.serializers.prefect_json_object_encoder",
    "object_decoder": "prefect.serializers.prefect_json_object_decoder", "dumps_kwargs": {}, "loads_kwargs": {},
}
_METADATA_KEYS = {"storage_key", "expiration", "serializer", "prefect_version", "storage_block_id"}
_CODE_KEYS = ("__class__", "__exc_type__")  # Prefect's JSON decoder imports what these name


def read_cache_record(path: str | os.PathLike) -> Any:
    """Return the task summary held by a cache record, read with the standard `json` module only.

    The record must be `{"metadata": {...}, "result": "<JSON text>"}` with the JSON serializer above, no
    storage block, `storage_key` naming the record itself, and a summary of plain JSON values (no key
    that Prefect's decoder would turn into an import). ValueError naming the file otherwise.
    """
    return parse_cache_record(Path(path), Path(path).read_bytes())


def parse_cache_record(path: Path | str, data: bytes) -> Any:
    """Return the task summary of the cache record `data` stored at `path` (a file or an object URL); see
    `read_cache_record`."""

    def refuse(why: str) -> ValueError:
        return ValueError(f"{path}: {why}; expected a JSON task summary written by this project")

    try:
        record = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise refuse("not JSON") from None
    if not isinstance(record, dict) or set(record) != {"metadata", "result"} or not isinstance(record["metadata"], dict):
        raise refuse("not a result record")
    metadata = record["metadata"]
    if set(metadata) - _METADATA_KEYS:
        raise refuse(f"unknown metadata {sorted(set(metadata) - _METADATA_KEYS)}")
    serializer = metadata.get("serializer")
    if serializer != _JSON_SERIALIZER:
        kind = serializer.get("type") if isinstance(serializer, dict) else serializer
        raise refuse(f"serializer {kind!r} with settings {serializer!r} (only Prefect's plain JSON serializer)")
    on_bucket = mirrors.is_url(path)  # kept through our saved block, which names records by key alone
    names = {str(path), str(path).rsplit("/", 1)[-1]} if on_bucket else {str(path)}
    if (metadata.get("storage_block_id") is not None and not on_bucket) or metadata.get("storage_key") not in names:
        raise refuse(f"storage {metadata.get('storage_block_id')!r}, {metadata.get('storage_key')!r} is not this file")
    if not isinstance(record["result"], str):
        raise refuse("result is not JSON text")
    try:
        summary = json.loads(record["result"])
    except json.JSONDecodeError:
        raise refuse("result is not valid JSON") from None
    if found := _code_keys(summary):
        raise refuse(f"result holds {found!r}, which Prefect's decoder would import")
    return summary


def _code_keys(value: Any) -> str | None:
    """Return the first key of `value` (nested) that Prefect's JSON decoder treats as code, or None."""
    if isinstance(value, dict):
        for key, item in value.items():
            if key in _CODE_KEYS:
                return key
            if found := _code_keys(item):
                return found
    elif isinstance(value, list):
        for item in value:
            if found := _code_keys(item):
                return found
    return None


def cache_store(output_root: str | os.PathLike) -> Path:
    """Return the folder holding task results and cache records for runs writing under `output_root`."""
    return Path(output_root).resolve() / CACHE_DIR


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
    bucket_task.fn = _through_bucket(task.fn, pulls=not isinstance(policy, ContentKey))
    return bucket_task


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


def _through_bucket(fn: Callable[..., Any], *, pulls: bool) -> Callable[..., Any]:
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
