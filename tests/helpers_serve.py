"""Policy-server test helpers: steer-step vectors, LIBERO observations, a fake policy, a server thread, the
real openpi client run in its own environment, and equal kernel settings for comparing actions across processes."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from steering_core.data.libero import read_demo
from steering_core.serve import codec
from steering_core.serve.server import PolicyServer, serving_in_thread
from steering_core.synthetic.libero import DRAWER_OPEN, MotionSpec, SyntheticSettings, SyntheticTask, write_libero_file
from steering_core.synthetic.sae import write_sae_folder
from steering_core.vectors.directions import SteeringSettings, compute_steering

CLIENT_SCRIPT = Path(__file__).with_name("openpi_client_script.py")
OPENPI_CLIENT = ("--with", "openpi-client==0.1.2", "--with", "typing_extensions")  # 0.1.2 omits typing_extensions
PAIRS = ("open_vs_close", "on_vs_off")
# the direction methods write_vectors asks the steer step for, at its SAE layer and at its plain layer
SAE_METHODS, PLAIN_METHODS = ("sae", "mean_difference", "sae_top_k"), ("mean_difference",)

# Equal results across processes need equal kernels. The intra-op thread count changes how gemm and sum split
# their work (so the last bits of float32 results), and oneMKL's default MKL_DYNAMIC=TRUE lets it use fewer
# threads than asked at run time; torch turns that off only in a process that calls torch.set_num_threads.
# A server subprocess gets this environment, the test process `fixed_threads()`: one thread on both sides.
FIXED_THREADS_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OMP_DYNAMIC": "FALSE", "MKL_DYNAMIC": "FALSE"}
# Served and direct float32 actions may still differ by rounding if a kernel sums in another order: each action
# ends 10 Euler steps of the model, each a few ulps of the largest value from the order. Measured on the tiny
# checkpoint: ATen's AVX2 kernels instead of AVX-512 move actions by 2 eps * max|action| (6e-7 at 2.6). The
# bound, 64 eps * max(1, max|action|) (2e-5 at 2.6), leaves room for that and is 4000x below the steering's
# effect on these actions (0.08), so a server that ignored or misapplied steering still fails.
ACTION_ROUNDING_EPS = 64


def write_vectors(root: Path, width: int, *, sae_layer: int = 1, plain_layer: int = 2,
                  include_decoder_bias: bool = False) -> Path:
    """Run the real steer step on random concept rows: an SAE at `sae_layer` (methods SAE_METHODS), none at
    `plain_layer` (PLAIN_METHODS). Return the output root."""
    work = root.parent / f"{root.name}_inputs"
    pairs = []
    for i, pair in enumerate(PAIRS):
        paths = {}
        for j, side in enumerate(("positive", "negative")):
            gen = torch.Generator().manual_seed(10 * i + j)
            paths[side] = work / f"{pair}_{side}.pt"
            paths[side].parent.mkdir(parents=True, exist_ok=True)
            torch.save(torch.randn(20, width, generator=gen) + 2.0 * (j - 0.5) * (i + 1), paths[side])
        pairs.append({"name": pair, "positive_label": f"{pair}+", "positive_path": str(paths["positive"]),
                      "negative_label": f"{pair}-", "negative_path": str(paths["negative"])})
    config = work / "pairs.json"
    config.write_text(json.dumps({"pairs": pairs}))
    sae = write_sae_folder(work / "sae", d_in=width, d_sae=3 * width, hook_layer=sae_layer)
    for layer, sae_path, methods in ((sae_layer, sae, SAE_METHODS), (plain_layer, None, PLAIN_METHODS)):
        compute_steering(SteeringSettings(pairs_config=config, output_root=root, layer=layer, device="cpu",
                                          sae=str(sae_path) if sae_path else None, methods=methods,
                                          include_decoder_bias=include_decoder_bias))
    return root


def libero_observations(folder: Path, frames: int = 4, image_size: int = 32) -> list[dict]:
    """Return observations of a generated LIBERO demo as openpi's LIBERO client builds them: both images
    rotated 180 degrees (`[::-1, ::-1]`), the state eef position + axis-angle + gripper qpos in float64."""
    task = SyntheticTask(instruction=DRAWER_OPEN, motion=MotionSpec(axis=2, direction=1))
    settings = SyntheticSettings(image_size=image_size, num_steps=max(8, frames), state_dim=12)
    demo_file = write_libero_file(folder, task, num_demos=1, settings=settings)
    demo = read_demo(demo_file.path, demo_file.demos[0].demo)
    return [{
        "observation/image": np.ascontiguousarray(demo.agentview_rgb[t, ::-1, ::-1]),
        "observation/wrist_image": np.ascontiguousarray(demo.eye_in_hand_rgb[t, ::-1, ::-1]),
        "observation/state": np.concatenate([demo.ee_pos[t], demo.ee_ori[t], demo.gripper_states[t]]),
        "prompt": task.instruction,
    } for t in range(frames)]


class FakePolicy:
    """A deterministic stand-in with the served-policy protocol: actions from image, state, prompt and steering.

    Counts calls running at once (`max_concurrent`) so tests can check that inference is serialised.
    """

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s
        self.calls = 0
        self.max_concurrent = 0
        self._running = 0
        self._lock = threading.Lock()

    @property
    def metadata(self) -> dict:
        return {"policy": "fake", "action_horizon": 10}

    def infer(self, observation: dict, steering) -> dict:
        with self._lock:
            self._running += 1
            self.calls += 1
            self.max_concurrent = max(self.max_concurrent, self._running)
        try:
            time.sleep(self.delay_s)
            return {"actions": fake_actions(observation, [steering_term(s) for s in steering]),
                    "policy_timing": {"infer_ms": 0.0}}
        finally:
            with self._lock:
                self._running -= 1


def steering_term(applied) -> tuple[torch.Tensor, float]:
    """The fake policy's (vector, factor) of one applied steering: an add entry's unit vector and `vector_alpha`;
    a clamp entry's negated unit vector and its target m₋ + α(m₊ − m₋) (unlike an add of the same number)."""
    if applied.mode == "clamp":
        start, end = applied.vector.levels
        return -applied.vector.vector, start + applied.alpha * (end - start)
    return applied.vector.vector, applied.vector_alpha


def fake_actions(observation: dict, steering: list[tuple[torch.Tensor, float]]) -> np.ndarray:
    """(10, 7) float32 depending on every input bit that matters: pixels, state, prompt, vectors and alphas."""
    base = np.float32(observation["observation/image"].astype(np.float64).mean() / 255)
    wrist = np.float32(observation["observation/wrist_image"].astype(np.float64).std() / 255)
    state = np.resize(observation["observation/state"].astype(np.float32), 7)
    shift = sum((alpha * vector[:7].numpy() for vector, alpha in steering), np.zeros(7, np.float32))
    steps = np.arange(10, dtype=np.float32)[:, None]
    return (base + wrist * steps + state + np.float32(len(observation["prompt"])) / 100 + shift).astype(np.float32)


@contextlib.contextmanager
def running(server: PolicyServer) -> Iterator[PolicyServer]:
    """Run `server` on a free loopback port in a background thread; stop it and wait on exit."""
    server.host, server.port = "127.0.0.1", 0
    with serving_in_thread(server):
        yield server


def run_openpi_client(
    tmp_path: Path, port: int, clients: list[list[dict]], timeout: float = 240, wrapper_steering=None,
    api_keys: list[str | None] | None = None,
) -> list[dict]:
    """Send each client's requests through the real openpi-client (one thread per client); return per client
    {"metadata", "results": [{"reply": ...} | {"error": "Type: message"}]}, or {"error", "status"} when it could
    not connect. With `wrapper_steering`, the clients are examples/libero_steered_client.py's class adding that
    entry; `api_keys` gives each client's api key. Requests: see openpi_client_script.py."""
    uv = os.environ.get("UV") or shutil.which("uv")
    assert uv, "uv not found: the openpi client runs in its own environment made by `uv run --isolated`"
    plan, out = tmp_path / "plan.msgpack", tmp_path / "out.msgpack"
    options = {"wrapper_steering": wrapper_steering, "api_keys": api_keys}
    plan.write_bytes(codec.pack({"host": "127.0.0.1", "port": port, "clients": clients,
                                 **{k: v for k, v in options.items() if v is not None}}))
    completed = subprocess.run(
        [uv, "run", "--isolated", "--no-project", *OPENPI_CLIENT, "python", str(CLIENT_SCRIPT), str(plan), str(out)],
        capture_output=True, text=True, timeout=timeout, cwd=tmp_path,
    )
    assert completed.returncode == 0, f"openpi client failed:\n{completed.stdout}\n{completed.stderr}"
    return codec.unpack(out.read_bytes())["clients"]


@contextlib.contextmanager
def fixed_threads() -> Iterator[None]:
    """Run the block with one torch intra-op thread, as a server started with FIXED_THREADS_ENV; restore after.

    (torch.set_num_threads also sets MKL's thread count and turns MKL_DYNAMIC off.)
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def server_env() -> dict[str, str]:
    """This process's environment with FIXED_THREADS_ENV: for a server subprocess whose actions are compared."""
    return {**os.environ, **FIXED_THREADS_ENV}


def assert_actions_match(got: np.ndarray, want: np.ndarray) -> None:
    """Actions computed in another process: equal shape and dtype, values within ACTION_ROUNDING_EPS float32
    eps of the largest |action| (float32 rounding of a different summation order; see its comment)."""
    assert got.shape == want.shape and got.dtype == want.dtype, (got.shape, got.dtype, want.shape, want.dtype)
    bound = ACTION_ROUNDING_EPS * float(np.finfo(np.float32).eps) * max(1.0, float(np.abs(want).max()))
    np.testing.assert_allclose(got, want, rtol=0, atol=bound)


def port_from_log(process: subprocess.Popen, timeout: float = 120) -> int:
    """Return the port of a server process from its "serving on ws://host:port" log line (stderr, INFO), then
    keep draining its stderr so the server never blocks on a full pipe."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = process.stderr.readline()
        match = re.search(r"serving on ws://[\d.]+:(\d+)", line)
        if match:
            threading.Thread(target=process.stderr.read, daemon=True).start()
            return int(match.group(1))
        assert line or process.poll() is None, "server exited before listening"
    raise AssertionError("server did not report its port")
