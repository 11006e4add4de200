"""The policy server under attack: each bad request is answered with one line naming its key (never a
traceback) and the connection then serves a good request; plain HTTP, stuck inference, too many connections,
a client sending ahead and oversize frames are bounded and answered without an error traceback in the log; another
HTTP method than GET is answered 405, and an episodes file that cannot be written is said to the client as that."""

from __future__ import annotations

import contextlib
import logging
import shutil
import socket
import threading
import time
import urllib.error
import urllib.request

import msgpack
import numpy as np
import pytest
from helpers_serve import FakePolicy, fake_actions, libero_observations, running, write_vectors
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from steering_core.serve import PolicyServer, VectorCatalog
from steering_core.serve.codec import pack, unpack
from steering_core.serve.episodes import EpisodeLog
from steering_core.serve.server import MAX_REPLY_CHARS, serving_in_thread

MAX_MESSAGE_BYTES = 1_000_000
TRACEBACK_MARKS = ("Traceback", 'File "')


class TrappedPolicy(FakePolicy):
    """The fake policy, with prompts that make it fail as a real one can: raise, return NaN or no actions,
    or take `slow_s` seconds."""

    def __init__(self, slow_s: float = 0.0) -> None:
        super().__init__()
        self.slow_s = slow_s

    @property
    def metadata(self) -> dict:
        return {**super().metadata, "state_dim": 8}  # as Pi05Policy's: the widest state its norm stats describe

    def infer(self, observation: dict, steering) -> dict:
        prompt = observation["prompt"]
        if prompt == "raise":
            raise ValueError("observation: `observation/state` has 9 dimensions but the norm stats only 8\n"
                             "  a second line of the policy's message")
        if prompt == "slow":
            time.sleep(self.slow_s)
        result = super().infer(observation, steering)
        if prompt == "nan":
            result["actions"][3, 2] = np.nan
        if prompt == "none":
            del result["actions"]
        return result


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> VectorCatalog:
    return VectorCatalog.scan(write_vectors(tmp_path_factory.mktemp("steer") / "latent_steering", 64))


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict:
    return libero_observations(tmp_path_factory.mktemp("demo"), frames=1)[0]


@pytest.fixture(scope="module")
def server(catalog):
    with running(PolicyServer(TrappedPolicy(), catalog, max_message_bytes=MAX_MESSAGE_BYTES)) as server:
        yield server


def url(server: PolicyServer) -> str:
    return f"ws://127.0.0.1:{server.port}"


def assert_one_line_naming(reply, key: str) -> None:
    assert isinstance(reply, str), f"expected an error line, got {type(reply).__name__}"
    assert "\n" not in reply and "\r" not in reply and len(reply) <= MAX_REPLY_CHARS, reply[:2000]
    assert reply.startswith(("bad request: ", "inference failed (the server keeps serving): ")), reply
    assert key in reply, (key, reply)
    assert not any(mark in reply for mark in TRACEBACK_MARKS), reply


def assert_serves(ws, good: dict) -> None:
    ws.send(pack(good))
    assert unpack(ws.recv(timeout=30))["actions"].tobytes() == fake_actions(good, []).tobytes()


# ---------------------------------------------------------------- building bad messages

def tagged(data, dtype, shape) -> dict:
    """An openpi-client array map with any fields, as a hand-made client may send it."""
    return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}


def scalar(data, dtype) -> dict:
    return {b"__npgeneric__": True, b"data": data, b"dtype": dtype}


def image(height: int, width: int) -> np.ndarray:
    return np.zeros((height, width, 3), np.uint8)


def state(*values) -> np.ndarray:
    return np.array(values, np.float64)


def steer(**entry) -> dict:
    return {"pair": "open_vs_close", "layer": 1, "alpha": 1.0} | entry


def without(name: str):
    return lambda g: pack({k: v for k, v in g.items() if k != name})


def with_(**values):
    """A good observation with `values` replacing or adding keys (`observation_image` for `observation/image`)."""
    return lambda g: pack(g | {k.replace("observation_", "observation/"): v for k, v in values.items()})


def with_steering(value):
    return lambda g: pack(g | {"steering": value})


def deep_map(depth: int) -> bytes:
    """A map holding a map ... `depth` deep under key "a" (msgpack.packb refuses to nest beyond 512)."""
    return b"\x81\xa1a" * depth + b"\xc0"


def with_raw(name: str, raw: bytes):
    """A good observation plus key `name` holding the already-encoded value `raw`."""
    def build(g: dict) -> bytes:
        body = pack(g)
        assert body[0] == 0x80 | len(g)  # a fixmap: one more key bumps its count
        return bytes([body[0] + 1]) + body[1:] + msgpack.packb(name) + raw
    return build


def ctrl(**fields):
    return lambda g: pack({"__ctrl__": "episode_start"} | fields)


CASES = {
    # the message as a whole
    "text_frame": (lambda g: "observation please", "text frame"),
    "not_msgpack": (lambda g: b"\xc1\x00 this is not msgpack", "message is not msgpack"),
    "empty_message": (lambda g: b"", "message is not msgpack"),
    "truncated_message": (lambda g: pack(g)[:-7], "message is not msgpack"),
    "trailing_bytes": (lambda g: pack(g) + b"\x00", "message is not msgpack"),
    "integer_map_key": (lambda g: b"\x81\x01\x02", "message is not msgpack"),
    "message_is_a_list": (lambda g: pack([g]), "observation dict, got list"),
    "message_is_an_int": (lambda g: pack(7), "observation dict, got int"),
    "message_is_a_str": (lambda g: pack("observation/image"), "observation dict, got str"),
    "map_900_deep": (lambda g: deep_map(900), "nested deeper than 32"),
    "list_900_deep_in_steering": (with_raw("steering", b"\x91" * 900 + b"\xc0"), "steering[0][0]"),
    "list_5000_deep": (with_raw("steering", b"\x91" * 5000 + b"\xc0"), "message is not msgpack"),
    "over_the_size_limit": (with_(padding=np.zeros(MAX_MESSAGE_BYTES, np.uint8)), "message: "),
    # missing keys
    "missing_image": (without("observation/image"), "observation/image: missing"),
    "missing_wrist_image": (without("observation/wrist_image"), "observation/wrist_image: missing"),
    "missing_state": (without("observation/state"), "observation/state: missing"),
    "missing_prompt": (without("prompt"), "prompt: missing"),
    # images
    "image_0x0": (with_(observation_image=image(0, 0)), "observation/image: image of 0x0"),
    "image_1x2000": (with_(observation_image=image(1, 2000)), "observation/image: image of 1x2000"),
    "wrist_image_2000x1": (with_(observation_wrist_image=image(2000, 1)), "observation/wrist_image: image of 2000x1"),
    "wrist_image_0x224": (with_(observation_wrist_image=image(0, 224)), "observation/wrist_image: image of 0x224"),
    "image_float32": (with_(observation_image=image(8, 8).astype(np.float32)), "observation/image: expected a uint8"),
    "image_int8": (with_(observation_image=image(8, 8).astype(np.int8)), "observation/image: expected a uint8"),
    "image_2d": (with_(observation_image=np.zeros((8, 8), np.uint8)), "observation/image: expected a uint8"),
    "image_4_channels": (with_(observation_image=np.zeros((8, 8, 4), np.uint8)), "observation/image: expected"),
    "image_batched_alone": (with_(observation_image=np.zeros((1, 8, 8, 3), np.uint8)),
                            "observation/wrist_image: expected a uint8 (B, H, W, 3) array with B = 1"),
    "batch_over_max_batch": (with_(observation_image=np.zeros((17, 8, 8, 3), np.uint8)),
                             "observation/image: a batch of 17 frames; this server takes 1 to 16 per request"),
    "batch_of_zero": (with_(observation_image=np.zeros((0, 8, 8, 3), np.uint8)),
                      "observation/image: a batch of 0 frames"),
    "batch_prompt_count": (with_(observation_image=np.zeros((2, 8, 8, 3), np.uint8),
                                 observation_wrist_image=np.zeros((2, 8, 8, 3), np.uint8),
                                 observation_state=np.zeros((2, 8)), prompt=["one"]),
                           "prompt: expected 2 str (a list or array)"),
    "batch_state_rows": (with_(observation_image=np.zeros((2, 8, 8, 3), np.uint8),
                               observation_wrist_image=np.zeros((2, 8, 8, 3), np.uint8),
                               observation_state=np.zeros((3, 8)), prompt=["a", "b"]),
                         "observation/state: expected a real-valued (B, D) array with D >= 1 and B = 2"),
    "image_as_nested_lists": (with_(observation_image=[[[0, 0, 0]]]), "observation/image: expected a uint8"),
    "image_as_bytes": (with_(observation_image=b"\x00" * 192), "observation/image: expected a uint8"),
    "image_none": (with_(observation_image=None), "observation/image: expected a uint8"),
    "image_data_too_short": (with_(observation_image=tagged(b"\x00" * 10, "|u1", [8, 8, 3])),
                             "observation/image: array of shape (8, 8, 3)"),
    "image_object_dtype": (with_(observation_image=tagged(b"\x00" * 8, "|O", [1])), "observation/image: array dtype"),
    "image_struct_dtype": (with_(observation_image=tagged(b"\x00" * 8, "<f4,<f4", [1])),
                           "observation/image: array dtype"),
    "image_garbage_dtype": (with_(observation_image=tagged(b"", "zz9", [0])), "observation/image: array dtype 'zz9'"),
    "image_no_dtype": (with_(observation_image=tagged(b"", None, [0])), "observation/image: array dtype None"),
    "image_negative_shape": (with_(observation_image=tagged(b"", "|u1", [-1, 3])), "observation/image: array shape"),
    "image_shape_a_str": (with_(observation_image=tagged(b"", "|u1", "224x224")), "observation/image: array shape"),
    "image_70_dimensions": (with_(observation_image=tagged(b"\x00", "|u1", [1] * 70)),
                            "observation/image: array of shape"),
    "image_data_a_str": (with_(observation_image=tagged("pixels", "|u1", [6])), "observation/image: array data"),
    # the state
    "state_nan": (with_(observation_state=state(0.1, np.nan, 0.3)), "observation/state: the state is not finite"),
    "state_inf": (with_(observation_state=state(np.inf, 0.0)), "observation/state: the state is not finite"),
    "state_minus_inf_float32": (with_(observation_state=np.array([0, -np.inf], np.float32)),
                                "observation/state: the state is not finite"),
    "state_empty": (with_(observation_state=state()), "observation/state: expected a real-valued (D,)"),
    "state_2d": (with_(observation_state=np.zeros((1, 8))), "observation/state: expected a real-valued (D,)"),
    "state_strings": (with_(observation_state=np.array(["a", "b"])), "observation/state: expected a real-valued"),
    "state_bool": (with_(observation_state=np.ones(8, bool)), "observation/state: expected a real-valued"),
    "state_complex": (with_(observation_state=tagged(b"\x00" * 16, "<c16", [1])), "observation/state: array dtype"),
    "state_as_list": (with_(observation_state=[0.1, 0.2]), "observation/state: expected a real-valued"),
    "state_as_scalar": (with_(observation_state=np.float64(0.5)), "observation/state: expected a real-valued"),
    "state_scalar_holding_a_list": (with_(observation_state=scalar([1, 2], "<f8")),
                                    "observation/state: numpy scalar"),
    "state_scalar_bad_value": (with_(observation_state=scalar("x", "<f8")), "observation/state: numpy scalar"),
    "state_10000_wide": (with_(observation_state=np.zeros(10_000)),
                         "observation/state: 10000 dimensions; this policy takes at most 8"),
    # a key given twice in one map (msgpack keeps the last silently)
    "prompt_twice": (with_raw("prompt", msgpack.packb("close the drawer")), "prompt: this key appears twice"),
    "steering_alpha_twice": (with_raw("steering", b"\x84" + b"".join(map(msgpack.packb, (
        "pair", "open_vs_close", "layer", 1, "alpha", 1.0, "alpha", 90.0)))), "steering.alpha: this key appears twice"),
    # the prompt
    "prompt_bytes": (with_(prompt=b"open the drawer"), "prompt: expected a str"),
    "prompt_int": (with_(prompt=3), "prompt: expected a str"),
    "prompt_none": (with_(prompt=None), "prompt: expected a str"),
    "prompt_list": (with_(prompt=["open", "the drawer"]), "prompt: expected a str"),
    "prompt_too_long": (with_(prompt="open " * 1000), "prompt: 5000 characters"),
    # steering
    "steering_str": (with_steering("open_vs_close"), "steering: expected a dict"),
    "steering_int": (with_steering(12), "steering: expected a dict"),
    "steering_unknown_pair": (with_steering(steer(pair="nope")), "steering.pair: unknown pair"),
    "steering_pair_int": (with_steering(steer(pair=3)), "steering.pair: expected a str"),
    "steering_missing_pair": (with_steering({"layer": 1, "alpha": 1.0}), "steering.pair: missing"),
    "steering_missing_alpha": (with_steering({"pair": "open_vs_close", "layer": 1}), "steering.alpha: missing"),
    "steering_layer_float": (with_steering(steer(layer=1.0)), "steering.layer: expected an integer"),
    "steering_layer_str": (with_steering(steer(layer="1")), "steering.layer: expected an integer"),
    "steering_layer_bool": (with_steering(steer(layer=True)), "steering.layer: expected an integer"),
    "steering_layer_absent": (with_steering(steer(layer=7)), "steering.layer: pair 'open_vs_close' has no vectors"),
    "steering_layer_huge": (with_steering(steer(layer=2**63)), "steering.layer: pair 'open_vs_close' has no vectors"),
    "steering_alpha_nan": (with_steering(steer(alpha=float("nan"))), "steering.alpha: expected a finite number"),
    "steering_alpha_inf": (with_steering(steer(alpha=float("inf"))), "steering.alpha: expected a finite number"),
    "steering_alpha_str": (with_steering(steer(alpha="2")), "steering.alpha: expected a finite number"),
    "steering_alpha_huge": (with_steering(steer(alpha=1e39)), "steering.alpha: |alpha| is 1e+39"),
    "steering_unknown_key": (with_steering(steer(scale=2)), "steering: unknown key(s) ['scale']"),
    "steering_unknown_direction": (with_steering(steer(direction="sideways")), "steering.direction: pair"),
    "steering_direction_int": (with_steering(steer(direction=1)), "steering.direction: expected a str"),
    "steering_bad_units": (with_steering(steer(alpha_units="R")), "steering.alpha_units: expected one of"),
    "steering_mode_unknown": (with_steering(steer(mode="replace")), "steering.mode: expected one of ['add', 'clamp']"),
    "steering_mode_int": (with_steering(steer(mode=1)), "steering.mode: expected one of ['add', 'clamp'], got int"),
    "steering_clamp_with_units": (with_steering(steer(mode="clamp", alpha_units="vector")),
                                  "steering.alpha_units: mode 'clamp' takes alpha as the level fraction"),
    "steering_clamp_of_a_random_control": (with_steering(steer(mode="clamp", direction="random_0")),
                                           "steering.mode: 'random_0' is a random control"),
    "steering_clamp_alpha_str": (with_steering(steer(mode="clamp", alpha="0.5")),
                                 "steering.alpha: expected a finite number"),
    "steering_two_clamps_of_one_layer": (with_steering([steer(mode="clamp"), steer(mode="clamp", alpha=0.0)]),
                                         "steering[1].layer: layer 1 is clamped by steering[0] too"),
    "steering_second_entry_not_a_dict": (with_steering([steer(), 3]), "steering[1]: expected a dict"),
    "steering_second_entry_bad_alpha": (with_steering([steer(), steer(alpha=None)]), "steering[1].alpha"),
    "steering_of_20k_entries": (with_steering([steer(alpha=0.0)] * 20_000), "steering: 20000 entries"),
    "steering_entries_each_within_the_bound_adding_up_over_it": (
        with_steering([steer(alpha=90.0)] * 16), "steering: the entries' |alpha| add up to 1440"),
    # control messages
    "ctrl_unknown": (lambda g: pack({"__ctrl__": "reset"}), "__ctrl__: unknown control message 'reset'"),
    "ctrl_not_a_str": (lambda g: pack({"__ctrl__": 1}), "__ctrl__: expected a str"),
    "ctrl_episode_id_str": (ctrl(__episode_id__="7"), "__episode_id__: expected int"),
    "ctrl_success_str": (lambda g: pack({"__ctrl__": "episode_end", "__success__": "yes"}),
                         "__success__: expected bool"),
    "ctrl_unknown_field": (ctrl(__robot__="arm"), "episode_start: unknown key(s) ['__robot__']"),
    "ctrl_task_of_500k_characters": (ctrl(__task__="t" * 500_000), "__task__: 500000 characters; expected at most"),
    "ctrl_experiment_over_the_bound": (ctrl(__experiment__="e" * 1001), "__experiment__: 1001 characters"),
    # the client's own text in a key, and a key too long to echo
    "line_break_in_a_key": (with_(**{"extra\nline": tagged(b"", "|O", [0])}), "extra line: array dtype"),
    "key_of_100k_characters": (with_(**{"k" * 100_000: tagged(b"", "|O", [0])}), "kkkkkkkk"),
    # the policy's own failures
    "policy_raises": (with_(prompt="raise"), "ValueError: observation: `observation/state` has 9 dimensions"),
    "policy_returns_nan_actions": (with_(prompt="nan"), "the policy's actions are not finite"),
    "policy_returns_no_actions": (with_(prompt="none"), "no actions array"),
}


@pytest.mark.parametrize("name", CASES)
def test_bad_request_gets_one_line_naming_the_key_then_the_connection_serves(server, good, name, caplog):
    build, key = CASES[name]
    with connect(url(server), max_size=None) as ws:
        ws.recv()
        ws.send(build(good))
        reply = ws.recv(timeout=30)
        assert_one_line_naming(reply, key)
        assert_serves(ws, good)
    logged = [r for r in caplog.records if r.exc_info and r.name.startswith("steering_core")]
    assert len(logged) == (name == "policy_raises")  # only the policy's own error is logged with its traceback


def test_edge_requests_that_are_valid_are_served(server, good):
    edge = [good | {"observation/image": image(1, 1)}, good | {"observation/wrist_image": image(1, 16)},
            good | {"observation/state": np.array([7], np.int64)}, good | {"prompt": ""},
            good | {"prompt": "p" * 2000}, good | {"unknown_extra_key": [1, {"a": None}]}]
    with connect(url(server), max_size=None) as ws:
        ws.recv()
        for observation in edge:
            ws.send(pack(observation))
            assert unpack(ws.recv(timeout=30))["actions"].shape == (10, 7)


# ---------------------------------------------------------------- plain HTTP

def test_plain_http_is_answered_426_or_404_without_an_error_in_the_log(server, good, caplog):
    caplog.set_level(logging.INFO)
    for path, status in (("/", 426), ("/favicon.ico", 404), ("/index.html?x=1", 404)):
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(f"http://127.0.0.1:{server.port}{path}", timeout=10)
        assert err.value.code == status, path
        body = err.value.read().decode()
        assert "/healthz" in body and "Traceback" not in body
    two_upgrades = b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: h2c\r\nUpgrade: h2\r\n\r\n"
    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
        sock.sendall(two_upgrades)
        assert sock.recv(4096).startswith(b"HTTP/1.1 426 ")
    for raw in (b"GARBAGE\r\n\r\n", b"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n\r\n", b""):
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
            sock.sendall(raw)
            sock.shutdown(socket.SHUT_WR)
            assert b"Traceback" not in sock.recv(4096)
    def refusals() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.getMessage().startswith("refused a malformed")]

    deadline = time.monotonic() + 10
    while len(refusals()) < 3 and time.monotonic() < deadline:  # the server may log after its reply
        time.sleep(0.05)
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    malformed = refusals()
    assert len(malformed) == 3 and "invalid HTTP request line: GARBAGE" in malformed[0], malformed
    with connect(url(server), max_size=None) as ws:
        ws.recv()
        assert_serves(ws, good)


@pytest.mark.parametrize(("method", "path"), [("POST", "/healthz"), ("PUT", "/"), ("DELETE", "/healthz"),
                                              ("HEAD", "/healthz")])
def test_another_method_than_get_is_answered_405(server, good, caplog, method, path):
    caplog.set_level(logging.INFO)
    request = urllib.request.Request(f"http://127.0.0.1:{server.port}{path}", method=method,
                                     data=b"{}" if method in ("POST", "PUT") else None)
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(request, timeout=10)
    assert err.value.code == 405 and err.value.headers["Allow"] == "GET", method
    if method != "HEAD":
        assert "/healthz" in err.value.read().decode()
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING or r.exc_info]
    with connect(url(server), max_size=None) as ws:
        ws.recv()
        assert_serves(ws, good)


def test_a_port_in_use_is_one_line_naming_it(catalog):
    """The server's own bind (the address taken after `serve` checked it) raises one line, not asyncio's."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        with pytest.raises(ValueError, match=rf"^127\.0\.0\.1:{port} is in use: .* choose another port"):
            with serving_in_thread(PolicyServer(TrappedPolicy(), catalog, port=port)):
                pass


def test_an_episodes_file_that_cannot_be_written_is_said_to_the_client(catalog, good, tmp_path, caplog):
    """The episodes file's folder removed while serving: the client hears that the episode was not recorded (not
    "inference failed"), the log names the file, the episode is kept in memory and the connection serves on; an
    episode ended by the disconnect is logged the same, with no traceback."""
    episodes_file = tmp_path / "records" / "episodes.jsonl"
    episodes_file.parent.mkdir()
    with running(PolicyServer(TrappedPolicy(), catalog, episode_log=EpisodeLog(episodes_file))) as server, \
            connect(url(server), max_size=None) as ws:
        ws.recv()
        shutil.rmtree(episodes_file.parent)
        ws.send(pack({"__ctrl__": "episode_start", "__episode_id__": 1}))
        assert unpack(ws.recv(timeout=30)) == {"__ack__": "episode_start"}  # nothing ended: nothing to write
        assert_serves(ws, good)
        # episode 2 begins, ending episode 1; then episode 2 ends: neither can be written
        for message in ({"__ctrl__": "episode_start", "__episode_id__": 2}, {"__ctrl__": "episode_end"}):
            ws.send(pack(message))
            reply = ws.recv(timeout=30)
            assert isinstance(reply, str) and reply.startswith(
                "the server could not record the episode: No such file or directory"), reply
            assert "\n" not in reply and str(tmp_path) not in reply, reply
        assert_serves(ws, good)
        ws.send(pack({"__ctrl__": "episode_start", "__episode_id__": 3}))  # ended by the disconnect: only logged
        assert unpack(ws.recv(timeout=30)) == {"__ack__": "episode_start"}
    assert [(r["episode_id"], r["ended_by"], r["inferences"]) for r in server.episodes] == [
        (1, "episode_start", 1), (2, "episode_end", 0), (3, "disconnect", 0)]
    unwritten = [r.getMessage() for r in caplog.records if "not written" in r.getMessage()]
    assert len(unwritten) == 3 and all(str(episodes_file) in m for m in unwritten), unwritten
    assert not [r for r in caplog.records if r.exc_info]


# ---------------------------------------------------------------- timeout, connection cap, queue, frame size

def test_inference_timeout_answers_and_keeps_inference_serialised(catalog, good, caplog):
    policy = TrappedPolicy(slow_s=3.0)
    with running(PolicyServer(policy, catalog, inference_timeout_s=0.4)) as server, \
            connect(url(server), max_size=None) as first, connect(url(server), max_size=None) as second:
        assert unpack(first.recv())["server"]["inference_timeout_s"] == 0.4
        second.recv()
        start = time.monotonic()
        first.send(pack(good | {"prompt": "slow"}))
        time.sleep(0.1)
        second.send(pack(good))  # waits for the model the slow request still holds
        assert_one_line_naming(first.recv(timeout=10), "timed out: no actions within 0.4 s")
        assert_one_line_naming(second.recv(timeout=10), "timed out after 0.4 s waiting for the model")
        assert time.monotonic() - start < 2.0  # answered at the timeout, not when the slow inference ends
        time.sleep(3.0)  # the slow inference ends and frees the model
        assert_serves(first, good)
        assert_serves(second, good)
    assert policy.max_concurrent == 1
    assert any("a policy call that timed out ended after" in m for m in caplog.messages)


def test_a_stuck_inference_does_not_keep_the_server_from_stopping(catalog, good):
    with running(PolicyServer(TrappedPolicy(slow_s=30.0), catalog, inference_timeout_s=0.3)) as server, \
            connect(url(server), max_size=None) as ws:
        ws.recv()
        ws.send(pack(good | {"prompt": "slow"}))
        assert_one_line_naming(ws.recv(timeout=10), "timed out: no actions within 0.3 s")
        stopping = time.monotonic()
    assert time.monotonic() - stopping < 10  # not the 30 s the inference is stuck for


def test_connection_cap_closes_extra_connections_with_try_again_later(catalog, good):
    with running(PolicyServer(TrappedPolicy(), catalog, max_connections=2)) as server:
        with connect(url(server), max_size=None) as one, connect(url(server), max_size=None) as two:
            one.recv(), two.recv()
            with connect(url(server), max_size=None) as third, pytest.raises(ConnectionClosed) as closed:
                third.recv(timeout=10)
            assert closed.value.rcvd.code == 1013 and "--max-connections" in closed.value.rcvd.reason
            assert_serves(two, good)
        for _ in range(50):  # the two closed: room again once the server has seen them go
            with connect(url(server), max_size=None) as again:
                with contextlib.suppress(ConnectionClosed):
                    again.recv(timeout=10)
                    assert_serves(again, good)
                    return
            time.sleep(0.1)
        raise AssertionError("no room after two of two connections closed")


def test_idle_connections_are_closed_and_cannot_hold_the_cap(catalog, good):
    """16 sockets that never send shut every client out: an idle timeout closes them, and at the cap the
    connection idle longest gives way to a new client (one with a request in flight never does)."""
    with running(PolicyServer(TrappedPolicy(), catalog, idle_timeout_s=0.5)) as server, \
            connect(url(server), max_size=None) as idle:
        idle.recv()
        with pytest.raises(ConnectionClosed) as closed:
            idle.recv(timeout=60)
        assert closed.value.rcvd.code == 1001 and "--idle-timeout-s" in closed.value.rcvd.reason
    with running(PolicyServer(TrappedPolicy(), catalog, max_connections=2, evict_idle_s=0.2)) as server:
        with connect(url(server), max_size=None) as first, connect(url(server), max_size=None) as second:
            first.recv(), second.recv()
            time.sleep(0.5)  # both idle past evict_idle_s
            assert_serves(second, good)  # `second` is active again: `first` is the idlest
            with connect(url(server), max_size=None) as third:
                third.recv(timeout=10)  # admitted
                with pytest.raises(ConnectionClosed) as closed:
                    first.recv(timeout=10)
                assert closed.value.rcvd.code == 1013 and "idle for" in closed.value.rcvd.reason
                assert_serves(second, good)
    with running(PolicyServer(TrappedPolicy(slow_s=3.0), catalog, max_connections=1, evict_idle_s=0.0)) as server, \
            connect(url(server), max_size=None) as busy:
        busy.recv()
        busy.send(pack(good | {"prompt": "slow"}))
        deadline = time.monotonic() + 60  # generous: only a broken server takes this long to read one frame
        while not server._busy and time.monotonic() < deadline:
            time.sleep(0.01)
        with connect(url(server), max_size=None) as other, pytest.raises(ConnectionClosed) as refused:
            other.recv(timeout=10)  # the one connection has a request in flight: it never gives way
        assert refused.value.rcvd.code == 1013 and "--max-connections" in refused.value.rcvd.reason
        assert unpack(busy.recv(timeout=30))["actions"].shape == (10, 7)


def frames_sent_ahead(catalog, good, max_queue: int) -> int:
    """Frames of 2 MB a client gets onto the wire while the server answers a 4 s request, with `max_queue`."""
    policy = TrappedPolicy(slow_s=4.0)
    frame = pack({"padding": np.zeros(2_000_000, np.uint8)})
    sent = []
    with running(PolicyServer(policy, catalog, max_message_bytes=3_000_000, max_queue=max_queue)) as server, \
            connect(url(server), max_size=None) as ws:
        ws.recv()
        ws.send(pack(good | {"prompt": "slow"}))
        time.sleep(0.2)

        def flood() -> None:
            for _ in range(40):
                ws.send(frame)
                sent.append(time.monotonic())

        threading.Thread(target=flood, daemon=True).start()
        time.sleep(3.0)  # the slow request is still running
        ahead = len(sent)
        assert unpack(ws.recv(timeout=10))["actions"].shape == (10, 7)
        for _ in range(40):  # then every frame is read and answered, in order
            assert_one_line_naming(ws.recv(timeout=30), "observation/image: missing")
        assert_serves(ws, good)
    return ahead


def test_a_client_sending_ahead_is_held_at_the_queue_bound(catalog, good):
    bounded, unbounded = frames_sent_ahead(catalog, good, max_queue=1), frames_sent_ahead(catalog, good, 64)
    # with a queue of 1 only the kernel's socket buffers (a few MB on loopback) and a frame or two get through;
    # a queue of 64 frames takes all 80 MB
    assert bounded < 15 and unbounded == 40, (bounded, unbounded)


def test_a_frame_beyond_twice_the_message_limit_closes_only_that_connection(server, good):
    with connect(url(server), max_size=None) as ws:
        ws.recv()
        ws.send(pack({"padding": np.zeros(2 * MAX_MESSAGE_BYTES + 1, np.uint8)}))
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=10)
        assert closed.value.rcvd.code == 1009
    with connect(url(server), max_size=None) as ws:
        ws.recv()
        assert_serves(ws, good)



# ---------------------------------------------------------------- the real model and the command line

@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict:
    """A tiny pi0.5 checkpoint, its tokenizer and arch file."""
    from steering_core.storage.fileio import write_json
    from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
    from steering_core.synthetic.tokenizer import write_tokenizer

    folder, arch = tmp_path_factory.mktemp("pi05"), tiny_arch()
    return {"arch": arch, "checkpoint": write_pi05_checkpoint(folder / "ckpt", arch, seed=3),
            "tokenizer": write_tokenizer(folder / "tokenizer.model"),
            "arch_file": write_json(folder / "arch.json", arch.model_dump())}


def test_the_tiny_pi05_policy_behind_the_server_gets_the_same_one_line_answers(tiny, good):
    """The issue's attacks on the real model: 0x0 and 1x2000 images, a NaN state, a 900-deep message."""
    from steering_core.pi05.policy import Pi05Policy
    from steering_core.serve import SteeredPi05Policy

    policy = Pi05Policy.from_checkpoint(tiny["checkpoint"], tiny["arch"], device="cpu",
                                        tokenizer_path=tiny["tokenizer"])
    names = ("image_0x0", "image_1x2000", "wrist_image_2000x1", "state_nan", "state_inf", "map_900_deep",
             "list_900_deep_in_steering", "prompt_too_long", "prompt_twice")
    with running(PolicyServer(SteeredPi05Policy(policy, noise_seed=1))) as server, \
            connect(url(server), max_size=None) as ws:
        ws.recv()
        ws.send(pack(good))
        want = unpack(ws.recv(timeout=60))["actions"]
        width = policy.state_dim  # its norm stats' state width
        wide = f"observation/state: {width + 1} dimensions; this policy takes at most {width}"
        for build, key in [CASES[name] for name in names] + [(with_(observation_state=np.zeros(width + 1)), wide)]:
            ws.send(build(good))
            assert_one_line_naming(ws.recv(timeout=60), key)
            ws.send(pack(good))
            assert unpack(ws.recv(timeout=60))["actions"].tobytes() == want.tobytes()


def test_serve_command_passes_its_bounds_to_the_server(tiny, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import latent_steering_cli.serve  # noqa: F401  (registers `serve`)
    from latent_steering_cli import app

    built = []
    monkeypatch.setattr(PolicyServer, "run", lambda self: built.append(self))
    monkeypatch.chdir(tmp_path)  # no data/latent_steering here: the plain policy is served
    command = ["serve", "--checkpoint-path", str(tiny["checkpoint"]), "--tokenizer-path", str(tiny["tokenizer"]),
               "--arch-file", str(tiny["arch_file"]), "--device", "cpu"]
    bounds = ["--inference-timeout-s", "2.5", "--max-connections", "3", "--max-queue", "1", "--max-message-mb", "0.5"]
    for options, want in (([], (120.0, 16, 2, 16 * 2**20)), (bounds, (2.5, 3, 1, 2**19))):
        result = CliRunner().invoke(app, command + options)
        assert result.exit_code == 0, result.output
        server = built.pop()
        assert (server.inference_timeout_s, server.max_connections, server.max_queue, server.max_message_bytes) == want
        assert server.metadata["server"]["max_connections"] == want[1]
    result = CliRunner().invoke(app, command + ["--max-queue", "0"])
    assert result.exit_code == 2 and "--max-queue" in result.output
