"""The policy server over real loopback sockets: the real openpi client (its own environment), steering per
request, errors that keep the connection, concurrency, health check, keepalive during inference, shutdown."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_serve import (
    PAIRS,
    PLAIN_METHODS,
    SAE_METHODS,
    FakePolicy,
    fake_actions,
    libero_observations,
    port_from_log,
    run_openpi_client,
    running,
    write_vectors,
)
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from steering_core.pi05.preprocess import Cameras
from steering_core.serve import (
    PolicyServer,
    RequestError,
    SteeredPi05Policy,
    SteeringVector,
    VectorCatalog,
    parse_steering,
    parse_steering_option,
)
from steering_core.serve.auth import API_KEY_ENV, authorized, read_api_key
from steering_core.serve.catalog import random_control, random_direction
from steering_core.serve.codec import pack, unpack
from steering_core.serve.episodes import EpisodeLog
from steering_core.synthetic.pi05 import tiny_arch
from steering_core.vectors.methods import METHODS
from steering_core.vectors.methods.direction_file import read_method_direction, write_method_direction

WIDTH = 64


@pytest.fixture(scope="module")
def catalog(tmp_path_factory) -> VectorCatalog:
    return VectorCatalog.scan(write_vectors(tmp_path_factory.mktemp("steer") / "latent_steering", WIDTH))


@pytest.fixture(scope="module")
def observations(tmp_path_factory) -> list[dict]:
    return libero_observations(tmp_path_factory.mktemp("demo"), frames=4)


def expected(catalog: VectorCatalog, observation: dict, *entries: tuple) -> np.ndarray:
    """The fake policy's actions computed directly, steering entries given as (pair, layer, alpha[, direction[,
    alpha_units | "clamp"]]): α in residual_norm units (the default) adds α·R times the unit vector, in vector
    units α·‖d‖ times it; a clamp sets the level m₋ + α(m₊ − m₋) (helpers_serve.steering_term)."""
    return fake_actions(observation, [vector_term(catalog, *entry) for entry in entries])


def vector_term(catalog: VectorCatalog, pair: str, layer: int, alpha: float, direction: str | None = None,
                units: str = "residual_norm") -> tuple:
    vector = catalog.get(pair, layer, direction)
    if units == "clamp":
        start, end = vector.levels
        return -vector.vector, start + alpha * (end - start)
    return vector.vector, alpha * (vector.norm if units == "vector" else vector.mean_residual_norm)


def pair_folder(catalog: VectorCatalog, pair: str, layer: int) -> Path:
    return catalog.get(pair, layer).path.parent


# ---------------------------------------------------------------- catalog and request parsing (no sockets)

def test_catalog_offers_every_method_the_steer_step_wrote(catalog):
    keys = {(e["pair"], e["layer"], e["direction"]) for e in catalog.describe()}
    written = {(pair, layer, method) for pair in PAIRS for layer in (1, 2) for method in json.loads(
        (pair_folder(catalog, pair, layer) / "directions.json").read_text())["methods"]}
    assert keys == written == {(pair, 1, m) for pair in PAIRS for m in SAE_METHODS} | \
        {(pair, 2, m) for pair in PAIRS for m in PLAIN_METHODS}
    assert {e["description"] for e in catalog.describe()} == {METHODS[m].description for m in SAE_METHODS}
    for pair, layer, method in keys:
        vector, stored = catalog.get(pair, layer, method), read_method_direction(
            pair_folder(catalog, pair, layer) / f"{method}_direction.safetensors")
        assert vector.vector.dtype == torch.float32 and torch.equal(vector.vector, stored.direction)
        assert float(vector.vector.double().norm()) == pytest.approx(1.0, abs=1e-6)
        assert (vector.norm, vector.levels, vector.mean_residual_norm) == \
            (stored.norm, stored.levels, stored.mean_residual_norm)
    # the default direction: sae where an SAE was used, else mean_difference
    assert catalog.get("open_vs_close", 1).direction == "sae" and catalog.get("open_vs_close", 2).direction \
        == "mean_difference"


def test_catalog_refuses_a_missing_root_and_a_pair_folder_without_methods(catalog, tmp_path):
    with pytest.raises(FileNotFoundError, match="--vectors"):
        VectorCatalog.scan(tmp_path / "absent")
    old = tmp_path / "old"
    shutil.copytree(pair_folder(catalog, "on_vs_off", 2).parents[1], old)
    summary_path = old / "layer02" / "on_vs_off" / "directions.json"
    summary = json.loads(summary_path.read_text())
    del summary["methods"]  # written before the direction methods
    summary_path.write_text(json.dumps(summary))
    with pytest.raises(ValueError, match=re.escape(f"{summary_path}: no `methods` table") + ".*re-run steer"):
        VectorCatalog.scan(old)


def test_steering_entry_forms(catalog):
    one = parse_steering({"pair": "open_vs_close", "layer": 2, "alpha": 4}, catalog)
    assert [(s.vector.pair, s.vector.layer, s.vector.direction, s.alpha, s.mode) for s in one] == \
        [("open_vs_close", 2, "mean_difference", 4.0, "add")]
    two = parse_steering([{"pair": "on_vs_off", "layer": np.int64(1), "alpha": np.float32(-0.5),
                           "direction": "mean_difference"}, {"pair": "open_vs_close", "layer": 1, "alpha": 1.0}],
                         catalog)
    assert [(s.vector.pair, s.vector.direction, s.alpha) for s in two] == \
        [("on_vs_off", "mean_difference", -0.5), ("open_vs_close", "sae", 1.0)]
    assert parse_steering(None, catalog) == () and parse_steering([], catalog) == ()
    assert parse_steering_option("open_vs_close:12:4.0") == {"pair": "open_vs_close", "layer": 12, "alpha": 4.0}
    assert parse_steering_option("a:3:-1:mean_difference")["direction"] == "mean_difference"
    assert parse_steering_option("a:3:-1:sae:vector") == {"pair": "a", "layer": 3, "alpha": -1.0,
                                                          "direction": "sae", "alpha_units": "vector"}
    assert parse_steering_option("a:12:0.5:probe:clamp") == {"pair": "a", "layer": 12, "alpha": 0.5,
                                                             "direction": "probe", "mode": "clamp"}
    with pytest.raises(ValueError, match=r"pair:layer:alpha\[:direction\[:alpha_units\|mode\]\]"):
        parse_steering_option("open_vs_close:12")


def test_a_clamp_entry_sets_the_level_fraction_between_the_concepts(catalog):
    [clamp] = parse_steering(parse_steering_option("open_vs_close:1:0.25:mean_difference:clamp"), catalog)
    vector = catalog.get("open_vs_close", 1, "mean_difference")
    assert (clamp.mode, clamp.alpha, clamp.alpha_units, clamp.vector_alpha) == ("clamp", 0.25, None, None)
    assert clamp.describe() == {
        "pair": "open_vs_close", "layer": 1, "direction": "mean_difference", "mode": "clamp", "alpha": 0.25,
        "alpha_units": None, "vector_alpha": None, "levels": list(vector.levels), "norm": vector.norm,
        "mean_residual_norm": vector.mean_residual_norm}
    # mean_difference: the positive concept's mean level lies above the negative's by ‖d‖
    assert vector.levels[1] - vector.levels[0] == pytest.approx(vector.norm, rel=1e-5)
    # clamps are bounded each, and do not count toward the add entries' sum
    mixed = [{"pair": "open_vs_close", "layer": 1, "alpha": 90.0, "mode": "clamp"},
             {"pair": "on_vs_off", "layer": 2, "alpha": 90.0}]
    assert [s.mode for s in parse_steering(mixed, catalog)] == ["clamp", "add"]


def test_a_clamp_entry_reaches_the_policy_as_a_clamp_steering(catalog):
    """SteeredPi05Policy turns a clamp entry into Steering(mode="clamp", levels=(m₋, m₊)) with alpha as given,
    an add entry into Steering(alpha=vector_alpha); requests clamping one layer go to separate calls."""
    inner = RecordingPi05()
    served = SteeredPi05Policy(inner)
    clamp = {"pair": "open_vs_close", "layer": 1, "alpha": 0.75, "mode": "clamp"}
    add = {"pair": "on_vs_off", "layer": 2, "alpha": -2.0}
    requests = [parse_steering(value, catalog) for value in ([clamp, add], [clamp | {"alpha": 0.1}], [add], [])]
    frame = {"observation/image": np.zeros((8, 8, 3), np.uint8), "observation/wrist_image": np.zeros((8, 8, 3), np.uint8),
             "observation/state": np.zeros(8), "prompt": "open the drawer"}
    results = served.infer_batch([frame] * 4, requests)
    assert [r["policy_timing"]["batch_rows"] for r in results] == [3, 1, 3, 3]  # the second clamp: its own call
    first, second = inner.calls
    vector = catalog.get("open_vs_close", 1)
    [clamped, added, added_again] = first
    assert (clamped.mode, clamped.levels, clamped.alpha, clamped.layer) == ("clamp", vector.levels, 0.75, 1)
    assert torch.equal(clamped.vector, vector.vector)
    assert clamped.token_mask.tolist() == [[True] * 4, [False] * 4, [False] * 4]  # request 0's row only
    other = catalog.get("on_vs_off", 2)
    assert (added.mode, added.levels, added.alpha) == ("add", None, -2.0 * other.mean_residual_norm)
    assert added_again.token_mask.tolist() == [[False] * 4, [True] * 4, [False] * 4]  # request 2's row
    [alone] = second
    assert (alone.mode, alone.alpha, alone.token_mask.tolist()) == ("clamp", pytest.approx(0.1), [[True] * 4])


class RecordingPi05:
    """A stand-in for Pi05Policy under SteeredPi05Policy: every prompt token is an instruction token; records the
    steerings of each call and answers zeros."""

    arch = tiny_arch()
    cameras = Cameras()
    device = torch.device("cpu")
    action_horizon, action_dim = 10, 32

    def __init__(self) -> None:
        self.calls: list[list] = []

    def instruction_masks(self, prompts, states) -> torch.Tensor:
        return torch.ones(len(prompts), 4, dtype=torch.bool)

    def infer_rows(self, batch, steering, noise) -> np.ndarray:
        self.calls.append(list(steering or []))
        return np.zeros((len(batch.prompts), self.action_horizon, 7), np.float32)


def test_alpha_is_in_residual_norm_units_unless_the_entry_says_vector(catalog):
    vector = catalog.get("open_vs_close", 1)
    [default] = parse_steering({"pair": "open_vs_close", "layer": 1, "alpha": 2.0}, catalog)
    [raw] = parse_steering({"pair": "open_vs_close", "layer": 1, "alpha": 2.0, "alpha_units": "vector"}, catalog)
    assert default.alpha_units == "residual_norm" and raw.alpha_units == "vector"
    # the shift added to the unit vector has norm α·R in residual_norm units, α·‖d‖ in vector units
    assert default.vector_alpha == pytest.approx(2.0 * vector.mean_residual_norm)
    assert raw.vector_alpha == pytest.approx(2.0 * vector.norm)
    assert default.describe() | {"vector_alpha": None} == {
        "pair": "open_vs_close", "layer": 1, "direction": "sae", "mode": "add", "alpha": 2.0,
        "alpha_units": "residual_norm", "vector_alpha": None, "levels": list(vector.levels), "norm": vector.norm,
        "mean_residual_norm": vector.mean_residual_norm}


def test_metadata_lists_r_norm_levels_and_decoder_bias_per_vector(catalog, tmp_path):
    entries = catalog.describe()
    for entry in entries:
        summary = json.loads((pair_folder(catalog, entry["pair"], entry["layer"]) / "directions.json").read_text())
        listed = summary["methods"][entry["direction"]]
        assert entry["mean_residual_norm"] == summary["mean_residual_norm"] > 0
        assert (entry["norm"], entry["levels"]) == (listed["norm"], [listed["negative_level"],
                                                                     listed["positive_level"]])
        assert entry["include_decoder_bias"] is False
    biased = VectorCatalog.scan(write_vectors(tmp_path / "biased", WIDTH, include_decoder_bias=True))
    assert {(e["direction"], e["include_decoder_bias"]) for e in biased.describe() if e["layer"] == 1} == \
        {("sae", True), ("mean_difference", False), ("sae_top_k", False)}


def test_vectors_without_a_recorded_r_take_vector_units_only(catalog, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(pair_folder(catalog, "on_vs_off", 2).parents[1], old)
    path = old / "layer02" / "on_vs_off" / "mean_difference_direction.safetensors"
    # statistics older than the norm record: the steer step writes no R
    write_method_direction(path.parent, dataclasses.replace(read_method_direction(path), mean_residual_norm=None))
    older = VectorCatalog.scan(old)
    assert older.get("on_vs_off", 2).describe()["mean_residual_norm"] is None
    with pytest.raises(RequestError, match=r"no recorded mean_residual_norm.*send \"alpha_units\": \"vector\"") as err:
        parse_steering({"pair": "on_vs_off", "layer": 2, "alpha": 1.0}, older)
    assert err.value.key == "steering.alpha_units" and "\n" not in str(err.value)
    [entry] = parse_steering({"pair": "on_vs_off", "layer": 2, "alpha": 1.5, "alpha_units": "vector"}, older)
    assert entry.vector_alpha == pytest.approx(1.5 * entry.vector.norm)


def test_random_controls_are_norm_matched_seeded_by_name_and_the_same_in_any_process(catalog):
    default = catalog.get("open_vs_close", 1)
    control = catalog.get("open_vs_close", 1, "random_3")
    assert (control.pair, control.layer, control.direction, control.vector.dtype, control.vector.shape) == \
        ("open_vs_close", 1, "random_3", torch.float32, default.vector.shape)
    assert (control.norm, control.mean_residual_norm, control.levels, control.include_decoder_bias) == \
        (default.norm, default.mean_residual_norm, None, False)
    assert float(control.vector.double().norm()) == pytest.approx(1.0, rel=1e-6)
    assert torch.equal(catalog.get("open_vs_close", 1, "random_3").vector, control.vector)
    others = [catalog.get(*key).vector for key in (("open_vs_close", 1, "random_4"), ("on_vs_off", 1, "random_3"),
                                                   ("open_vs_close", 2, "random_3"))]
    assert all(not torch.equal(other, control.vector) for other in others)
    # another process drawing with ATen's scalar kernels (as a CPU without AVX2, where float32 draws differ)
    script = ("from steering_core.serve.catalog import random_direction; "
              f"print(random_direction('open_vs_close', 1, 3, {WIDTH}, 1.0).numpy().tobytes().hex())")
    other = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                           env={**os.environ, "ATEN_CPU_CAPABILITY": "default", "OMP_NUM_THREADS": "2"})
    assert other.stdout.strip() == control.vector.numpy().tobytes().hex()
    # pinned: a machine or torch build drawing other numbers fails here
    assert random_direction("open_vs_close", 12, 0, 2048, 1.0)[:3].tolist() == \
        [0.023906700313091278, 0.039484839886426926, 0.029711419716477394]


def test_random_controls_are_nearly_orthogonal_in_pi05_width():
    # a unit vector uniform on the sphere in d dimensions has P(|cos| > t) <= 2 exp(-d t^2 / 2) against any fixed
    # direction: under 1e-5 at t = 5 / sqrt(d). Controls against three directions (all ones: the mean) and each other.
    width = 2048
    defaults = [SteeringVector("p", 3, "sae", v / v.norm(), float(v.norm()), Path("p"), "residual", 40.0)
                for v in (torch.ones(width), torch.arange(width, dtype=torch.float32), torch.eye(width)[7] * 5)]
    controls = [random_control(defaults[0], k) for k in range(8)]
    assert all(c.norm == defaults[0].norm and float(c.vector.norm()) == pytest.approx(1.0) for c in controls)
    vectors = [c.vector for c in controls]
    pairs = [(c, d.vector) for c in vectors for d in defaults] + \
        [(a, b) for i, a in enumerate(vectors) for b in vectors[i + 1:]]
    assert max(abs(float(a @ b / (a.norm() * b.norm()))) for a, b in pairs) < 5 / math.sqrt(width)


def test_random_controls_in_requests(catalog):
    [entry] = parse_steering({"pair": "on_vs_off", "layer": 2, "alpha": 3.0, "direction": "random_0"}, catalog)
    assert entry.vector.direction == "random_0" and entry.describe()["direction"] == "random_0"
    assert entry.vector_alpha == pytest.approx(3.0 * catalog.get("on_vs_off", 2).mean_residual_norm)
    for name in ("random_1000", "random_01", "random_", "random_-1", "Random_0", "random_0x", "random", "residual",
                 ""):
        with pytest.raises(RequestError, match=r"has \['mean_difference'\] and random_0..random_999") as err:
            parse_steering({"pair": "on_vs_off", "layer": 2, "alpha": 1.0, "direction": name}, catalog)
        assert err.value.key == "steering.direction"


@pytest.mark.parametrize("value, key, problem", [
    ({"pair": "nope", "layer": 1, "alpha": 1.0}, "steering.pair", "unknown pair 'nope'"),
    ({"pair": "open_vs_close", "layer": 7, "alpha": 1.0}, "steering.layer", r"layers \[1, 2\]"),
    ({"pair": "open_vs_close", "layer": 1.0, "alpha": 1.0}, "steering.layer", "integer"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": "4"}, "steering.alpha", "finite number, got str"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": float("nan")}, "steering.alpha", "finite number"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": True}, "steering.alpha", "finite number, got bool"),
    ({"pair": "open_vs_close", "layer": 1}, "steering.alpha", "missing"),
    ({"pair": "open_vs_close", "layer": 2, "alpha": 1, "direction": "sae"}, "steering.direction",
     r"has no 'sae' direction; it has \['mean_difference'\]"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": 1, "scale": 2}, "steering", r"unknown key\(s\) \['scale'\]"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": 1, "alpha_units": "R"}, "steering.alpha_units",
     r"expected one of \['residual_norm', 'vector'\], got str 'R'"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": 1e39}, "steering.alpha",
     r"\|alpha\| is 1e\+39 in residual_norm units, above the server's bound 100 \(serve --max-alpha\)"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": -101.0}, "steering.alpha", "above the server's bound 100"),
    ([{"pair": "open_vs_close", "layer": 1, "alpha": 1}, 3], "steering[1]", "expected a dict"),
    ("open_vs_close", "steering", "expected a dict"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": 1, "mode": "set"}, "steering.mode",
     r"expected one of \['add', 'clamp'\], got str 'set'"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": 1, "mode": ["clamp"]}, "steering.mode", "got list"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": 0.5, "mode": "clamp", "alpha_units": "vector"},
     "steering.alpha_units", "mode 'clamp' takes alpha as the level fraction"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": 0.5, "mode": "clamp", "direction": "random_2"}, "steering.mode",
     r"'random_2' is a random control, with no concept levels to clamp to; use mode 'add', or clamp one of "
     r"\['mean_difference', 'sae', 'sae_top_k'\]"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": "0.5", "mode": "clamp"}, "steering.alpha",
     "finite number, got str"),
    ({"pair": "open_vs_close", "layer": 1, "alpha": -101.0, "mode": "clamp"}, "steering.alpha",
     r"\|alpha\| is 101 in level-fraction units, above the server's bound 100"),
    ([{"pair": "open_vs_close", "layer": 1, "alpha": 0.0, "mode": "clamp"},
      {"pair": "on_vs_off", "layer": 1, "alpha": 1.0, "mode": "clamp", "direction": "mean_difference"}],
     "steering[1].layer", r"layer 1 is clamped by steering\[0\] too"),
])
def test_bad_steering_entries_name_the_key(catalog, value, key, problem):
    with pytest.raises(RequestError, match=problem) as err:
        parse_steering(value, catalog)
    assert err.value.key == key and str(err.value).startswith(f"{key}: ")


# ---------------------------------------------------------------- the real openpi client

def test_openpi_client_round_trip_steering_and_metadata(catalog, observations, tmp_path):
    steer = {"pair": "open_vs_close", "layer": 1, "alpha": 4.0}
    both = [steer, {"pair": "on_vs_off", "layer": 2, "alpha": -2.5, "alpha_units": "vector"}]
    clamp = {"pair": "open_vs_close", "layer": 1, "alpha": 0.75, "direction": "sae_top_k", "mode": "clamp"}
    requests = [{"obs": obs} for obs in observations] + [
        {"obs": observations[0] | {"steering": steer}},
        {"obs": observations[1] | {"steering": both}},
        {"obs": observations[2] | {"steering": {**steer, "direction": "mean_difference"}}},
        {"obs": observations[3] | {"steering": {**steer, "direction": "random_2"}}},
        {"obs": observations[0] | {"steering": clamp}},
    ]
    with running(PolicyServer(FakePolicy(), catalog)) as server:
        [client] = run_openpi_client(tmp_path, server.port, [requests])
    replies = [result["reply"] for result in client["results"]]
    wanted = [expected(catalog, obs) for obs in observations] + [
        expected(catalog, observations[0], ("open_vs_close", 1, 4.0)),
        expected(catalog, observations[1], ("open_vs_close", 1, 4.0), ("on_vs_off", 2, -2.5, None, "vector")),
        expected(catalog, observations[2], ("open_vs_close", 1, 4.0, "mean_difference")),
        expected(catalog, observations[3], ("open_vs_close", 1, 4.0, "random_2")),
        expected(catalog, observations[0], ("open_vs_close", 1, 0.75, "sae_top_k", "clamp")),
    ]
    for reply, actions in zip(replies, wanted, strict=True):
        assert reply["actions"].dtype == np.float32 and reply["actions"].shape == (10, 7)
        assert reply["actions"].tobytes() == actions.tobytes()  # bit for bit
    assert not np.array_equal(replies[4]["actions"], replies[0]["actions"])  # steering changes the actions
    assert replies[0]["steering"] == []
    assert [(s["pair"], s["layer"], s["direction"], s["alpha"], s["alpha_units"]) for s in replies[5]["steering"]] \
        == [("open_vs_close", 1, "sae", 4.0, "residual_norm"), ("on_vs_off", 2, "mean_difference", -2.5, "vector")]
    vector, other = catalog.get("open_vs_close", 1), catalog.get("on_vs_off", 2)
    assert replies[5]["steering"][0]["norm"] == pytest.approx(vector.norm)
    assert replies[5]["steering"][0]["vector_alpha"] == pytest.approx(4.0 * vector.mean_residual_norm)
    assert replies[5]["steering"][1]["vector_alpha"] == pytest.approx(-2.5 * other.norm)
    assert [(s["direction"], s["mode"], s["alpha"], s["alpha_units"]) for s in replies[8]["steering"]] == \
        [("sae_top_k", "clamp", 0.75, None)]
    assert not np.array_equal(replies[8]["actions"], replies[0]["actions"])
    # prev_total_ms from the 2nd request on
    assert set(replies[0]["server_timing"]) == {"infer_ms", "queue_ms", "batch_rows", "batch_requests"}
    assert (replies[0]["server_timing"]["batch_rows"], replies[0]["server_timing"]["batch_requests"]) == (1, 1)
    assert set(replies[1]["server_timing"]) == {"infer_ms", "queue_ms", "batch_rows", "batch_requests", "prev_total_ms"}
    assert replies[0]["policy_timing"] == {"infer_ms": 0.0}
    metadata = client["metadata"]
    assert metadata["policy"] == "fake" and metadata["steering"]["vectors"] == catalog.describe()
    assert "one call at a time" in metadata["server"]["inference"] and metadata["server"]["api_key_required"] is False
    assert (metadata["server"]["max_batch"], metadata["server"]["batch_wait_ms"]) == (16, 5.0)
    assert "zlib.crc32(b'<pair>/<layer>/random_<k>')" in metadata["steering"]["random_controls"]


def test_libero_example_wrapper_adds_the_steering_entry(catalog, observations, tmp_path):
    entry = [{"pair": "on_vs_off", "layer": 1, "alpha": 2.0, "direction": "mean_difference"}]
    with running(PolicyServer(FakePolicy(), catalog)) as server:
        [client] = run_openpi_client(tmp_path, server.port, [[{"obs": obs} for obs in observations[:2]]],
                                     wrapper_steering=entry)
    for obs, result in zip(observations, client["results"], strict=False):
        want = expected(catalog, obs, ("on_vs_off", 1, 2.0, "mean_difference"))
        assert result["reply"]["actions"].tobytes() == want.tobytes()
        assert result["reply"]["steering"][0]["direction"] == "mean_difference"


def test_bad_requests_get_an_error_naming_the_key_and_the_connection_keeps_serving(catalog, observations, tmp_path):
    good = observations[0]
    image = good["observation/image"]
    bad = [
        ({"raw": b"\xc1\x00 this is not msgpack"}, "not msgpack"),
        ({"obs": {k: v for k, v in good.items() if k != "observation/image"}}, "observation/image: missing"),
        ({"obs": good | {"observation/wrist_image": image[:, :, :2].copy()}}, "observation/wrist_image: expected"),
        ({"obs": good | {"observation/image": image.astype(np.float32)}}, "observation/image: expected a uint8"),
        ({"obs": good | {"steering": {"pair": "nope", "layer": 1, "alpha": 1.0}}}, "steering.pair: unknown pair"),
        ({"obs": good | {"steering": {"pair": "on_vs_off", "layer": 9, "alpha": 1.0}}}, "steering.layer: pair"),
        ({"obs": good | {"steering": {"pair": "on_vs_off", "layer": 1, "alpha": "big"}}}, "steering.alpha: expected"),
        ({"obs": good | {"padding": np.zeros(300_000, np.uint8)}}, "message: "),
    ]
    requests = [request for b, _ in bad for request in (b, {"obs": good})]
    policy = FakePolicy()
    with running(PolicyServer(policy, catalog, max_message_bytes=200_000)) as server:
        first, other = run_openpi_client(tmp_path, server.port, [requests, [{"obs": good}] * 3])
    want = expected(catalog, good).tobytes()
    for i, (_, problem) in enumerate(bad):
        error, after = first["results"][2 * i], first["results"][2 * i + 1]
        assert "error" in error and error["error"].startswith("RuntimeError: Error in inference server:"), error
        assert problem in error["error"], (problem, error["error"])
        assert after["reply"]["actions"].tobytes() == want  # the same connection serves the next request
    assert all(result["reply"]["actions"].tobytes() == want for result in other["results"])
    assert policy.calls == len(bad) + 3  # bad requests never reached the policy


@pytest.mark.filterwarnings("ignore:overflow encountered")  # the fake policy's float32 actions overflow to inf
def test_huge_alpha_is_refused_and_non_finite_actions_are_never_returned(catalog, observations):
    huge = {"pair": "open_vs_close", "layer": 1, "alpha": 1e39, "alpha_units": "vector"}
    for max_alpha, problem in ((100.0, "bad request: steering.alpha: |alpha| is "),
                               (math.inf, "inference failed (the server keeps serving): the policy's actions are "
                                          "not finite")):
        with running(PolicyServer(FakePolicy(), catalog, max_alpha=max_alpha)) as server, \
                connect(f"ws://127.0.0.1:{server.port}", max_size=None) as ws:
            assert unpack(ws.recv())["steering"]["max_alpha"] == max_alpha
            ws.send(pack(observations[0] | {"steering": huge}))
            error = ws.recv()
            assert isinstance(error, str) and error.startswith(problem) and "\n" not in error, error
            ws.send(pack(observations[0]))
            assert unpack(ws.recv())["actions"].tobytes() == expected(catalog, observations[0]).tobytes()


def test_ten_concurrent_clients_twenty_requests_each(catalog, observations, tmp_path):
    def request(client: int, i: int) -> dict:
        obs = observations[(client + i) % len(observations)]
        return obs | {"steering": {"pair": "open_vs_close", "layer": 1 + i % 2, "alpha": client + i / 10}}

    clients = [[{"obs": request(c, i)} for i in range(20)] for c in range(10)]
    policy = FakePolicy(delay_s=0.002)
    with running(PolicyServer(policy, catalog)) as server:
        results = run_openpi_client(tmp_path, server.port, clients)
    for c, client in enumerate(results):
        assert len(client["results"]) == 20
        for i, result in enumerate(client["results"]):
            obs = observations[(c + i) % len(observations)]
            want = expected(catalog, obs, ("open_vs_close", 1 + i % 2, c + i / 10))
            assert result["reply"]["actions"].tobytes() == want.tobytes(), (c, i)
    assert policy.calls == 200 and policy.max_concurrent == 1  # one inference at a time


class BatchingFakePolicy(FakePolicy):
    """FakePolicy answering several requests per call (`infer_batch`), recording each call's requests; a prompt
    "explode" passes the request checks but fails the policy, in a batch or alone."""

    def __init__(self) -> None:
        super().__init__(delay_s=0.01)
        self.batches: list[int] = []

    def infer(self, observation: dict, steering) -> dict:
        if observation["prompt"] == "explode":
            raise RuntimeError("the policy failed on this observation")
        return super().infer(observation, steering)

    def infer_batch(self, observations: list[dict], steering: list) -> list[dict]:
        self.batches.append(len(observations))
        if any(observation["prompt"] == "explode" for observation in observations):
            raise RuntimeError("the policy failed on one observation of the batch")
        return [super(BatchingFakePolicy, self).infer(o, s) for o, s in zip(observations, steering, strict=True)]


def test_eight_batched_clients_a_failing_request_fails_alone(catalog, observations, tmp_path):
    """Requests of eight clients share calls; a malformed request is refused before any call, and one that fails
    inside a shared call fails alone: the call is run again request by request, every other reply exact."""
    def request(client: int, i: int) -> dict:
        obs = observations[(client + i) % len(observations)]
        if (client, i) == (3, 2):
            return obs | {"prompt": "explode"}
        if (client, i) == (5, 1):
            return obs | {"observation/state": np.array([np.nan])}
        return obs | {"steering": {"pair": "open_vs_close", "layer": 1 + i % 2, "alpha": client + i / 10}}

    clients = [[{"obs": request(c, i)} for i in range(6)] for c in range(8)]
    policy = BatchingFakePolicy()
    with running(PolicyServer(policy, catalog)) as server:
        results = run_openpi_client(tmp_path, server.port, clients)
    for c, client in enumerate(results):
        for i, result in enumerate(client["results"]):
            if (c, i) == (3, 2):
                assert "inference failed (the server keeps serving): RuntimeError: the policy failed on this " \
                       "observation" in result["error"]
            elif (c, i) == (5, 1):
                assert "bad request: observation/state: the state is not finite" in result["error"]
            else:
                obs = observations[(c + i) % len(observations)]
                want = expected(catalog, obs, ("open_vs_close", 1 + i % 2, c + i / 10))
                assert result["reply"]["actions"].tobytes() == want.tobytes(), (c, i)
    assert max(policy.batches) > 1 and policy.max_concurrent == 1  # calls were shared, one at a time


# ---------------------------------------------------------------- episodes and api key (openpi's current client)

def start(experiment: str, episode_id: int, task: str = "open the top drawer of the cabinet") -> dict:
    """openpi's current WebsocketClientPolicy.episode_start message."""
    return {"ctrl": {"__ctrl__": "episode_start", "__experiment__": experiment, "__task__": task,
                     "__episode_id__": episode_id}}


def end(success) -> dict:
    """openpi's current WebsocketClientPolicy.episode_end message."""
    return {"ctrl": {"__ctrl__": "episode_end", "__success__": success}}


def test_episode_control_messages_are_acknowledged_recorded_logged_and_written(catalog, observations, tmp_path,
                                                                              caplog):
    caplog.set_level(logging.INFO, logger="steering_core.serve.episodes")
    obs = {"obs": observations[0]}
    first = [obs, end(False),                                     # an end without a start: recorded as it is
             start("sweep", 7), {"obs": observations[1] | {"steering": {"pair": "on_vs_off", "layer": 1,
                                                                        "alpha": 2.0, "direction": "random_0"}}},
             obs, end(True),
             start("sweep", 8), {"ctrl": {"__ctrl__": "episode_pause"}}, end("yes"),
             {"ctrl": {"__ctrl__": "episode_end", "__sucess__": True}}, obs, end(False),
             start("sweep", 9), start("sweep", 10)]                # 9 ends when 10 starts; 10 when the client exits
    second = [start("other", 1, task="turn on the stove"), obs, obs, obs, end(True)]
    episodes_file = tmp_path / "episodes.jsonl"
    before = time.time()
    with running(PolicyServer(FakePolicy(), catalog, episode_log=EpisodeLog(episodes_file))) as server:
        a, b = run_openpi_client(tmp_path, server.port, [first, second])
    after = time.time()
    acks = {"episode_start": {"__ack__": "episode_start"}, "episode_end": {"__ack__": "episode_end"}}
    for request, result in zip(first + second, a["results"] + b["results"], strict=True):
        if "obs" in request:  # inference works between (and after refused) control messages
            steering = request["obs"].get("steering")
            want = expected(catalog, request["obs"], *([tuple(steering.values())] if steering else []))
            assert result["reply"]["actions"].tobytes() == want.tobytes()
        elif "reply" in result:  # the refused ones are checked below
            assert result["reply"] == acks[request["ctrl"]["__ctrl__"]]
    errors = [r["error"] for r in a["results"] if "error" in r]
    assert [e.split("\n")[1] for e in errors] == [
        "bad request: __ctrl__: unknown control message 'episode_pause'; expected 'episode_start' or 'episode_end'",
        "bad request: __success__: expected bool, got str 'yes'",
        "bad request: episode_end: unknown key(s) ['__sucess__']; expected ['__success__']"]
    records = server.episodes
    lines = episodes_file.read_text().splitlines()
    assert [json.loads(line) for line in lines] == records  # one whole JSON line per finished episode
    assert {r["client"] for r in records if r["experiment"] != "other"} != {r["client"] for r in records
                                                                            if r["experiment"] == "other"}
    fields = ("experiment", "task", "episode_id", "success", "inferences", "ended_by")
    drawer, stove = "open the top drawer of the cabinet", "turn on the stove"
    assert sorted((tuple(r[f] for f in fields) for r in records), key=str) == sorted([
        (None, None, None, False, 1, "episode_end"),
        ("sweep", drawer, 7, True, 2, "episode_end"),
        ("sweep", drawer, 8, False, 1, "episode_end"),
        ("sweep", drawer, 9, None, 0, "episode_start"),
        ("sweep", drawer, 10, None, 0, "disconnect"),
        ("other", stove, 1, True, 3, "episode_end"),
    ], key=str)
    for r in records:
        assert r["start_time"] is None if r["experiment"] is None else before <= r["start_time"] <= r["end_time"]
        assert before <= r["end_time"] <= after
    logged = [m for m in caplog.messages if m.startswith("episode ") and " from 127.0.0.1:" in m]
    assert len(logged) == len(records)
    for line, r in zip(logged, records, strict=True):  # logged as recorded
        assert line.endswith(f"from {r['client']}: success {r['success']}, {r['inferences']} inference(s), "
                             f"ended by {r['ended_by']}")
    assert any("episode_end from 127.0.0.1:" in m and "without episode_start" in m for m in caplog.messages)


def test_the_episodes_file_rotates_at_its_bound(tmp_path, monkeypatch):
    from steering_core.serve import episodes

    monkeypatch.setattr(episodes, "MAX_EPISODES_FILE_BYTES", 2000)
    path = tmp_path / "episodes.jsonl"
    log = EpisodeLog(path)
    for index in range(40):
        log.add(episodes.Episode("127.0.0.1:1", "exp", "a task", index, 0.0, 3, True, 1.0, "episode_end"))
    rotated = tmp_path / "episodes.jsonl.1"
    assert path.stat().st_size <= 2000 and rotated.stat().st_size <= 2000  # disk use under twice the bound
    ids = [json.loads(line)["episode_id"] for f in (rotated, path) for line in f.read_text().splitlines()]
    assert ids == list(range(40 - len(ids), 40)) and len(ids) > 10  # the newest episodes, in order
    assert len(log.records) == 40


def test_api_key_refuses_the_upgrade_with_401_and_leaves_healthz_open(catalog, observations, tmp_path, caplog):
    key = "k3y-0f-th1s-server"
    with running(PolicyServer(FakePolicy(), catalog, api_key=key)) as server:
        with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=10) as response:
            assert response.status == 200 and response.read() == b"OK\n"
        keyed, none, wrong = run_openpi_client(
            tmp_path, server.port, [[{"obs": observations[0]}, start("keyed", 0), end(True)], [], []],
            api_keys=[key, None, key[:-1] + "X"])
    assert keyed["results"][0]["reply"]["actions"].tobytes() == expected(catalog, observations[0]).tobytes()
    assert keyed["results"][2]["reply"] == {"__ack__": "episode_end"}
    assert keyed["metadata"]["server"]["api_key_required"] is True and key not in json.dumps(keyed["metadata"])
    assert none["status"] == wrong["status"] == 401 and "HTTP 401" in none["error"]
    refused = [m for m in caplog.messages if m.startswith("refused a connection")]
    assert sorted(m.split(": ")[1] for m in refused) == ["no api key", "wrong api key"]
    assert not any(key[:-1] in m for m in caplog.messages)  # neither the key nor the wrong one is logged


def test_api_key_from_a_file_or_the_environment(tmp_path):
    path = tmp_path / "key"
    path.write_text("  s3cret\n")
    assert read_api_key(path, {}) == "s3cret"
    assert read_api_key(path, {API_KEY_ENV: "other"}) == "s3cret"  # the file given explicitly wins
    assert read_api_key(None, {API_KEY_ENV: " env-key "}) == "env-key"
    assert read_api_key(None, {}) is None
    for text, problem in (("\n  \n", "is empty"), ("two words", "printable ASCII without spaces")):
        path.write_text(text)
        with pytest.raises(ValueError, match=problem) as err:
            read_api_key(path, {})
        assert str(path) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ValueError, match=rf"\${API_KEY_ENV} is empty"):
        read_api_key(None, {API_KEY_ENV: ""})
    assert authorized(["Api-Key s3cret"], "s3cret")
    assert not any(authorized(values, "s3cret") for values in
                   ([], ["Api-Key s3cre"], ["Api-Key s3cret "], ["Bearer s3cret"], ["Api-Key s3cret"] * 2))


# ---------------------------------------------------------------- health, keepalive, default steering, shutdown

class WarmingPolicy(FakePolicy):
    """A fake policy whose warm-up records whether the server already listened."""

    def __init__(self, events: list[str]) -> None:
        super().__init__()
        self.events = events

    def warm_up(self, max_rows: int) -> None:
        self.events.append(f"warm_up {max_rows}")


def test_warm_up_runs_once_before_the_server_listens(catalog):
    events: list[str] = []
    server = PolicyServer(WarmingPolicy(events), catalog, port=0, max_batch=6)

    def ready() -> None:
        events.append("ready")
        server.request_stop()

    asyncio.run(server.serve(ready=ready))
    assert events == ["warm_up 6", "ready"]  # every row count a batched call may have


class CompiledRecorder:
    """A compiled policy's stand-in: records the batch sizes it is warmed up at."""

    def __init__(self, compiled: bool) -> None:
        self.compiled, self.batches = compiled, []

    def warm_up(self, batch: int) -> None:
        self.batches.append(batch)


def test_a_served_compiled_policy_warms_every_row_bucket_up_to_the_served_batch():
    for max_rows, expected in ((1, [1]), (6, [1, 2, 4, 8]), (16, [1, 2, 4, 8, 16]), (40, [1, 2, 4, 8, 16])):
        policy = CompiledRecorder(compiled=True)
        SteeredPi05Policy(policy).warm_up(max_rows)
        assert policy.batches == expected, max_rows  # past 16 rows the denoising step runs eagerly
    eager = CompiledRecorder(compiled=False)
    SteeredPi05Policy(eager).warm_up(16)
    assert eager.batches == []


def test_health_check_and_default_steering(catalog, observations):
    default = parse_steering({"pair": "on_vs_off", "layer": 2, "alpha": 3.0}, catalog)
    with running(PolicyServer(FakePolicy(), catalog, default_steering=default)) as server:
        with urllib.request.urlopen(f"http://127.0.0.1:{server.port}/healthz", timeout=10) as response:
            assert response.status == 200 and response.read() == b"OK\n"
        with connect(f"ws://127.0.0.1:{server.port}", max_size=None) as ws:
            assert unpack(ws.recv())["steering"]["default"] == [s.describe() for s in default]
            ws.send(pack(observations[0]))
            defaulted = unpack(ws.recv())
            ws.send(pack(observations[0] | {"steering": None}))
            plain = unpack(ws.recv())
    assert defaulted["actions"].tobytes() == expected(catalog, observations[0], ("on_vs_off", 2, 3.0)).tobytes()
    assert plain["actions"].tobytes() == expected(catalog, observations[0]).tobytes() and plain["steering"] == []


def test_pings_are_answered_while_inference_runs(catalog, observations):
    # a client pinging every 0.1 s with a 0.2 s timeout gives up during a 1.5 s inference on the event loop
    with running(PolicyServer(FakePolicy(delay_s=1.5), catalog)) as server:
        with connect(f"ws://127.0.0.1:{server.port}", ping_interval=0.1, ping_timeout=0.2, max_size=None) as ws:
            ws.recv()
            ws.send(pack(observations[0]))
            assert unpack(ws.recv())["actions"].shape == (10, 7)


def test_stop_finishes_the_request_in_flight_then_closes_every_connection(catalog, observations):
    server = PolicyServer(FakePolicy(delay_s=1.0), catalog)
    with running(server):
        url = f"ws://127.0.0.1:{server.port}"
        with connect(url, max_size=None) as busy, connect(url, max_size=None) as idle:
            busy.recv(), idle.recv()
            busy.send(pack(observations[0]))
            time.sleep(0.3)  # inference is running
            server.request_stop()
            reply = unpack(busy.recv(timeout=10))
            assert reply["actions"].tobytes() == expected(catalog, observations[0]).tobytes()
            for ws in (busy, idle):
                with pytest.raises(ConnectionClosed) as closed:
                    ws.recv(timeout=10)
                assert closed.value.rcvd.code == 1001


def test_asking_a_stopped_server_to_stop_again_does_nothing(catalog):
    """A stop asked for inside the block (as above) is asked again on leaving it, after the loop has closed."""
    server = PolicyServer(FakePolicy(), catalog)
    with running(server):
        pass
    server.request_stop()


@pytest.mark.slow
def test_sigterm_answers_the_request_in_flight_and_exits_cleanly(catalog, observations, tmp_path):
    vectors = next(iter(catalog)).path.parents[2]
    script = textwrap.dedent(f"""
        import logging, sys
        logging.basicConfig(level=logging.INFO)
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from helpers_serve import FakePolicy
        from steering_core.serve import PolicyServer, VectorCatalog
        server = PolicyServer(FakePolicy(delay_s=1.0), VectorCatalog.scan({str(vectors)!r}), port=0)
        server.run()
    """)
    process = subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True)
    try:
        port = port_from_log(process)
        with connect(f"ws://127.0.0.1:{port}", max_size=None) as ws:
            ws.recv()
            ws.send(pack(observations[1]))
            time.sleep(0.3)
            process.send_signal(signal.SIGTERM)
            assert unpack(ws.recv(timeout=10))["actions"].tobytes() == expected(catalog, observations[1]).tobytes()
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=10)
        assert process.wait(timeout=20) == 0
    finally:
        process.kill()



def test_serving_guide_commands_use_existing_flags():
    import re

    import typer

    import latent_steering_cli.serve  # noqa: F401  (commands are imported lazily; this registers `serve`)
    from latent_steering_cli import app

    guide = (Path(__file__).resolve().parents[1] / "docs" / "serving.md").read_text(encoding="utf-8")
    section = guide.split("## Steered rollouts in LIBERO", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"latent-steering serve (.*?)\n(?:until )?curl", section, re.S)  # real and demo
    serve = typer.main.get_command(app).commands["serve"]
    known = {opt for param in serve.params for opt in param.opts}
    assert len(commands) == 2
    for command in commands:
        used = set(re.findall(r"(--[a-z][a-z-]+)", command))
        assert used and used <= known, used - known
    assert "--steer open_vs_close:12:2.0" in section and parse_steering_option("open_vs_close:12:2.0")
