"""The policies an episode asks for actions (`RolloutPolicy` of steering_core.rollout.episode): in process, or a
running `latent-steering serve` over openpi's websocket protocol.

`RemotePolicy` speaks openpi-client's wire format (steering_core.serve.codec): it reads the server's metadata on
connect, sends each observation with this policy's `steering` entries, and brackets episodes with openpi's
control messages `{"__ctrl__": "episode_start", "__experiment__", "__task__", "__episode_id__"}` and
`{"__ctrl__": "episode_end", "__success__"}`, each answered by a msgpack reply. A text frame is the server's
error message and raises PolicyServerError.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from steering_core.serve import codec
from steering_core.serve.policy import SteeredPi05Policy
from steering_core.serve.request import PROMPT_KEY, STEERING_KEY, AppliedSteering

logger = logging.getLogger(__name__)

CONTROL_KEY = "__ctrl__"
DEFAULT_CONNECT_TIMEOUT_S = 300.0  # a server loading the real checkpoint takes minutes before it listens
RETRY_INTERVAL_S = 2.0


class PolicyServerError(RuntimeError):
    """The policy server refused the connection or answered a message with an error."""


class LocalPolicy:
    """A `SteeredPi05Policy` in this process with a fixed list of steerings; episode messages are only counted."""

    def __init__(self, policy: SteeredPi05Policy, steering: Sequence[AppliedSteering] = ()) -> None:
        self.policy, self.steering = policy, tuple(steering)
        self.episodes_started = self.episodes_ended = 0

    def infer(self, observation: dict[str, Any]) -> np.ndarray:
        """Return the (H, 7) actions of one openpi LIBERO observation."""
        return np.asarray(self.policy.infer(observation, self.steering)["actions"])

    def infer_batch(self, observations: Sequence[dict[str, Any]]) -> list[np.ndarray]:
        """Return the (H, 7) actions of each observation, from one policy call over all of them (each row as if
        alone, up to float32 rounding)."""
        results = self.policy.infer_batch(observations, [self.steering] * len(observations))
        return [np.asarray(result["actions"]) for result in results]

    def episode_start(self, task: str, episode_id: int) -> None:
        self.episodes_started += 1

    def episode_end(self, success: bool) -> None:
        self.episodes_ended += 1


class RemotePolicy:
    """A client of `latent-steering serve` at `address` (`ws://host:port` or `host:port`) adding `steering`
    (entries {pair, layer, alpha, direction, alpha_units}, as the server's `steering` key takes them) to every
    observation. Connection attempts are retried every `retry_interval` seconds for up to `connect_timeout`;
    `api_key` is sent as `Authorization: Api-Key <key>`. Close it (or use it as a context manager) when done.
    """

    def __init__(self, address: str, steering: Sequence[Mapping[str, Any]] = (), *, api_key: str | None = None,
                 experiment: str = "latent-steering rollout",
                 connect_timeout: float = DEFAULT_CONNECT_TIMEOUT_S, retry_interval: float = RETRY_INTERVAL_S) -> None:
        self.url = address if address.startswith(("ws://", "wss://")) else f"ws://{address}"
        self.steering = [dict(entry) for entry in steering]
        self.experiment = experiment
        self._ws = self._connect(api_key, connect_timeout, retry_interval)
        self.metadata = self._receive()

    def _connect(self, api_key: str | None, timeout: float, interval: float) -> ClientConnection:
        headers = {"Authorization": f"Api-Key {api_key}"} if api_key else None
        deadline = time.monotonic() + timeout
        while True:
            try:
                return connect(self.url, compression=None, max_size=None, additional_headers=headers)
            except InvalidStatus as err:
                status = err.response.status_code
                hint = " (wrong or missing API key)" if status in (401, 403) else ""
                raise PolicyServerError(f"policy server at {self.url} refused the connection with HTTP {status}"
                                        f"{hint}") from None
            except OSError as err:  # refused or reset: the server may still be starting
                if time.monotonic() + interval > deadline:
                    raise PolicyServerError(f"no policy server at {self.url} after {timeout:g} s ({err}); start "
                                            "`latent-steering serve` there or check the address") from None
                logger.info("waiting for the policy server at %s (%s)", self.url, err)
                time.sleep(interval)

    def _receive(self) -> Any:
        reply = self._ws.recv()
        if isinstance(reply, str):
            raise PolicyServerError(f"policy server at {self.url}: {reply}")
        return codec.unpack(reply)

    def _call(self, message: dict[str, Any]) -> Any:
        self._ws.send(codec.pack(message))
        return self._receive()

    def infer(self, observation: dict[str, Any]) -> np.ndarray:
        """Return the (H, 7) actions the server computes for one observation with this policy's steering ((B, H, 7)
        for a batched one)."""
        message = {**observation, STEERING_KEY: self.steering} if self.steering else dict(observation)
        return np.asarray(self._call(message)["actions"])

    def infer_batch(self, observations: Sequence[dict[str, Any]]) -> list[np.ndarray]:
        """Return the (H, 7) actions of each observation, from one request carrying them along a leading batch
        dimension (the server answers (B, H, 7))."""
        stacked = {key: np.stack([np.asarray(o[key]) for o in observations]) for key in observations[0]
                   if key != PROMPT_KEY}
        stacked[PROMPT_KEY] = [str(o[PROMPT_KEY]) for o in observations]
        return list(self.infer(stacked))

    def episode_start(self, task: str, episode_id: int) -> None:
        self._call({CONTROL_KEY: "episode_start", "__experiment__": self.experiment, "__task__": task,
                    "__episode_id__": int(episode_id)})

    def episode_end(self, success: bool) -> None:
        self._call({CONTROL_KEY: "episode_end", "__success__": bool(success)})

    def close(self) -> None:
        self._ws.close()

    def __enter__(self) -> RemotePolicy:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()
