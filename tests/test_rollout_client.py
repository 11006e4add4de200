"""Rollout policies: RemotePolicy's exact messages, header, errors and retries against a recording websocket
server; LocalPolicy steers the tiny pi0.5 (α = 0 equal to the plain policy bit for bit)."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_serve import fixed_threads, libero_observations
from websockets.sync.server import serve

from steering_core.pi05.policy import Pi05Policy
from steering_core.rollout.client import LocalPolicy, PolicyServerError, RemotePolicy
from steering_core.serve import codec
from steering_core.serve.catalog import SteeringVector
from steering_core.serve.policy import SteeredPi05Policy
from steering_core.serve.request import AppliedSteering
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

ACTIONS = np.arange(70, dtype=np.float32).reshape(10, 7)
STEER = [{"pair": "open_vs_close", "layer": 1, "alpha": 2.0, "direction": "sae", "alpha_units": "residual_norm"}]


class RecordingServer:
    """A websocket server in a thread that records each connection's headers and decoded messages; it answers
    observations with ACTIONS, control messages with {}, and a prompt "fail" with a text frame."""

    def __init__(self, port: int = 0, api_key: str | None = None) -> None:
        self.headers: list[dict] = []
        self.messages: list[dict] = []
        self.api_key = api_key
        self.server = serve(self.handle, "127.0.0.1", port, process_request=self.check_key)
        self.port = self.server.socket.getsockname()[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def check_key(self, connection, request):
        self.headers.append(dict(request.headers.raw_items()))
        if self.api_key and request.headers.get("Authorization") != f"Api-Key {self.api_key}":
            return connection.respond(401, "bad key\n")
        return None

    def handle(self, ws):
        ws.send(codec.pack({"model": "recording"}))
        for message in ws:
            obs = codec.unpack(message)
            self.messages.append(obs)
            if "__ctrl__" in obs:
                ws.send(codec.pack({}))
            else:
                failed = obs.get("prompt") == "fail"
                ws.send("bad request: prompt: fail" if failed else codec.pack({"actions": ACTIONS}))

    def stop(self):
        self.server.shutdown()
        self.thread.join(10)


@contextlib.contextmanager
def recording(**kwargs):
    server = RecordingServer(**kwargs)
    try:
        yield server
    finally:
        server.stop()


def observation(prompt: str = "open the top drawer of the cabinet") -> dict:
    return {"observation/image": np.zeros((4, 4, 3), np.uint8), "observation/wrist_image": np.ones((4, 4, 3), np.uint8),
            "observation/state": np.arange(8, dtype=np.float64), "prompt": prompt}


def test_remote_policy_sends_openpi_messages_with_steering_and_key():
    with recording(api_key="s3cret") as server:
        with RemotePolicy(f"127.0.0.1:{server.port}", STEER, api_key="s3cret", experiment="exp1") as policy:
            assert policy.metadata == {"model": "recording"}
            policy.episode_start("open the top drawer of the cabinet", 3)
            actions = policy.infer(observation())
            policy.episode_end(True)
            with pytest.raises(PolicyServerError, match=r"127\.0\.0\.1:\d+: bad request: prompt: fail$"):
                policy.infer(observation("fail"))
    assert actions.dtype == np.float32 and np.array_equal(actions, ACTIONS)
    assert server.headers[0]["Authorization"] == "Api-Key s3cret"
    start, obs, end, _ = server.messages
    assert start == {"__ctrl__": "episode_start", "__experiment__": "exp1",
                     "__task__": "open the top drawer of the cabinet", "__episode_id__": 3}
    assert type(start["__episode_id__"]) is int and end == {"__ctrl__": "episode_end", "__success__": True}
    assert set(obs) == {*observation(), "steering"} and obs["steering"] == STEER
    assert all(np.array_equal(obs[k], v) and obs[k].dtype == v.dtype for k, v in observation().items()
               if isinstance(v, np.ndarray))


def test_remote_policy_without_steering_sends_the_bare_observation():
    with recording() as server, RemotePolicy(f"ws://127.0.0.1:{server.port}") as policy:
        policy.infer(observation())
    assert set(server.messages[0]) == set(observation()) and "Authorization" not in server.headers[0]


def test_a_wrong_key_is_refused_at_once():
    with recording(api_key="s3cret") as server:
        start = time.monotonic()
        with pytest.raises(PolicyServerError, match=r"refused the connection with HTTP 401 \(wrong or missing API"):
            RemotePolicy(f"127.0.0.1:{server.port}", api_key="wrong", connect_timeout=30)
        assert time.monotonic() - start < 5  # not retried


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_connection_is_retried_for_a_bounded_time():
    port = free_port()
    with pytest.raises(PolicyServerError, match=rf"no policy server at ws://127\.0\.0\.1:{port} after 0\.3 s"):
        RemotePolicy(f"127.0.0.1:{port}", connect_timeout=0.3, retry_interval=0.1)
    servers = []
    timer = threading.Timer(0.5, lambda: servers.append(RecordingServer(port)))
    timer.start()
    try:
        with RemotePolicy(f"127.0.0.1:{port}", connect_timeout=20, retry_interval=0.1) as policy:
            assert policy.metadata == {"model": "recording"}
    finally:
        timer.join()
        for server in servers:
            server.stop()


def test_local_policy_steers_and_alpha_zero_is_the_plain_policy(tmp_path):
    arch = tiny_arch()
    checkpoint = write_pi05_checkpoint(tmp_path / "ckpt", arch, seed=3)
    tokenizer = write_tokenizer(tmp_path / "tokenizer.model")
    policy = Pi05Policy.from_checkpoint(checkpoint, arch, device="cpu", tokenizer_path=tokenizer)
    served = SteeredPi05Policy(policy, noise_seed=7)
    direction = torch.randn(arch.width, generator=torch.Generator().manual_seed(0))
    vector = SteeringVector("open_vs_close", 1, "sae", direction / direction.norm(), float(direction.norm()),
                            Path("sae_direction.safetensors"), "residual", mean_residual_norm=5.0)
    obs = libero_observations(tmp_path / "demo", frames=1, image_size=32)[0]
    with fixed_threads():
        plain = LocalPolicy(served).infer(obs)
        zero = LocalPolicy(served, [AppliedSteering(vector, 0.0)]).infer(obs)
        steered_policy = LocalPolicy(served, [AppliedSteering(vector, 4.0)])
        steered = steered_policy.infer(obs)
    assert plain.shape == (10, 7) and plain.dtype == np.float32
    assert zero.tobytes() == plain.tobytes() and np.abs(steered - plain).max() > 1e-4
    steered_policy.episode_start("task", 0)
    steered_policy.episode_end(False)
    assert (steered_policy.episodes_started, steered_policy.episodes_ended) == (1, 1)


def test_batched_calls_answer_each_observation_as_alone_in_process_and_through_the_server(tmp_path):
    """K environments share one policy call per replan: `infer_batch` in process, and as one batched request to a
    served policy; each row equals its observation alone, within float32 rounding (the rows' batch positions)."""
    from helpers_serve import assert_actions_match, running, write_vectors

    from steering_core.serve import PolicyServer, VectorCatalog

    arch = tiny_arch()
    checkpoint = write_pi05_checkpoint(tmp_path / "ckpt", arch, seed=3)
    tokenizer = write_tokenizer(tmp_path / "tokenizer.model")
    policy = Pi05Policy.from_checkpoint(checkpoint, arch, device="cpu", tokenizer_path=tokenizer)
    served = SteeredPi05Policy(policy, noise_seed=7)
    catalog = VectorCatalog.scan(write_vectors(tmp_path / "vectors", arch.width))
    observations = libero_observations(tmp_path / "demo", frames=3, image_size=32)
    steered = LocalPolicy(served, [AppliedSteering(catalog.get("open_vs_close", 1), 4.0)])
    with fixed_threads():
        alone = [steered.infer(obs) for obs in observations]
        together = steered.infer_batch(observations)
        with running(PolicyServer(served, catalog)) as server, \
                RemotePolicy(f"127.0.0.1:{server.port}", [STEER[0] | {"alpha": 4.0}], connect_timeout=30) as remote:
            remote_rows = remote.infer_batch(observations)
    assert len(together) == len(remote_rows) == 3
    for mine, theirs, there in zip(together, alone, remote_rows, strict=True):
        assert mine.shape == (10, 7)
        assert_actions_match(mine, theirs)
        assert_actions_match(there, theirs)
    assert np.abs(alone[0] - LocalPolicy(served).infer(observations[0])).max() > 1e-4  # steering applies
