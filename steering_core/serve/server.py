"""A websocket policy server speaking openpi's protocol, with per-request steering (spec "Serving protocol").

On connect the client gets the metadata; each binary msgpack observation gets one binary msgpack result
(`actions`, `policy_timing`, `server_timing`, and the `steering` applied). Unlike openpi's server, a bad request
gets one line of text naming the key (never a traceback) and the connection stays open for the next request.
Control messages (`__ctrl__` episode_start / episode_end, openpi's current client) record episodes
(steering_core.serve.episodes). With an api key, an upgrade without `Authorization: Api-Key <key>` gets HTTP 401.
`GET /healthz` answers 200 "OK\\n" on the same port, key or not, from the moment the server listens: after the
policy's `warm_up()` (if it has one) has run; any other plain HTTP request gets 426 (at `/`) or 404, another
method than GET 405, and a malformed one a one-line warning in the log. An address in use is one line naming it.
One model serves every connection: requests run in order per connection, and requests of all connections that arrive
within `batch_wait_ms` of the oldest waiting one share one policy call of up to `max_batch` rows (dynamic batching,
steering_core.serve.batching; a request may itself carry a leading batch dimension), each row with its own prompt,
steering and noise. One call runs at a time, in a worker thread so the event loop keeps answering pings; a request
without actions within the inference timeout is answered with an error.
Bounds per server: `max_connections` connections (at the cap the connection idle longest, if idle for
`evict_idle_s`, is closed to admit a new one; otherwise the new one is closed with 1013, try again later; a
connection that sends nothing for `idle_timeout_s` is closed, so idle sockets cannot hold the cap), each reading
at most `max_queue` frames ahead of the request being answered, each frame at most TRANSPORT_LIMIT_FACTOR x
`max_message_bytes` (websockets closes a connection sending more with 1009).
SIGINT/SIGTERM (or `request_stop`) stop accepting connections, let the request in flight finish and be
answered, then close every connection with 1001 (going away).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import http
import logging
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

from steering_core.serve import codec
from steering_core.serve.auth import HEADER, SCHEME, authorized
from steering_core.serve.batching import (
    DEFAULT_BATCH_WAIT_MS,
    Batcher,
    InferenceFailed,
)
from steering_core.serve.catalog import DEFAULT_DIRECTIONS, RANDOM_DERIVATION, VectorCatalog
from steering_core.serve.episodes import (
    CTRL_KEY,
    END_FIELDS,
    START_FIELDS,
    ConnectionEpisodes,
    EpisodeLog,
    EpisodeNotRecorded,
)
from steering_core.serve.policy import ServedPolicy
from steering_core.serve.request import (
    ALPHA_UNITS,
    DEFAULT_ALPHA_UNITS,
    DEFAULT_MODE,
    MAX_ALPHA,
    MODES,
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
TRANSPORT_LIMIT_FACTOR = 2  # messages above limit x factor are cut off by websockets itself (close 1009)
# pi0.5 answers in well under a second on a GPU and in seconds on a CPU; far longer means a stuck device
DEFAULT_INFERENCE_TIMEOUT_S = 120.0
# openpi's LIBERO evaluation runs one client per environment worker; worst-case buffered input is
# max_connections x (max_queue + 1) x TRANSPORT_LIMIT_FACTOR x max_message_bytes (1.5 GiB with the defaults)
DEFAULT_MAX_CONNECTIONS = 16
DEFAULT_MAX_QUEUE = 2  # an openpi client sends one observation and waits for its actions
# an openpi client sends a frame every few control steps and resets its env between episodes in seconds: a
# connection silent this long is gone or idle on purpose, and holds a place another client may need
DEFAULT_IDLE_TIMEOUT_S = 300.0
DEFAULT_EVICT_IDLE_S = 30.0  # at the connection cap, the connection idle longest gives way if idle this long
DEFAULT_MAX_BATCH = DEFAULT_MAX_CONNECTIONS  # rows per policy call: one frame from every connection
MAX_REPLY_CHARS = 1000  # an error reply is one line, cut to this length


class _OneLineHandshakeErrors(logging.Filter):
    """websockets logs a failed opening handshake (no valid HTTP request, a failed upgrade check) at ERROR with
    a traceback: keep one WARNING line naming the problem (a port scan or a stray client is not a server error)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.msg == "opening handshake failed" and record.exc_info:
            err = record.exc_info[1]
            causes = [err]
            while causes[-1].__cause__ is not None:
                causes.append(causes[-1].__cause__)
            record.levelno, record.levelname = logging.WARNING, logging.getLevelName(logging.WARNING)
            record.msg, record.args = "refused a malformed connection: %s", ("; ".join(map(str, causes)),)
            record.exc_info = record.exc_text = None
        return True


transport_logger = logging.getLogger(f"{__name__}.transport")
transport_logger.addFilter(_OneLineHandshakeErrors())

# HTTP methods other than GET: websockets closes their connection unanswered; these get 405 Method Not Allowed
_NOT_GET = frozenset({b"POST", b"PUT", b"DELETE", b"PATCH", b"HEAD", b"OPTIONS", b"CONNECT", b"TRACE"})


class _MethodCheckingConnection(ServerConnection):
    """A connection that answers a request of another method than GET (`POST /healthz`) with 405 Method Not
    Allowed and closes; websockets itself would close it without an HTTP answer."""

    _line: bytes | None = b""  # the request line's start, until its method is known (None: known)
    _refused = False

    def data_received(self, data: bytes) -> None:
        if self._line is not None and self.request is None:
            self._line += data
            if b" " in self._line or b"\n" in self._line or len(self._line) > 16:
                method, self._line = self._line.split(b" ", 1)[0], None
                if method in _NOT_GET:
                    self._refuse(method.decode())
                    return
        super().data_received(data)

    def _refuse(self, method: str) -> None:
        self._refused = True
        body = b"" if method == "HEAD" else (f"method {method} not allowed: GET {HEALTH_PATH} for the health check, "
                                             "or connect with a websocket client (openpi-client)\n").encode()
        self.transport.write(b"HTTP/1.1 405 Method Not Allowed\r\nAllow: GET\r\nConnection: close\r\n"
                             b"Content-Type: text/plain; charset=utf-8\r\n"
                             + f"Content-Length: {len(body)}\r\n\r\n".encode() + body)
        self.transport.close()
        host, port = (self.transport.get_extra_info("peername") or ("?", 0))[:2]
        logger.info("answered %s from %s:%s with 405 Method Not Allowed", method, host, port)

    async def handshake(self, *args: Any, **kwargs: Any) -> None:
        """websockets' handshake; a refused method's connection (closed before any request) ends quietly."""
        try:
            await super().handshake(*args, **kwargs)
        except Exception:
            if not self._refused:
                raise


class PolicyServer:
    """Serve `policy` with the vectors of `catalog` on host:port (port 0: a free port, see `port` once ready).

    Requests with |α| above `max_alpha` (residual_norm units; clamps: level fractions) are refused, and so are
    steerings of the last language-model layer when the policy's metadata gives its depth (`steerable.lm.layers`,
    as Pi05Policy's does).
    With `api_key`, only upgrades carrying it are accepted. Finished episodes go to `episode_log` (default: one
    kept in memory only); `episodes` lists the last EPISODES_KEPT. `inference_timeout_s`, `max_connections` and
    `max_queue` bound a request's wait and the server's memory; `max_batch` (rows) and `batch_wait_ms` shape the
    policy calls (steering_core.serve.batching); `max_batch` 1 serves one request per call.
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
        max_alpha: float = MAX_ALPHA,
        api_key: str | None = None,
        episode_log: EpisodeLog | None = None,
        inference_timeout_s: float = DEFAULT_INFERENCE_TIMEOUT_S,
        max_connections: int = DEFAULT_MAX_CONNECTIONS,
        max_queue: int = DEFAULT_MAX_QUEUE,
        max_batch: int = DEFAULT_MAX_BATCH,
        batch_wait_ms: float = DEFAULT_BATCH_WAIT_MS,
        idle_timeout_s: float = DEFAULT_IDLE_TIMEOUT_S,
        evict_idle_s: float = DEFAULT_EVICT_IDLE_S,
    ) -> None:
        self.policy = policy
        self.catalog = catalog or VectorCatalog()
        self.limits = SteeringLimits(max_alpha, lm_depth(policy.metadata))
        state_dim = policy.metadata.get("state_dim")  # the widest state the policy takes, when it says
        self.max_state_dim = state_dim if isinstance(state_dim, int) else None
        self.default_steering = tuple(default_steering)
        self.host, self.port = host, port
        self.max_message_bytes = max_message_bytes
        self.inference_timeout_s, self.max_connections, self.max_queue = inference_timeout_s, max_connections, max_queue
        self.batcher = Batcher(policy, max_batch=max_batch, batch_wait_ms=batch_wait_ms,
                               inference_timeout_s=inference_timeout_s, open_connections=lambda: len(self._connections))
        self.max_batch, self.batch_wait_ms = self.batcher.max_batch, self.batcher.batch_wait_ms
        if not idle_timeout_s > 0 or not evict_idle_s >= 0:
            raise ValueError(f"idle_timeout_s {idle_timeout_s!r} and evict_idle_s {evict_idle_s!r}: expected a "
                             "positive number of seconds and a non-negative one")
        self.idle_timeout_s, self.evict_idle_s = idle_timeout_s, evict_idle_s
        self.api_key = api_key
        self.episode_log = episode_log or EpisodeLog()
        self.metadata = self._metadata()
        self._encoded_metadata = codec.pack(self.metadata)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._connections: set[ServerConnection] = set()
        self._busy: set[ServerConnection] = set()
        self._active: dict[ServerConnection, float] = {}  # when each connection last sent a frame (or opened)

    def run(self) -> None:
        """Serve until SIGINT or SIGTERM (blocking; call from the main thread)."""
        asyncio.run(self.serve(install_signal_handlers=True))

    async def serve(self, *, ready: Callable[[], None] | None = None, install_signal_handlers: bool = False) -> None:
        """Serve until `request_stop`; call `ready()` once listening."""
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        batches = self.batcher.start()
        if install_signal_handlers:
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._loop.add_signal_handler(signum, self._stop.set)
        warm_up = getattr(self.policy, "warm_up", None)
        if warm_up is not None:  # before listening: once /healthz answers, no request pays a compilation
            await asyncio.to_thread(warm_up, self.max_batch)  # every row count a call may have
        try:
            server = await serve(
                self._handle, self.host, self.port, compression=None, process_request=self._check_request,
                max_size=self.max_message_bytes * TRANSPORT_LIMIT_FACTOR, max_queue=self.max_queue,
                logger=transport_logger, create_connection=_MethodCheckingConnection,
            )
        except OSError as err:  # the address in use, not this machine's, a port below 1024 without privileges
            batches.cancel()
            raise ValueError(listen_error_line(self.host, self.port, err)) from None
        try:
            self.port = server.sockets[0].getsockname()[1]
            logger.info("serving on ws://%s:%d (health: http://%s:%d%s)%s", self.host, self.port, self.host,
                        self.port, HEALTH_PATH, "; clients must send the api key" if self.api_key else "")
            if ready is not None:
                ready()
            await self._stop.wait()
            await self._shutdown(server)
        finally:
            server.close()
            await server.wait_closed()
        batches.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await batches

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
        """Answer the health check and plain HTTP requests; refuse an upgrade without the api key (when one is set)."""
        if request.path == HEALTH_PATH:
            return connection.respond(http.HTTPStatus.OK, "OK\n")
        if "websocket" not in ",".join(request.headers.get_all("Upgrade")).lower():
            if request.path != "/":
                return connection.respond(http.HTTPStatus.NOT_FOUND, f"not found; health check: {HEALTH_PATH}\n")
            response = connection.respond(http.HTTPStatus.UPGRADE_REQUIRED, "an openpi policy server: connect with a "
                                          f"websocket client (openpi-client); health check: {HEALTH_PATH}\n")
            response.headers["Upgrade"] = "websocket"
            return response
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
        if len(self._connections) >= self.max_connections and not await self._evict_idlest():
            logger.warning("refused a connection from %s: %d connections open (serve --max-connections)",
                           _address(ws), len(self._connections))
            await ws.close(CloseCode.TRY_AGAIN_LATER, f"the server has its limit of {self.max_connections} "
                                                      "connections (--max-connections); try again later")
            return
        self._connections.add(ws)
        self._active[ws] = time.monotonic()
        episodes = ConnectionEpisodes(_address(ws), self.episode_log)
        try:
            await ws.send(self._encoded_metadata)
            previous_total_ms = None
            while not self._stop.is_set():
                try:
                    message = await asyncio.wait_for(ws.recv(), self.idle_timeout_s)
                except TimeoutError:
                    logger.info("closed %s: idle for %g s (serve --idle-timeout-s)", _address(ws), self.idle_timeout_s)
                    await ws.close(CloseCode.GOING_AWAY, f"idle for {self.idle_timeout_s:g} s (--idle-timeout-s)")
                    break
                start = self._active[ws] = time.monotonic()
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
            self._active.pop(ws, None)
            episodes.close()

    async def _evict_idlest(self) -> bool:
        """Close the connection idle longest, if it has no request in flight and has been idle `evict_idle_s`;
        return whether one was (its place is free at once)."""
        now = time.monotonic()
        idle = [(now - self._active[c], c) for c in self._connections if c not in self._busy and c in self._active]
        seconds, idlest = max(idle, key=lambda entry: entry[0], default=(0.0, None))
        if idlest is None or seconds < self.evict_idle_s:
            return False
        logger.warning("closed %s, idle for %.0f s, to admit a new connection (serve --max-connections)",
                       _address(idlest), seconds)
        self._connections.discard(idlest)
        self._active.pop(idlest, None)
        await idlest.close(CloseCode.TRY_AGAIN_LATER, f"idle for {seconds:.0f} s while the server is full "
                                                      "(--max-connections); reconnect when you next need it")
        return True

    async def _answer(self, message: str | bytes, previous_total_ms: float | None,
                      episodes: ConnectionEpisodes) -> tuple[str | bytes, bool]:
        """Return the encoded reply, or the text of the error (the connection stays usable either way), and
        whether the message was a control message."""
        try:
            request = self._unpack(message)
            if isinstance(request, dict) and CTRL_KEY in request:
                return codec.pack(episodes.control(request)), True
            observation, steering, rows = self._read(request)
            result, timing = await self.batcher.submit(observation, steering, rows)
            _check_actions(result, steering)
            episodes.inferred()
            result[STEERING_KEY] = [s.describe() for s in steering]
            result["server_timing"] = timing
            if previous_total_ms is not None:
                timing["prev_total_ms"] = previous_total_ms
            return codec.pack(result), False
        except (codec.WireError, RequestError) as err:
            reply = _one_line(f"bad request: {err}")
            logger.warning("%s", reply)
            return reply, False
        except InferenceFailed as err:
            reply = _one_line(f"inference failed (the server keeps serving): {err}")
            logger.warning("%s", reply)
            return reply, False
        except EpisodeNotRecorded as err:  # logged naming the file; the control message was applied
            return _one_line(str(err)), True
        except Exception as err:  # the policy's own error: its traceback goes to the log, one line to the client
            logger.exception("inference failed")
            return _one_line(f"inference failed (the server keeps serving): {type(err).__name__}: {err}"), False

    def _unpack(self, message: str | bytes) -> Any:
        if isinstance(message, str):
            raise RequestError(None, "got a text frame; send the observation as binary msgpack (openpi-client does)")
        if len(message) > self.max_message_bytes:
            raise RequestError("message", f"{len(message)} bytes is over the server's limit of "
                                          f"{self.max_message_bytes} bytes (--max-message-mb)")
        return codec.unpack(message)

    def _read(self, observation: Any) -> tuple[dict[str, Any], tuple[AppliedSteering, ...], int]:
        rows = check_observation(observation, self.max_batch, self.max_state_dim)
        if STEERING_KEY in observation:
            steering = parse_steering(observation.pop(STEERING_KEY), self.catalog, limits=self.limits)
            return observation, steering, rows
        return observation, self.default_steering, rows

    def _metadata(self) -> dict[str, Any]:
        return {
            **self.policy.metadata,
            "steering": {
                "request_key": STEERING_KEY,
                "entry": {"pair": "str", "layer": "int", "alpha": "float",
                          "direction": f"str: a method of `vectors` or random_<k> (default: "
                                       f"{' if stored, else '.join(DEFAULT_DIRECTIONS)})",
                          "mode": f"one of {list(MODES)} (default {DEFAULT_MODE})",
                          "alpha_units": f"add mode: one of {list(ALPHA_UNITS)} (default {DEFAULT_ALPHA_UNITS})"},
                "modes": {"add": "alpha (in alpha_units) times the unit vector is added",
                          "clamp": "each steered token's projection on the unit vector is set to m- + alpha * "
                                   "(m+ - m-), (m-, m+) the vector's levels: alpha 0 the negative concept's mean, "
                                   "1 the positive's; no alpha_units, no random controls"},
                "alpha_units": {
                    "residual_norm": "alpha * mean_residual_norm * vector is added (the evaluation's unit)",
                    "vector": "alpha * norm * vector is added (the method's vector before normalising, times alpha)",
                },
                "max_alpha": self.limits.max_alpha,
                "applied_at": "language-model residual stream, the prompt's instruction tokens",
                "random_controls": RANDOM_DERIVATION,
                "default": [s.describe() for s in self.default_steering],
                "vectors": self.catalog.describe(),
            },
            "server": {
                "inference": (f"batched: requests arriving within {self.batch_wait_ms:g} ms of the oldest waiting "
                              f"one share one policy call of up to {self.max_batch} rows, each row with its own "
                              "prompt, steering and noise; one call at a time"),
                "max_batch": self.max_batch,
                "batch_wait_ms": self.batch_wait_ms,
                "batched_requests": "a request may carry a leading batch dimension (images (B, H, W, 3), state "
                                    "(B, D), B prompts), answered with actions (B, H, 7)",
                "errors": "a text frame of one line naming the key; the connection stays open",
                "max_message_bytes": self.max_message_bytes,
                "inference_timeout_s": self.inference_timeout_s,
                "max_connections": self.max_connections,
                "idle_timeout_s": self.idle_timeout_s,
                "evict_idle_s": self.evict_idle_s,
                "max_queue": self.max_queue,
                "api_key_required": self.api_key is not None,
                "control_messages": {"episode_start": list(START_FIELDS), "episode_end": list(END_FIELDS),
                                     "reply": "{'__ack__': <__ctrl__ value>}, as openpi's server"},
            },
        }


def _check_actions(result: dict[str, Any], steering: tuple[AppliedSteering, ...]) -> None:
    """Raise InferenceFailed unless the result holds a real-valued, finite `actions` array."""
    actions = result.get("actions")
    if not isinstance(actions, np.ndarray) or actions.dtype.kind not in "fiu":
        raise InferenceFailed(f"the policy returned no actions array ({type(actions).__name__})")
    if not np.isfinite(actions).all():
        logger.warning("non-finite actions withheld (steering %s)", [s.describe() for s in steering])
        raise InferenceFailed("the policy's actions are not finite; lower |alpha| of the steering entry")


def _one_line(text: str) -> str:
    """Return `text` on one line (every whitespace run, line breaks included, one space), cut to MAX_REPLY_CHARS."""
    text = " ".join(text.split())
    return text if len(text) <= MAX_REPLY_CHARS else text[: MAX_REPLY_CHARS - 3] + "..."


def _address(connection: ServerConnection) -> str:
    host, port = connection.remote_address[:2]
    return f"{host}:{port}"


def check_address_free(host: str, port: int) -> None:
    """Return when `host`:`port` can be bound now (as the server binds it); ValueError naming the address and what
    to do otherwise. For a check before a model loads: the server's own bind says the same if it is taken later."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
        with socket.socket(family, kind, proto) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server does
            sock.bind(address)
    except OSError as err:
        raise ValueError(listen_error_line(host, port, err)) from None


def listen_error_line(host: str, port: int, err: OSError) -> str:
    """Return one line for an address the server cannot listen on, naming it and what to do."""
    if err.errno == errno.EADDRINUSE:
        return (f"{host}:{port} is in use: another server listens there; stop it, or choose another port "
                "(serve --port, or --port 0 for a free one)")
    return f"cannot listen on {host}:{port} ({err.strerror or err}); choose another --host or --port"


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
