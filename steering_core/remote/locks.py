"""Locks on outputs, across machines: the local lock (`storage.locks`) and, on an output root in object storage,
a lock object in the bucket made by a conditional create (`bucket_lock`), taken after it.

Steps lock what they write with `output_lock` (one output) and `group_locks` (capture's shard groups)."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from steering_core.remote.filesystems import object_path
from steering_core.storage.locks import GROUP_LOCK, local_group_locks, local_output_lock
from steering_core.storage.mirrors import root_of

logger = logging.getLogger(__name__)

LOCKS_DIR = ".locks"
LEASE_ENV = "LATENT_STEERING_LOCK_LEASE_S"


@contextlib.contextmanager
def output_lock(output: str | os.PathLike) -> Iterator[None]:
    """Hold the lock on the output file or folder `output`: the local one, then the bucket's (see `local_output_lock`)."""
    with local_output_lock(output), bucket_lock(output):
        yield


@contextlib.contextmanager
def group_locks(run_dir: str | os.PathLike, groups: Iterable[int]) -> Iterator[None]:
    """Hold the lock on each shard group of `run_dir`: the local ones, then the bucket's, in ascending order."""
    groups = sorted(set(groups))
    with local_group_locks(run_dir, groups), contextlib.ExitStack() as bucket:
        for group in groups:
            bucket.enter_context(bucket_lock(Path(run_dir) / GROUP_LOCK.format(group=group)))
        yield


def lease_seconds() -> float:
    """Return how long a lock object may go unrenewed before waiters take it as abandoned ($LATENT_STEERING_LOCK_LEASE_S)."""
    return float(os.environ.get(LEASE_ENV, "60"))


@contextlib.contextmanager
def bucket_lock(path: str | os.PathLike) -> Iterator[None]:
    """Hold the bucket-wide lock on the output `path` of a mounted root (no-op for other paths).

    The lock is an object `<root>/.locks/<key>.lock` made by a conditional create (S3 `If-None-Match: *`),
    so only one writer can make it. Its holder rewrites it every lease/4 seconds. A waiter that sees the
    same ETag for a whole lease, by its own clock, takes the holder as dead and deletes the object: no
    clock is shared between machines, and a killed worker delays the next one by at most one lease.
    """
    found = root_of(path)
    if found is None or found[0].role != "output":
        yield
        return
    root, key = found
    url = f"{root.url}/{LOCKS_DIR}/{key}.lock"
    fs, lock_path = object_path(url)
    holder = f"{socket.gethostname()}-{os.getpid()}-{threading.get_ident()}-{uuid.uuid4().hex[:8]}"
    lease = lease_seconds()
    seen: tuple[str | None, float] = (None, time.monotonic())
    waited = False
    while not _create_if_absent(fs, lock_path, holder):
        try:
            etag = fs.info(lock_path, refresh=True).get("ETag")
        except FileNotFoundError:
            continue
        now = time.monotonic()
        if etag != seen[0]:
            seen = (etag, now)
        elif now - seen[1] > lease:
            logger.warning("%s: lock not renewed for %.0f s; its holder is gone, taking it over", url, lease)
            with contextlib.suppress(FileNotFoundError):
                fs.rm_file(lock_path)
            continue
        if not waited:
            logger.info("%s is being written by another machine; waiting", f"{root.url}/{key}")
            waited = True
        time.sleep(min(1.0, lease / 8))
    stop = threading.Event()
    renewer = threading.Thread(target=_renew, args=(fs, lock_path, holder, lease / 4, stop), daemon=True)
    renewer.start()
    try:
        yield
    finally:
        stop.set()
        renewer.join()
        with contextlib.suppress(FileNotFoundError):
            fs.rm_file(lock_path)
        fs.invalidate_cache()


def _create_if_absent(fs: Any, path: str, holder: str) -> bool:
    """Create the object `path` only if it does not exist; return False when it does."""
    body = json.dumps({"holder": holder}).encode()
    protocol = fs.protocol[0] if isinstance(fs.protocol, (tuple, list)) else fs.protocol
    try:
        if protocol in ("s3", "s3a"):
            bucket, _, key = path.partition("/")
            fs.call_s3("put_object", Bucket=bucket, Key=key, Body=body, IfNoneMatch="*")
        elif protocol in ("gs", "gcs"):
            fs.pipe_file(path, body, if_generation_match=0)
        else:  # a local file system: exclusive create
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            with open(path, "xb") as handle:
                handle.write(body)
    except FileExistsError:
        return False
    except Exception as err:  # noqa: BLE001  s3fs/gcsfs report a failed precondition in their own ways
        if "412" in str(err) or "PreconditionFailed" in str(err) or "conditionNotMet" in str(err):
            return False
        raise
    fs.invalidate_cache()
    return True


def _renew(fs: Any, path: str, holder: str, every: float, stop: threading.Event) -> None:
    """Rewrite the lock object every `every` seconds until `stop`, so waiters see it alive."""
    beat = 0
    while not stop.wait(every):
        beat += 1
        with contextlib.suppress(Exception):
            fs.pipe_file(path, json.dumps({"holder": holder, "beat": beat}).encode())
