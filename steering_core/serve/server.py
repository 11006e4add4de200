"""A websocket policy server speaking openpi's protocol, with per-request steering (spec "Serving protocol").

On connect the client gets the metadata; each binary msgpack observation gets one binary msgpack result
(`actions`, `policy_timing`, `server_timing`, and the `steering` applied). Unlike openpi's server, a bad request
gets a text frame naming the key and the connection stays open for the next request. Control messages
(`__ctrl__` episode_start / episode_end, openpi's current client) record episodes (steering_core.serve.episodes).
With an api key, an upgrade without `Authorization: Api-Key <key>` gets HTTP 401. `GET /healthz` answers
200 "OK\\n" on the same port, key or not. One model serves every connection: requests run in order per
connection and one at a time overall (an asyncio lock), in a worker thread so the event loop keeps answering pings.
SIGINT/SIGTERM (or `request_stop`) stop accepting connections, let the request in flight finish and be
answered, then close every connection with 1001 (going away).
"""

from __future__ import annotations

import asyncio
import contextlib
import http
import logging
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

from steering_core.serve import codec
from steering_core.serve.auth import HEADER, SCHEME, authorized
from steering_core.serve.catalog import RANDOM_DERIVATION, VectorCatalog
from steering_core.serve.episodes import CTRL_KEY, END_FIELDS, START_FIELDS, ConnectionEpisodes, EpisodeLog
from steering_core.serve.policy import ServedPolicy
from steering_core.serve.request import (
    ALPHA_UNITS,
    DEFAULT_ALPHA_UNITS,
    DEFAULT_MAX_ALPHA,
    STEERING_KEY,
    AppliedSteering,
    RequestError,
    SteeringLimits,
    check_observation,
    parse_steering,
)

logger = logging.getLogger(__name__)

HEALTH_PATH = "/healthz"
DEFAULT_MAX_MESSAGE_BYTES = 16 * 2**20  # a LIBERO observation (two 224x224 RGB images) is ~0.3 MB
TRANSPORT_LIMIT_FACTOR = 4  # messages above limit x factor are cut off by websockets itself (close 1009)


class PolicyServer:
    """Serve `policy` with the vectors of `catalog` on host:port (port 0: a free port, see `port` once ready).

    Requests with |α| above `max_alpha` (residual_norm units) are refused, and so are steerings of the last
    language-model layer when the policy's metadata gives its depth (`steerable.lm.layers`, as Pi05Policy's does).
    With `api_key`, only upgrades carrying it are accepted. Finished episodes go to `episode_log` (default: one
    kept in memory only); `episodes` lists the last EPISODES_KEPT.
    """

    def __init__(
        self,
        policy: ServedPolicy,
        catalog: VectorCatalog | None = None,
        *,
        default_steering: Sequence[AppliedSteering] = (),
        host: str = "127.0.0.1",
        port: int = 8000,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        max_alpha: float = DEFAULT_MAX_ALPHA,
        api_key: str | None = None,
        episode_log: EpisodeLog | None = None,
    ) -> None:
        self.policy = policy
        self.catalog = catalog or VectorCatalog()
        self.limits = SteeringLimits(max_alpha, lm_depth(policy.metadata))
        self.default_steering = tuple(default_steering)
        self.host, self.port = host, port
        self.max_message_bytes = max_message_bytes
        self.api_key = api_key
        self.episode_log = episode_log or EpisodeLog()
        self.metadata = self._metadata()
        self._encoded_metadata = codec.pack(self.metadata)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._connections: set[ServerConnection] = set()
        self._busy: set[ServerConnection] = set()
        self._inference: asyncio.Lock | None = None

    def run(self) -> None:
        """Serve until SIGINT or SIGTERM (blocking; call from the main thread)."""
        asyncio.run(self.serve(install_signal_handlers=True))

    async def serve(self, *, ready: Callable[[], None] | None = None, install_signal_handlers: bool = False) -> None:
        """Serve until `request_stop`; call `ready()` once listening."""
        self._loop, self._stop, self._inference = asyncio.get_running_loop(), asyncio.Event(), asyncio.Lock()
        if install_signal_handlers:
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(signum, self._stop.set)
        async with serve(
            self._handle, self.host, self.port, compression=None, process_request=self._check_request,
            max_size=self.max_message_bytes * TRANSPORT_LIMIT_FACTOR,
        ) as server:
            self.port = server.sockets[0].getsockname()[1]
            logger.info("serving on ws://%s:%d (health: http://%s:%d%s)%s", self.host, self.port, self.host,
                        self.port, HEALTH_PATH, "; clients must send the api key" if self.api_key else "")
            if ready is not None:
                ready()
            await self._stop.wait()
            await self._shutdown(server)

    @property
    def episodes(self) -> list[dict[str, Any]]:
        """Return the finished episodes the server keeps, oldest first (JSON-ready records)."""
        return list(self.episode_log.records)

    def request_stop(self) -> None:
        """Ask a running server to shut down (thread-safe); `serve` returns once it has. Asking again, after it
        has stopped, does nothing."""
        if self._loop is not None and self._stop is not None:
            with contextlib.suppress(RuntimeError):  # the loop already closed: the server stopped
                self._loop.call_soon_threadsafe(self._stop.set)

    async def _shutdown(self, server: Server) -> None:
        logger.info("shutting down: %d connection(s), %d request(s) in flight", len(self._connections), len(self._busy))
        server.close(close_connections=False)  # stop listening; busy handlers close after replying
        await asyncio.gather(*(ws.close(CloseCode.GOING_AWAY, "server shutting down")
                               for ws in self._connections - self._busy))
        await server.wait_closed()

    def _check_request(self, connection: ServerConnection, request: Request) -> Response | None:
        """Answer the health check; refuse an upgrade without the api key (when one is set)."""
        if request.path == HEALTH_PATH:
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        values = request.headers.get_all(HEADER)
        if self.api_key is None or authorized(values, self.api_key):
            return None
        logger.warning("refused a connection from %s: %s api key", _address(connection),
                       "wrong" if values else "no")
        response = connection.respond(http.HTTPStatus.UNAUTHORIZED,
                                      f"send the server's api key as the header {HEADER}: {SCHEME} <key>\n")
        response.headers["WWW-Authenticate"] = SCHEME
        return response

    async def _handle(self, ws: ServerConnection) -> None:
        self._connections.add(ws)
        episodes = ConnectionEpisodes(_address(ws), self.episode_log)
        try:
            await ws.send(self._encoded_metadata)
            previous_total_ms = None
            while not self._stop.is_set():
                message = await ws.recv()
                start = time.monotonic()
                self._busy.add(ws)
                try:
                    reply, control = await self._answer(message, previous_total_ms, episodes)
                    await ws.send(reply)
                finally:
                    self._busy.discard(ws)
                if not control:  # as openpi's server: prev_total_ms is the previous observation's
                    previous_total_ms = (time.monotonic() - start) * 1000
            await ws.close(CloseCode.GOING_AWAY, "server shutting down")
        except ConnectionClosed:
            pass
        finally:
            self._connections.discard(ws)
            episodes.close()

    async def _answer(self, message: str | bytes, previous_total_ms: float | None,
                      episodes: ConnectionEpisodes) -> tuple[str | bytes, bool]:
        """Return the encoded reply, or the text of the error (the connection stays usable either way), and
        whether the message was a control message."""
        try:
            request = self._unpack(message)
            if isinstance(request, dict) and CTRL_KEY in request:
                return codec.pack(episodes.control(request)), True
            observation, steering = self._read(request)
            queued = time.monotonic()
            async with self._inference:
                started = time.monotonic()
                result = await asyncio.to_thread(self.policy.infer, observation, steering)
                finished = time.monotonic()
            result = dict(result)
            if not np.isfinite(result["actions"]).all():
                logger.warning("non-finite actions withheld (steering %s)", [s.describe() for s in steering])
                return ("inference failed (the server keeps serving): the policy's actions are not finite; "
                        "lower |alpha| of the steering entry"), False
            episodes.inferred()
            result[STEERING_KEY] = [s.describe() for s in steering]
            result["server_timing"] = {"infer_ms": (finished - started) * 1000, "queue_ms": (started - queued) * 1000}
            if previous_total_ms is not None:
                result["server_timing"]["prev_total_ms"] = previous_total_ms
            return codec.pack(result), False
        except (codec.WireError, RequestError) as err:
            logger.warning("bad request: %s", err)
            return f"bad request: {err}", False
        except Exception:
            logger.exception("inference failed")
            return f"inference failed (the server keeps serving):\n{traceback.format_exc()}", False

    def _unpack(self, message: str | bytes) -> Any:
        if isinstance(message, str):
            raise RequestError(None, "got a text frame; send the observation as binary msgpack (openpi-client does)")
        if len(message) > self.max_message_bytes:
            raise RequestError("message", f"{len(message)} bytes is over the server's limit of "
                                          f"{self.max_message_bytes} bytes (--max-message-mb)")
        return codec.unpack(message)

    def _read(self, observation: Any) -> tuple[dict[str, Any], tuple[AppliedSteering, ...]]:
        check_observation(observation)
        if STEERING_KEY in observation:
            return observation, parse_steering(observation.pop(STEERING_KEY), self.catalog, limits=self.limits)
        return observation, self.default_steering

    def _metadata(self) -> dict[str, Any]:
        return {
            **self.policy.metadata,
            "steering": {
                "request_key": STEERING_KEY,
                "entry": {"pair": "str", "layer": "int", "alpha": "float",
                          "direction": "str: residual (default), mean_difference or random_<k>",
                          "alpha_units": f"one of {list(ALPHA_UNITS)} (default {DEFAULT_ALPHA_UNITS})"},
                "alpha_units": {"residual_norm": "alpha * mean_residual_norm / norm * vector is added (the "
                                                 "evaluation's unit)", "vector": "alpha * vector is added"},
                "max_alpha": self.limits.max_alpha,
                "applied_at": "language-model residual stream, the prompt's instruction tokens",
                "random_controls": RANDOM_DERIVATION,
                "default": [s.describe() for s in self.default_steering],
                "vectors": self.catalog.describe(),
            },
            "server": {
                "inference": "serialised: one model, one request at a time across all connections",
                "errors": "a text frame naming the key; the connection stays open",
                "max_message_bytes": self.max_message_bytes,
                "api_key_required": self.api_key is not None,
                "control_messages": {"episode_start": list(START_FIELDS), "episode_end": list(END_FIELDS),
                                     "reply": "{'__ack__': <__ctrl__ value>}, as openpi's server"},
            },
        }


def _address(connection: ServerConnection) -> str:
    host, port = connection.remote_address[:2]
    return f"{host}:{port}"


def lm_depth(metadata: dict[str, Any]) -> int | None:
    """Return the language-model depth a policy's metadata gives (`steerable.lm.layers`), or None."""
    depth = metadata.get("steerable", {}).get("lm", {}).get("layers")
    return depth if isinstance(depth, int) else None


@contextlib.contextmanager
def serving_in_thread(server: PolicyServer, timeout: float = 60) -> Iterator[PolicyServer]:
    """Run `server` in a background thread (its own event loop) while the block runs; stop and join it after.

    For tests, benchmarks and notebooks; `server.port` is the bound port inside the block.
    """
    ready, failure = threading.Event(), []

    def main() -> None:
        try:
            asyncio.run(server.serve(ready=ready.set))
        except BaseException as err:  # re-raised in the caller's thread
            failure.append(err)
            ready.set()

    thread = threading.Thread(target=main, name="policy-server", daemon=True)
    thread.start()
    if not ready.wait(timeout):
        raise TimeoutError(f"policy server did not start listening within {timeout} s")
    if failure:
        raise failure[0]
    try:
        yield server
    finally:
        server.request_stop()
        thread.join(timeout)
    if failure:
        raise failure[0]
    if thread.is_alive():
        raise TimeoutError(f"policy server did not stop within {timeout} s")
