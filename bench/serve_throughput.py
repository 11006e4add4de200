"""Policy server under concurrent clients: calls/s with dynamic batching against one request per call, and the
modelled time of a closed-loop study on one GPU machine.

1. Calls/s against concurrent clients (1, 2, 4, 8), batching on (`PolicyServer` defaults: up to 16 rows per
   call, a 5 ms window) against off (`max_batch=1`, one request per call, as before batching), with the random
   tiny pi0.5 (openpi's "dummy" sizes) and a mid-size one (`bench.capture_throughput.ARCH`: real depths and
   sequence lengths, 8x narrower) on the CPU. Each client is a thread of this process doing what openpi's client
   does (msgpack-numpy pack, send, wait, unpack) in a closed loop, each with its own steering (none, or a vector
   at α 1..7) on one real-size LIBERO observation; the server runs in a thread of this process on 127.0.0.1.
   Calls/s counts every client's calls from a barrier to the last reply. Every reply is checked against the same
   request answered alone (within float32 rounding). The headline: 8 clients batched over 8 clients unbatched.
2. The modelled wall time of one steering grid at the field's scale (2,000 episodes of up to 300 steps, 120,000
   policy rows) on one machine with one GPU and 16 simulator cores: GPU time of the batched calls (each the
   larger of the batch-1 latency floor and the rows' FLOPs at an assumed MFU), and simulator time (steps at the
   measured per-core rate plus a camera render per replan), added (no overlap: an upper bound). Every input is
   listed with where it comes from; a GPU check JSON (`bench.gpu_check --json`) replaces the H200 defaults.

    uv run python -m bench.serve_throughput [--quick] [--gpu-check gpu_check.json]
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import Result, cache_dir, command, finish, parser, torch_threads
from bench.serve_latency import build_policy, observation

# ----------------------------------------------------------------------------- settings

CLIENTS = (1, 2, 4, 8)
CALLS = {"tiny": 12, "mid": 3}  # calls per client per configuration
TARGET = 3.0  # 8 clients: batched calls/s over unbatched
QUICK = {"clients": (1, 8), "calls": {"tiny": 2}}

# the grid (issue 35): 2 sides x (α = 0, the swap, 3 α x (direction, 4 randoms, wrong concept)) = 40 cells
GRID = {"episodes": 2000, "max_steps": 300, "wait_steps": 10, "replan": 5, "sim_cores": 16, "rows_per_call": 16}
# inputs the model takes when no GPU check JSON is given: the first H200 run (BENCHMARKS.md, GPU check)
H200 = {"peak_tflops": 796.0, "batch1_ms": 192.0, "source": "first H200 run, eager sample_actions (2026-12-04)"}
MFU = 0.40  # assumed fraction of the peak a batched sample_actions reaches (capture's forward reached 0.56)
# the simulator on this machine (BENCHMARKS.md section 12): steps/s per core without rendering, and the cost of
# rendering both 256 px cameras once (Mesa's software renderer; a GPU machine's EGL renders faster)
SIM = {"steps_per_s": 93.7, "render_s": 0.216, "source": "this machine, section 12"}
PROMPT_TOKENS = 16  # longest LIBERO prompt of a batch (bench.capture_throughput's assumption)


def client(port: int, requests: list[dict], calls: int, barrier: threading.Barrier, out: dict, index: int) -> None:
    """Send one observation `calls` times in a closed loop (after one untimed call); record the replies."""
    from websockets.sync.client import connect

    from steering_core.serve.codec import pack, unpack

    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
        ws.recv()  # metadata
        message = pack(requests[index])
        ws.send(message)
        first = unpack(ws.recv())
        barrier.wait()
        rows = []
        for _ in range(calls):
            ws.send(message)
            rows.append(unpack(ws.recv())["server_timing"]["batch_rows"])
        out[index] = {"first": first["actions"], "ended": time.perf_counter(), "rows": rows}


def clients_run(served: Any, catalog: Any, requests: list[dict], count: int, calls: int, max_batch: int) -> dict:
    """Return calls/s, mean rows per call and the first replies of `count` concurrent clients."""
    from steering_core.serve import PolicyServer
    from steering_core.serve.server import serving_in_thread

    out: dict[int, dict] = {}
    barrier = threading.Barrier(count + 1)
    with serving_in_thread(PolicyServer(served, catalog, host="127.0.0.1", port=0, max_batch=max_batch)) as server:
        threads = [threading.Thread(target=client, args=(server.port, requests, calls, barrier, out, i))
                   for i in range(count)]
        for thread in threads:
            thread.start()
        barrier.wait()
        start = time.perf_counter()
        for thread in threads:
            thread.join()
    wall = max(entry["ended"] for entry in out.values()) - start
    rows = [row for entry in out.values() for row in entry["rows"]]
    return {"calls_per_s": count * calls / wall, "rows": float(np.mean(rows)), "first": [out[i]["first"]
                                                                                           for i in range(count)]}


def requests_of(catalog: Any, count: int) -> list[dict]:
    """Return each client's request: the same observation, client i steered at α = i (client 0 unsteered)."""
    pair, layer = next(iter(catalog)).pair, next(iter(catalog)).layer
    steer = [{"steering": {"pair": pair, "layer": layer, "alpha": float(i), "alpha_units": "vector"}} if i else {}
             for i in range(count)]
    return [observation() | entry for entry in steer]


def alone(served: Any, catalog: Any, request: dict) -> np.ndarray:
    """Return the actions of `request` answered on its own."""
    from steering_core.serve import parse_steering

    entry = request.get("steering")
    steering = parse_steering(entry, catalog) if entry else ()
    return served.infer({k: v for k, v in request.items() if k != "steering"}, steering)["actions"]


def matches(got: np.ndarray, want: np.ndarray) -> bool:
    """Return True when `got` equals `want` within float32 rounding of the batch position (64 eps of the max)."""
    bound = 64 * float(np.finfo(np.float32).eps) * max(1.0, float(np.abs(want).max()))
    return bool(np.abs(got - want).max() <= bound)


def gpu_inputs(path: Path | None) -> dict[str, Any]:
    """Return the model's GPU inputs: the H200 defaults, or the peak and batch-1 latency of a GPU check JSON."""
    if path is None:
        return dict(H200)
    from bench.gpu_check import read_figures

    figures = read_figures(path, "peak_tflops", "sample_actions_ms")
    return {"peak_tflops": float(figures["peak_tflops"]), "batch1_ms": float(figures["sample_actions_ms"]["1"]),
            "source": f"GPU check {path}"}


def grid_model(gpu: dict[str, Any], episodes: int = GRID["episodes"], sim: dict[str, Any] | None = None
               ) -> list[dict[str, Any]]:
    """Return the modelled time of a study of `episodes` episodes: inputs, GPU time, simulator time (`sim`: steps/s
    and s per render of one core, default section 12's), their sum (upper bound) and the phase's time with its
    workers sharing one policy server (GPU calls overlapping the stepping)."""
    from bench.capture_throughput import REAL_ARCH, sample_flops
    from steering_core.rollout.settings import DEFAULT_ENVS_PER_WORKER

    sim = sim or SIM
    steps = GRID["max_steps"]
    calls_per_episode = math.ceil(steps / GRID["replan"])
    rows = episodes * calls_per_episode
    row_s = sample_flops(REAL_ARCH, PROMPT_TOKENS) / (MFU * gpu["peak_tflops"] * 1e12)
    per_call = max(gpu["batch1_ms"] / 1000, GRID["rows_per_call"] * row_s)
    gpu_s = math.ceil(rows / GRID["rows_per_call"]) * per_call
    episode_sim_s = (steps + GRID["wait_steps"]) / sim["steps_per_s"] + calls_per_episode * sim["render_s"]
    sim_s = episodes * episode_sim_s / GRID["sim_cores"]
    # a worker steps DEFAULT_ENVS_PER_WORKER envs in lockstep and waits for one call per replan of them
    wait_s = rows * per_call / (GRID["sim_cores"] * DEFAULT_ENVS_PER_WORKER)
    return [
        {"quantity": "policy rows (episodes x calls per episode)", "value": rows,
         "from": f"{episodes} episodes x {calls_per_episode} replans of {steps} steps"},
        {"quantity": "GPU s per call of rows_per_call rows", "value": per_call,
         "from": f"max(batch-1 floor {gpu['batch1_ms']:g} ms, {GRID['rows_per_call']} rows x "
                 f"{row_s * 1000:.2f} ms at {MFU:.0%} of {gpu['peak_tflops']:g} TFLOP/s); {gpu['source']}"},
        {"quantity": "GPU minutes", "value": gpu_s / 60, "from": "calls x s per call"},
        {"quantity": "simulator minutes", "value": sim_s / 60,
         "from": f"{GRID['sim_cores']} cores at {sim['steps_per_s']:g} steps/s + {sim['render_s']:g} s per replan "
                 f"render ({sim['source']})"},
        {"quantity": "study minutes (GPU + simulator, no overlap)", "value": (gpu_s + sim_s) / 60,
         "from": "upper bound; overlapping GPU calls with stepping approaches the larger of the two"},
        {"quantity": "phase minutes (workers sharing one policy server)", "value": max(gpu_s, sim_s + wait_s) / 60,
         "from": f"max(GPU minutes, simulator minutes + each of {GRID['sim_cores']} workers' wait for one call per "
                 f"replan of its {DEFAULT_ENVS_PER_WORKER} lockstep envs: {wait_s / 60:.1f} min)"},
    ]


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return its result."""
    args = parser(__doc__.splitlines()[0])
    args.add_argument("--gpu-check", type=Path, default=None, help="A bench.gpu_check JSON for the grid model.")
    args = args.parse_args(argv)
    if args.device != "cpu":
        raise SystemExit("bench.serve_throughput measures the server on the CPU: --device cpu only")
    with torch_threads(1):  # the policy thread on one core, the clients and the event loop on the other
        return measure(args)


def measure(args: argparse.Namespace) -> Result:
    """Take every measurement; return the result."""
    from bench.capture_throughput import ARCH as MID_ARCH
    from steering_core.synthetic.pi05 import tiny_arch

    counts = QUICK["clients"] if args.quick else CLIENTS
    sizes = QUICK["calls"] if args.quick else CALLS
    archs = {"tiny": tiny_arch(), "mid": MID_ARCH}
    table, same, rates = [], True, {}
    for size, calls in sizes.items():
        served, catalog = build_policy(cache_dir(args) / "serve", archs[size], "cpu")
        requests = requests_of(catalog, max(counts))
        expected = [alone(served, catalog, request) for request in requests]
        for count in counts if size == "tiny" else (1, max(counts)):
            for batching, max_batch in (("off", 1), ("on", 16)):
                run = clients_run(served, catalog, requests, count, calls, max_batch)
                same &= all(matches(got, want) for got, want in zip(run["first"], expected))
                rates[size, count, batching] = run["calls_per_s"]
                table.append({"policy": size, "clients": count, "batching": batching,
                              "calls/s": run["calls_per_s"], "rows per call": run["rows"],
                              "vs unbatched": run["calls_per_s"] / rates[size, count, "off"]})
    top = max(counts)
    ratio = rates["tiny", top, "on"] / rates["tiny", top, "off"]
    model = grid_model(gpu_inputs(args.gpu_check))
    study = model[-1]["value"]
    notes = [f"{row['quantity']}: {row['value']:.4g} ({row['from']})" for row in model]
    notes.append(f"every client's reply equals its request answered alone, within float32 rounding: {same}")
    return finish(Result(
        name="serve_throughput",
        title="16. Policy server under concurrent clients (dynamic batching), and the study it serves",
        command=command("serve_throughput", args),
        measured=f"{rates['tiny', top, 'on']:.1f} calls/s batched",
        baseline=f"{rates['tiny', top, 'off']:.1f} calls/s one request per call",
        ratio=ratio,
        target=f">= {TARGET:g}x with {top} clients (tiny pi0.5); the modelled grid under 60 min",
        met=ratio >= TARGET and study < 60,
        table=table,
        notes=notes,
        checks={"same_as_alone": bool(same), "study_minutes": study,
                "clients": list(counts), "rows_per_call_8": next(row["rows per call"] for row in table
                                                                 if row["clients"] == top and row["batching"] == "on")},
    ), args)


if __name__ == "__main__":
    main()
