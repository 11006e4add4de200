"""Policy server: round-trip latency over loopback against a direct `infer` call, and steering's added latency.

The served policy is `SteeredPi05Policy` over a random tiny pi0.5 checkpoint (openpi's "dummy" Gemma sizes),
with the same fixed noise for every call so each call does the same work. Each of 200 rounds times, in
turn, a direct `infer` call and a round trip through `PolicyServer` on 127.0.0.1 (a client in this process
doing what openpi-client does: msgpack-numpy pack, send, receive, unpack), plain and steered, so machine
load falls on all of them alike; direct calls run in a worker thread like the server's inference. The
overhead is the server's median minus the direct median; a server whose policy does no work times the
protocol alone. Steering's added latency is measured at a mid-size model (width 256, 6 layers) by direct
calls of the served policy, plain against one steering vector at the instruction tokens (the tokenizer's
instruction span included); its p99 is not a target, the small difference sinks in the noise of a loaded
machine.

    uv run python -m bench.serve_latency [--device cuda] [--quick]
"""

from __future__ import annotations

import argparse
import contextlib
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.common import Result, cache_dir, command, finish, median, parser, synchronize, torch_threads
from steering_core.devices import resolve_device

# ----------------------------------------------------------------------------- settings

ROUNDS = 200  # round trips per variant
MID_ROUNDS = 30  # steered/plain pairs at the mid-size model
OVERHEAD_TARGET_MS = 5.0
STEERING_TARGET = 0.02  # steered / plain - 1 at the mid-size model
NOISE_SEED = 0
PAIR, LAYER, ALPHA = "open_vs_close", 1, 4.0
QUICK = {"rounds": 5, "mid_rounds": 2}  # and the tiny model stands in for the mid-size one


def mid_arch() -> Any:
    """Return the mid-size model: 6 layers of width 256 (real pi0.5: 18 of 2048), 16 tokens per image."""
    from steering_core.pi05 import Pi05Arch

    return Pi05Arch(width=256, depth=6, mlp_dim=1024, num_heads=4, num_kv_heads=1, head_dim=64, vocab_size=512,
                    vision_width=64, vision_depth=2, vision_mlp_dim=256, vision_heads=2, patch_size=14,
                    image_size=56)


def build_policy(folder: Path, arch: Any, device: torch.device) -> tuple[Any, Any]:
    """Return (served policy, vector catalog) of a random checkpoint of `arch`, cached under `folder`."""
    from steering_core.pi05.policy import Pi05Policy
    from steering_core.synthetic.pi05 import write_pi05_checkpoint
    from steering_core.synthetic.tokenizer import write_tokenizer

    folder = folder / f"width{arch.width}-depth{arch.depth}-image{arch.image_size}"  # one cache per size
    checkpoint, tokenizer = folder / "ckpt", folder / "tokenizer.model"
    if not checkpoint.is_dir():
        write_pi05_checkpoint(checkpoint, arch, seed=1)
    if not tokenizer.is_file():
        write_tokenizer(tokenizer)
    return steered(Pi05Policy.from_checkpoint(checkpoint, arch, device=device, tokenizer_path=tokenizer), checkpoint)


def steered(policy: Any, checkpoint: Path) -> tuple[Any, Any]:
    """Return (served policy with fixed noise, a catalog of one random CPU vector at LAYER) for a `Pi05Policy`."""
    from steering_core.serve import SteeredPi05Policy, SteeringVector, VectorCatalog

    vector = torch.randn(policy.arch.width, generator=torch.Generator().manual_seed(2))
    catalog = VectorCatalog([SteeringVector(PAIR, LAYER, "mean_difference", vector / vector.norm(),
                                            float(vector.norm()), checkpoint, "residual")])
    served = SteeredPi05Policy(policy, noise_seed=NOISE_SEED)
    served.check_catalog(catalog)
    return served, catalog


def observation() -> dict[str, Any]:
    """Return one observation as openpi's LIBERO client sends it (224 x 224 images, float64 state)."""
    rng = np.random.default_rng(0)
    return {
        "observation/image": rng.integers(0, 256, (224, 224, 3), dtype=np.uint8),
        "observation/wrist_image": rng.integers(0, 256, (224, 224, 3), dtype=np.uint8),
        "observation/state": rng.normal(size=8),
        "prompt": "open the top drawer of the cabinet",
    }


def percentile(values: list[float], q: float) -> float:
    """Return the q-th percentile (linear interpolation), in the units of `values`."""
    return float(np.percentile(values, q))


def round_trips(served: Any, catalog: Any, device: torch.device, rounds: int) -> tuple[dict[str, list[float]], bool]:
    """Return per-variant call times in ms (direct/server x plain/steered) and whether served == direct bits."""
    from websockets.sync.client import connect

    from steering_core.serve import PolicyServer, parse_steering
    from steering_core.serve.codec import pack, unpack
    from steering_core.serve.server import serving_in_thread

    obs = observation()
    entry = {"pair": PAIR, "layer": LAYER, "alpha": ALPHA, "alpha_units": "vector"}  # its vector records no R
    steering = parse_steering(entry, catalog)
    times: dict[str, list[float]] = {key: [] for key in ("direct", "server", "direct steered", "server steered")}
    same = True
    with serving_in_thread(PolicyServer(served, catalog, host="127.0.0.1", port=0)) as server, \
            connect(f"ws://127.0.0.1:{server.port}", compression=None, max_size=None) as ws, \
            ThreadPoolExecutor(1) as worker:
        ws.recv()  # metadata

        def direct(steer: tuple) -> np.ndarray:
            return worker.submit(call_policy, served, obs, steer, device).result()["actions"]

        def remote(steer: tuple) -> np.ndarray:
            ws.send(pack(obs | {"steering": entry} if steer else obs))
            return unpack(ws.recv())["actions"]

        for index in range(rounds + 1):  # the first round warms up
            for name, call, steer in (("direct", direct, ()), ("server", remote, ()),
                                      ("direct steered", direct, steering), ("server steered", remote, steering)):
                start = time.perf_counter()
                actions = call(steer)
                elapsed = (time.perf_counter() - start) * 1000
                if index:
                    times[name].append(elapsed)
                if index == 1:
                    reference = direct(steer)
                    same &= actions.tobytes() == reference.tobytes()
    return times, same


def call_policy(served: Any, obs: dict, steer: tuple, device: torch.device) -> dict:
    """Return served.infer(obs, steer), its device work finished."""
    result = served.infer(obs, steer)
    synchronize(device)
    return result


class FixedActions:
    """A served policy that does no work: its round trips time the protocol alone (codec, socket, threads)."""

    metadata = {"policy": "fixed actions"}

    def __init__(self, actions: np.ndarray) -> None:
        self.actions = actions

    def infer(self, observation: dict, steering: tuple) -> dict:
        return {"actions": self.actions, "policy_timing": {"infer_ms": 0.0}}


def protocol_cost(rounds: int) -> list[float]:
    """Return round-trip times in ms through a server whose policy does no work."""
    from websockets.sync.client import connect

    from steering_core.serve import PolicyServer
    from steering_core.serve.codec import pack, unpack
    from steering_core.serve.server import serving_in_thread

    obs, times = observation(), []
    policy = FixedActions(np.zeros((10, 7), np.float32))
    with serving_in_thread(PolicyServer(policy, host="127.0.0.1", port=0)) as server, \
            connect(f"ws://127.0.0.1:{server.port}", compression=None, max_size=None) as ws:
        ws.recv()
        for index in range(rounds + 1):
            start = time.perf_counter()
            ws.send(pack(obs))
            unpack(ws.recv())
            if index:
                times.append((time.perf_counter() - start) * 1000)
    return times


def steering_cost(served: Any, catalog: Any, device: torch.device, rounds: int) -> dict[str, list[float]]:
    """Return direct call times in ms of the served policy, plain and steered, alternated."""
    from steering_core.serve import parse_steering

    obs = observation()
    steering = parse_steering({"pair": PAIR, "layer": LAYER, "alpha": ALPHA, "alpha_units": "vector"}, catalog)
    times: dict[str, list[float]] = {"plain": [], "steered": []}
    for index in range(rounds + 1):
        for name, steer in (("plain", ()), ("steered", steering)):
            start = time.perf_counter()
            call_policy(served, obs, steer, device)
            if index:
                times[name].append((time.perf_counter() - start) * 1000)
    return times


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)
    # on CPU one intra-op thread: two thrash on a shared 2-core machine (see the notes)
    with torch_threads(1) if device.type == "cpu" else contextlib.nullcontext():
        return measure(args, device)


def measure(args: argparse.Namespace, device: torch.device) -> Result:
    """Time the round trips, the protocol and steering's cost; return the result."""
    folder = cache_dir(args) / "serve"
    rounds, mid_rounds = (QUICK["rounds"], QUICK["mid_rounds"]) if args.quick else (ROUNDS, MID_ROUNDS)
    from steering_core.synthetic.pi05 import tiny_arch

    served, catalog = build_policy(folder, tiny_arch(), device)
    times, same = round_trips(served, catalog, device, rounds)
    protocol = protocol_cost(rounds)
    mid_served, mid_catalog = (served, catalog) if args.quick else build_policy(folder, mid_arch(), device)
    mid = steering_cost(mid_served, mid_catalog, device, mid_rounds)
    mid_label = "tiny model (--quick)" if args.quick else "mid-size model"

    med = {name: median(values) for name, values in times.items()} | {f"mid {k}": median(v) for k, v in mid.items()}
    overhead = med["server"] - med["direct"]
    steered_overhead = med["server steered"] - med["direct steered"]
    steering_added = med["mid steered"] / med["mid plain"] - 1
    table = [
        {"call": f"tiny model: {name}", "calls": len(values), "median ms": med[name],
         "p99 ms": percentile(values, 99)} for name, values in times.items()
    ] + [
        {"call": "server, policy doing no work (protocol alone)", "calls": len(protocol),
         "median ms": median(protocol), "p99 ms": percentile(protocol, 99)},
    ] + [
        {"call": f"{mid_label}: {name} (direct)", "calls": len(values), "median ms": med[f"mid {name}"],
         "p99 ms": percentile(values, 99)} for name, values in mid.items()
    ]
    return finish(Result(
        name="serve_latency",
        title="8. Policy server latency (loopback round trip, steering)",
        command=command("serve_latency", args),
        measured=f"{med['server']:.2f} ms median round trip",
        baseline=f"{med['direct']:.2f} ms direct infer",
        ratio=med["server"] / med["direct"],
        target=f"overhead <= {OVERHEAD_TARGET_MS:g} ms median; steering < {STEERING_TARGET:.0%} (mid-size)",
        met=overhead <= OVERHEAD_TARGET_MS and steering_added < STEERING_TARGET,
        table=table,
        notes=[
            f"server overhead (median round trip - median direct infer, tiny model): {overhead:.2f} ms plain, "
            f"{steered_overhead:.2f} ms steered (p99 {percentile(times['server'], 99):.2f} ms round trip "
            f"vs {percentile(times['direct'], 99):.2f} ms direct)",
            f"the protocol alone (pack, send, receive, check, reply, unpack of a LIBERO observation, with a "
            f"policy doing no work): {median(protocol):.2f} ms median round trip",
            f"steering's added latency at the {mid_label}: {steering_added:+.1%} of the plain median "
            f"(tiny model, direct: {med['direct steered'] / med['direct'] - 1:+.1%})",
            f"served actions equal direct infer bit for bit: {same}",
            "client and server share this process (and its GIL) on loopback, as a policy server and its "
            "simulator client share a machine; direct calls run in a worker thread, as the server's do",
            "on CPU torch runs one intra-op thread: on this shared 2-core machine two threads made single calls "
            "up to 10x slower and erratic",
        ],
        checks={"served_equals_direct": same, "overhead_ms": overhead, "steering_added": steering_added},
    ), args)


if __name__ == "__main__":
    main()
