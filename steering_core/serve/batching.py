"""Dynamic batching of policy requests: one policy call at a time, shared by the requests waiting for it.

A request waits until `batch_wait_ms` has passed since the oldest waiting one arrived, its call's rows (up to
`max_batch`) are full, or every open connection has a request waiting; the call then takes the oldest waiting
requests. It runs in a daemon thread of its own (a stuck call cannot stop the server), as one `infer_batch` when
the policy has it and there are several requests, else one `infer` each; a batch that fails is run again one
request at a time, so one bad request fails alone. A request without actions within the inference timeout of its
arrival gets InferenceFailed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from steering_core.serve.policy import ServedPolicy
from steering_core.serve.request import AppliedSteering

logger = logging.getLogger(__name__)

# a policy call costs about the same for 1 and 16 rows on a GPU (bound by launches), so requests arriving while
# one waits share a call; the window is short against a LIBERO client's 50 ms control step
DEFAULT_BATCH_WAIT_MS = 5.0
MAX_BATCH_WAIT_MS = 1000.0  # a longer window only delays every request
MAX_BATCH = 256  # rows of one call: pi0.5's activations at 256 rows fill a GPU's memory several times over


class InferenceFailed(RuntimeError):
    """The policy gave no usable actions for a well-formed request (timeout, non-finite actions)."""


@dataclass(eq=False)
class _Pending:
    """A checked request waiting for (or in) a policy call; `reply` gets (result, server timing) or an error."""

    observation: dict[str, Any]
    steering: tuple[AppliedSteering, ...]
    rows: int
    queued: float
    reply: asyncio.Future
    started: float | None = None


class Batcher:
    """Run the requests `submit`ted to it on `policy`, batched (module docstring), while the task of `start` runs.

    `open_connections()` is the number of connections that may still send a request: once each has one waiting,
    no other could join the call. `max_batch` 1 runs one request per call.
    """

    def __init__(self, policy: ServedPolicy, *, max_batch: int, batch_wait_ms: float, inference_timeout_s: float,
                 open_connections: Callable[[], int]) -> None:
        if isinstance(max_batch, bool) or not isinstance(max_batch, int) or not 1 <= max_batch <= MAX_BATCH:
            raise ValueError(f"max_batch {max_batch!r}: expected an integer from 1 to {MAX_BATCH} (rows per call)")
        if not 0 <= batch_wait_ms <= MAX_BATCH_WAIT_MS:
            raise ValueError(f"batch_wait_ms {batch_wait_ms!r}: expected 0 to {MAX_BATCH_WAIT_MS:g} ms")
        self.policy = policy
        self.max_batch, self.batch_wait_ms = max_batch, float(batch_wait_ms)
        self.inference_timeout_s = inference_timeout_s
        self._open_connections = open_connections
        self._loop: asyncio.AbstractEventLoop | None = None
        self._waiting: list[_Pending] = []  # requests not yet in a policy call, oldest first
        self._arrived: asyncio.Event | None = None

    @property
    def waiting_requests(self) -> int:
        """Return the number of requests not yet in a policy call."""
        return len(self._waiting)

    def start(self) -> asyncio.Task:
        """Return the task running the batches on the running event loop (cancel it to stop)."""
        self._loop, self._arrived = asyncio.get_running_loop(), asyncio.Event()
        return asyncio.create_task(self._batches())

    async def submit(self, observation: dict[str, Any], steering: tuple[AppliedSteering, ...],
                     rows: int) -> tuple[dict, dict]:
        """Return the policy's result and the server timing (queue and inference time, the call's rows and
        requests); raise InferenceFailed when no actions come within the inference timeout of its arrival."""
        pending = _Pending(observation, steering, rows, time.monotonic(), self._loop.create_future())
        self._waiting.append(pending)
        self._arrived.set()
        timeout = self.inference_timeout_s
        try:
            return await asyncio.wait_for(asyncio.shield(pending.reply), timeout)
        except TimeoutError:
            pending.reply.cancel()  # its call, if one runs, drops the result
            if pending.started is None:
                self._waiting.remove(pending)
                raise InferenceFailed(f"timed out after {timeout:g} s waiting for the model, which other requests "
                                      "hold (serve --inference-timeout-s)") from None
            raise InferenceFailed(f"timed out: no actions within {timeout:g} s (serve --inference-timeout-s)") from None

    async def _batches(self) -> None:
        """Run the waiting requests, one policy call at a time: each call takes the oldest waiting requests (up to
        `max_batch` rows, at least one request), once `batch_wait_ms` has passed since the oldest arrived, the rows
        are full, or every open connection has a request waiting (a connection sends its next one only after its
        reply, so no other could join: a lone client never waits)."""
        while True:
            await self._arrived.wait()
            while (self._waiting and sum(p.rows for p in self._waiting) < self.max_batch
                   and len(self._waiting) < self._open_connections()):
                left = self._waiting[0].queued + self.batch_wait_ms / 1000 - time.monotonic()
                if left <= 0:
                    break
                self._arrived.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._arrived.wait(), left)
            batch, rows = [], 0
            while self._waiting and (not batch or rows + self._waiting[0].rows <= self.max_batch):
                batch.append(self._waiting.pop(0))
                rows += batch[-1].rows
            if not self._waiting:
                self._arrived.clear()
            if batch:
                await self._call(batch)

    async def _call(self, batch: list[_Pending]) -> None:
        """Run one policy call for `batch` in a daemon thread and settle each request's reply.

        A call still running at a request's inference timeout keeps the model until its thread returns (later
        requests time out too), so two calls never run at once. A daemon thread of its own keeps a stuck call from
        stopping the server.
        """
        started = time.monotonic()
        for pending in batch:
            pending.started = started
        try:
            results = await _in_daemon_thread(self._loop, self._run_policy, [p.observation for p in batch],
                                              [p.steering for p in batch])
        except Exception as err:  # handed to every request of the call
            results = [err] * len(batch)
        finished, rows = time.monotonic(), sum(p.rows for p in batch)
        late = [p for p in batch if p.reply.done()]  # answered with the timeout meanwhile
        if late:
            logger.warning("a policy call that timed out ended after %.1f s; the results of %d request(s) were "
                           "dropped", finished - started, len(late))
        for pending, result in zip(batch, results, strict=True):
            if pending in late:
                continue
            if isinstance(result, BaseException):
                pending.reply.set_exception(result)
            else:
                pending.reply.set_result((dict(result), {
                    "infer_ms": (finished - started) * 1000, "queue_ms": (started - pending.queued) * 1000,
                    "batch_rows": rows, "batch_requests": len(batch)}))

    def _run_policy(self, observations: list[dict[str, Any]],
                    steering: list[tuple[AppliedSteering, ...]]) -> list[dict[str, Any] | Exception]:
        """Return a result (or the error) per request: one `infer_batch` call when the policy has it and there are
        several, else one `infer` each. A batch that fails is run again one request at a time, so one bad request
        fails alone."""
        batched = getattr(self.policy, "infer_batch", None)
        if batched is not None and len(observations) > 1:
            try:
                return list(batched(observations, steering))
            except Exception:  # found again, request by request, below
                logger.warning("a batch of %d requests failed; running them one at a time", len(observations))
        results: list[dict[str, Any] | Exception] = []
        for observation, entries in zip(observations, steering, strict=True):
            try:
                results.append(self.policy.infer(observation, entries))
            except Exception as err:  # handed to its own request
                results.append(err)
        return results


def _in_daemon_thread(loop: asyncio.AbstractEventLoop, fn: Callable, *args: Any) -> asyncio.Future:
    """Return a future of `fn(*args)` run in a new daemon thread (the loop's default executor joins its threads
    at shutdown, without a timeout before Python 3.12)."""
    future = loop.create_future()

    def settle(result: Any, error: Exception | None) -> None:
        if future.cancelled():
            return
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)

    def main() -> None:
        try:
            result, error = fn(*args), None
        except Exception as err:  # handed to the awaiting request
            result, error = None, err
        with contextlib.suppress(RuntimeError):  # the loop has closed: the server stopped, nobody waits
            loop.call_soon_threadsafe(settle, result, error)

    threading.Thread(target=main, name="policy-inference", daemon=True).start()
    return future
