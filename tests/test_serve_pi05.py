"""The served pi0.5 policy (tiny checkpoint) through the real openpi client equals `Pi05Policy.infer` bit for
bit, plain and steered at the instruction tokens; `latent-steering serve` starts, serves and stops on a signal,
its actions (another process, the same kernel settings) equal to direct ones up to float32 rounding."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_serve import (
    assert_actions_match,
    fixed_threads,
    libero_observations,
    port_from_log,
    run_openpi_client,
    running,
    server_env,
    write_vectors,
)
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

from steering_core.pi05.policy import Pi05Policy
from steering_core.pi05.steering import Steering
from steering_core.serve import PolicyServer, SteeredPi05Policy, VectorCatalog
from steering_core.serve.codec import pack, unpack
from steering_core.serve.request import parse_steering
from steering_core.storage.fileio import write_json
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

ARCH = tiny_arch()
LATENT_STEERING = str(Path(sys.executable).parent / "latent-steering")  # the console script of this venv
SEED = 7


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("pi05")
    checkpoint = write_pi05_checkpoint(folder / "ckpt", ARCH, seed=3)
    tokenizer = write_tokenizer(folder / "tokenizer.model")
    vectors = write_vectors(folder / "latent_steering", ARCH.width)
    policy = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu", tokenizer_path=tokenizer)
    return checkpoint, tokenizer, vectors, policy


@pytest.fixture(autouse=True)
def one_thread():
    """Each test computes actions with one intra-op thread, like the server subprocess (FIXED_THREADS_ENV)."""
    with fixed_threads():
        yield


@pytest.fixture(scope="module")
def observations(tmp_path_factory):
    return libero_observations(tmp_path_factory.mktemp("demo"), frames=3, image_size=32)


def direct(policy: Pi05Policy, catalog: VectorCatalog, observation: dict, *entries: tuple) -> np.ndarray:
    """`Pi05Policy.infer` with the server's fixed noise and each (pair, layer, alpha[, direction[, "clamp"]]) at
    the instruction tokens: α in residual_norm units, the unit vector times α·R; a clamp sets the projection to
    level fraction α of the vector's levels (m₋, m₊)."""
    noise = torch.randn(policy.action_horizon, policy.action_dim, generator=torch.Generator().manual_seed(SEED))
    mask = policy.instruction_mask(observation["prompt"])
    steering = []
    for pair, layer, alpha, *rest in entries:
        v = catalog.get(pair, layer, *rest[:1])
        steering.append(Steering(v.layer, v.vector, alpha, token_mask=mask, mode="clamp", levels=v.levels)
                        if rest[1:] == ["clamp"] else Steering(v.layer, v.vector, alpha * v.mean_residual_norm,
                                                               token_mask=mask))
    return policy.infer(observation, steering=steering or None, noise=noise)["actions"]


def test_openpi_client_gets_pi05_infer_bit_for_bit(model, observations, tmp_path):
    _, _, vectors, policy = model
    catalog = VectorCatalog.scan(vectors)
    steer = [{"pair": "open_vs_close", "layer": 1, "alpha": 6.0}, {"pair": "on_vs_off", "layer": 2, "alpha": -3.0}]
    control = {"pair": "open_vs_close", "layer": 1, "alpha": 6.0, "direction": "random_1"}
    clamp = [{"pair": "open_vs_close", "layer": 1, "alpha": 0.5, "direction": "mean_difference", "mode": "clamp"},
             {"pair": "on_vs_off", "layer": 2, "alpha": -3.0}]
    requests = [{"obs": obs} for obs in observations] + [{"obs": obs | {"steering": steer}} for obs in observations] \
        + [{"obs": observations[0] | {"steering": control}}, {"obs": observations[0] | {"steering": clamp}}]
    served = SteeredPi05Policy(policy, noise_seed=SEED)
    served.check_catalog(catalog)
    with running(PolicyServer(served, catalog)) as server:
        [client] = run_openpi_client(tmp_path, server.port, [requests])
    replies = [result["reply"]["actions"] for result in client["results"]]
    wanted = [direct(policy, catalog, obs) for obs in observations] + \
        [direct(policy, catalog, obs, ("open_vs_close", 1, 6.0), ("on_vs_off", 2, -3.0)) for obs in observations] \
        + [direct(policy, catalog, observations[0], ("open_vs_close", 1, 6.0, "random_1")),
           direct(policy, catalog, observations[0], ("open_vs_close", 1, 0.5, "mean_difference", "clamp"),
                  ("on_vs_off", 2, -3.0))]
    for reply, actions in zip(replies, wanted, strict=True):
        assert reply.shape == (10, 7) and reply.dtype == actions.dtype
        assert reply.tobytes() == actions.tobytes()
    for plain, steered in zip(replies[:3], replies[3:6], strict=True):
        assert np.abs(plain - steered).max() > 1e-4  # steering changes the actions
    assert np.abs(replies[6] - replies[0]).max() > 1e-4  # and so does its random control
    assert np.abs(replies[7] - direct(policy, catalog, observations[0], ("on_vs_off", 2, -3.0))).max() > 1e-4
    assert [s["mode"] for s in client["results"][7]["reply"]["steering"]] == ["clamp", "add"]
    metadata = client["metadata"]
    assert metadata["model"] == "pi05" and metadata["noise_seed"] == SEED
    assert metadata["steering"]["vectors"] == catalog.describe()


GATE_TIMEOUT_S = 300  # generous: only a broken server leaves requests unsent this long


class HeldFirstCall:
    """The served policy with its first call held until every other of `total` requests waits in the server, so
    the next call takes them all whatever the machine's speed; records each call's requests."""

    def __init__(self, served: SteeredPi05Policy, total: int) -> None:
        self.served, self.total, self.server = served, total, None
        self.calls: list[int] = []

    @property
    def metadata(self):
        return self.served.metadata

    def _hold(self, requests: int) -> None:
        if not self.calls:
            deadline = time.monotonic() + GATE_TIMEOUT_S
            while self.server.batcher.waiting_requests + requests < self.total and time.monotonic() < deadline:
                time.sleep(0.01)
        self.calls.append(requests)

    def infer(self, observation, steering):
        self._hold(1)
        return self.served.infer(observation, steering)

    def infer_batch(self, observations, steering):
        self._hold(len(observations))
        return self.served.infer_batch(observations, steering)


def test_concurrent_clients_share_a_call_and_each_row_equals_its_request_alone(model, observations, tmp_path):
    """Ten openpi clients at once, with mixed steering (pairs, layers, α units, a random control, two clamps of one
    layer, none) and one request carrying two frames: two calls of the served policy answer them all (the two
    clamps in separate calls of the model), each row as its request alone."""
    _, _, vectors, policy = model
    catalog = VectorCatalog.scan(vectors)
    open_close = {"pair": "open_vs_close", "layer": 1, "alpha": 6.0}
    entries = [None, open_close, {"pair": "on_vs_off", "layer": 2, "alpha": -3.0},
               [open_close, {"pair": "on_vs_off", "layer": 2, "alpha": -3.0}],
               open_close | {"direction": "random_1"}, open_close | {"direction": "mean_difference"},
               {"pair": "on_vs_off", "layer": 1, "alpha": 0.5, "alpha_units": "vector"},
               open_close | {"alpha": 0.8, "mode": "clamp"},
               {"pair": "on_vs_off", "layer": 1, "alpha": 0.2, "direction": "sae_top_k", "mode": "clamp"}]
    single = [observations[i % 3] | ({"steering": entry} if entry else {}) for i, entry in enumerate(entries)]
    batched = {key: np.stack([observations[1][key], observations[2][key]]) for key in observations[0]
               if key != "prompt"} | {"prompt": [observations[1]["prompt"], "put the bowl on the plate"],
                                      "steering": open_close}
    requests = [*single, batched]
    served = SteeredPi05Policy(policy, noise_seed=SEED)
    held = HeldFirstCall(served, total=len(requests))
    with running(PolicyServer(held, catalog, max_batch=16, inference_timeout_s=2 * GATE_TIMEOUT_S)) as server:
        held.server = server
        clients = run_openpi_client(tmp_path, server.port, [[{"obs": request}] for request in requests])
    replies = [client["results"][0]["reply"] for client in clients]
    # the first call takes what arrived within the batching window, the next (if any) all the others
    assert len(held.calls) <= 2 and sum(held.calls) == len(requests) and max(held.calls) >= len(requests) / 2
    assert sorted({reply["server_timing"]["batch_requests"] for reply in replies}) == sorted(set(held.calls))

    def alone(observation):
        entry = observation.get("steering")
        steering = parse_steering(entry, catalog) if entry is not None else ()
        return served.infer({k: v for k, v in observation.items() if k != "steering"}, steering)["actions"]

    for reply, request in zip(replies[:-1], single, strict=True):
        assert_actions_match(reply["actions"], alone(request))
    rows = [{key: value[i] for key, value in batched.items() if key != "steering"} for i in range(2)]
    assert replies[-1]["actions"].shape == (2, 10, 7)
    for row, actions in zip(rows, replies[-1]["actions"], strict=True):
        assert_actions_match(actions, alone(row | {"steering": open_close}))
    plain = alone(single[0])
    assert np.abs(alone(single[3]) - plain).max() > 1e-2  # the steering moves the same frame's actions (a leak of
    # another row's steering into the plain request would move it as much)


def test_vectors_that_do_not_fit_the_model_are_refused(model, tmp_path):
    _, _, _, policy = model
    catalog = VectorCatalog.scan(write_vectors(tmp_path / "wide", ARCH.width + 1, sae_layer=1, plain_layer=9))
    with pytest.raises(ValueError, match=r"do not fit this model \(layers 0..3, width 64\)") as err:
        SteeredPi05Policy(policy).check_catalog(catalog)
    assert "layer 9, width 65" in str(err.value)


def test_last_layer_huge_alpha_and_non_finite_actions_get_one_line_errors(model, observations, tmp_path):
    """A finite α of 1e39 overflowed to NaN actions sent as a normal reply; the last LM layer was accepted."""
    _, _, _, policy = model
    catalog = VectorCatalog.scan(write_vectors(tmp_path / "vectors", ARCH.width, plain_layer=ARCH.depth - 1))
    served = SteeredPi05Policy(policy, noise_seed=SEED)
    huge = {"pair": "open_vs_close", "layer": 1, "alpha": 1e39}
    last = {"pair": "open_vs_close", "layer": ARCH.depth - 1, "alpha": 1.0}
    cases = [(100.0, huge, "bad request: steering.alpha: |alpha| is 1e+39 in residual_norm units, above"),
             (100.0, last, f"bad request: steering.layer: layer {ARCH.depth - 1}: the last language-model layer"),
             (float("inf"), huge | {"alpha_units": "vector"}, "inference failed (the server keeps serving): the "
                                                              "policy's actions are not finite")]
    for max_alpha, entry, problem in cases:
        with running(PolicyServer(served, catalog, max_alpha=max_alpha)) as server, \
                connect(f"ws://127.0.0.1:{server.port}", max_size=None) as ws:
            ws.recv()
            ws.send(pack(observations[0] | {"steering": entry}))
            reply = ws.recv(timeout=60)
            assert isinstance(reply, str) and reply.startswith(problem) and "\n" not in reply, reply
    mask = policy.instruction_mask(observations[0]["prompt"])
    with pytest.raises(ValueError, match=r"steering\[0\] \(lm layer 3\): the last language-model layer's output"):
        policy.infer(observations[0], steering=Steering(ARCH.depth - 1, catalog.get("open_vs_close", 1).vector,
                                                        token_mask=mask))


@pytest.mark.slow
def test_serve_command_serves_until_sigint(model, observations, tmp_path):
    checkpoint, tokenizer, vectors, policy = model
    arch_file = write_json(tmp_path / "arch.json", ARCH.model_dump())
    key_file, episodes_file = tmp_path / "api_key", tmp_path / "episodes.jsonl"
    key_file.write_text("s3cret\n")
    command = [LATENT_STEERING, "serve", "--checkpoint-path", str(checkpoint), "--tokenizer-path", str(tokenizer),
               "--arch-file", str(arch_file), "--vectors", str(vectors), "--port", "0", "--device", "cpu",
               "--noise-seed", str(SEED), "--steer", "open_vs_close:2:5.0", "--api-key-file", str(key_file),
               "--episodes-file", str(episodes_file)]
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, env=server_env())
    try:
        port = port_from_log(process)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=10) as response:
            assert response.read() == b"OK\n"
        with pytest.raises(InvalidStatus, match="HTTP 401"):
            connect(f"ws://127.0.0.1:{port}")
        with connect(f"ws://127.0.0.1:{port}", max_size=None, additional_headers={"Authorization": "Api-Key s3cret"}) \
                as ws:
            metadata = unpack(ws.recv())
            assert [(s["pair"], s["layer"], s["alpha"]) for s in metadata["steering"]["default"]] == \
                [("open_vs_close", 2, 5.0)]
            ws.send(pack({"__ctrl__": "episode_start", "__experiment__": "cli", "__task__": "t", "__episode_id__": 4}))
            assert unpack(ws.recv(timeout=10)) == {"__ack__": "episode_start"}
            ws.send(pack(observations[0]))
            reply = unpack(ws.recv(timeout=60))
            catalog = VectorCatalog.scan(vectors)
            assert_actions_match(reply["actions"], direct(policy, catalog, observations[0], ("open_vs_close", 2, 5.0)))
            process.send_signal(signal.SIGINT)
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv(timeout=20)
            assert closed.value.rcvd.code == 1001
        assert process.wait(timeout=20) == 0
        [record] = [json.loads(line) for line in episodes_file.read_text().splitlines()]
        assert (record["experiment"], record["episode_id"], record["inferences"], record["ended_by"]) == \
            ("cli", 4, 1, "disconnect")
    finally:
        process.kill()

