"""Which task failures are retried: only those a second attempt can get past.

File systems (network mounts, a full disk being cleared) and GPUs (memory held by a neighbour) are retried;
bad content, missing files and bugs fail at once.
"""

from __future__ import annotations

import errno
import re
from collections.abc import Callable
from typing import Any

import torch
from prefect.states import State
from prefect.tasks import Task
from safetensors import SafetensorError

IO_RETRIES, IO_RETRY_DELAYS = 2, [2, 30]            # seconds
GPU_RETRIES, GPU_RETRY_DELAYS = 2, [30, 120]        # seconds: give a crashed neighbour time to free memory
TRANSIENT_ERRNOS = frozenset({errno.EIO, errno.EAGAIN, errno.EBUSY, errno.EINTR, errno.ETIMEDOUT, errno.ESTALE,
                              errno.ENOSPC, errno.ECONNRESET, errno.ECONNABORTED, errno.ENETUNREACH,
                              errno.EHOSTUNREACH})
_RUST_OS_ERROR = re.compile(r"\(os error (\d+)\)")  # how Rust's std::io::Error names its errno


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
