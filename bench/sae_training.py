"""SAE training: rows/s of `train_sae` (SAELens's trainer fed by our shard stream) against the matmul bound.

Ours is `steering_core.sae.training.trainer.train_sae`: a TopK SAE trained by SAELens's SAETrainer on rows
streamed by `RowSource.shuffled` from a generated capture run (float32 shards). A TopK step's work is dominated by
five products of the same size: the forward pass's x @ W_enc and f @ W_dec, and the backward pass's gradients
of W_dec (fᵀ @ g), of f (g @ W_decᵀ) and of W_enc (xᵀ @ g_pre). The bound is torch.matmul of exactly those five
shapes into preallocated buffers, timed between our training steps (same process, same load). The loader alone
(`RowSource.shuffled`, the same stream, no training) is timed on the same run in the same process.

    uv run python -m bench.sae_training [--device cuda] [--quick]
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch

from bench.common import Result, cache_dir, command, finish, median, parser, synchronize, timed
from steering_core.devices import resolve_device

# ----------------------------------------------------------------------------- settings

D_IN, D_SAE, K = 2048, 16384, 64  # Gemma-2B width, the borrowed SAE's 16384 latents, TopK default k
BATCH_SIZE = 2048  # rows per step (TrainSettings: 4096; half keeps the section within a few minutes on 2 cores)
STEPS = 5  # timed steps; the first is left out as warm-up
RUN_ROWS = 8192  # rows in the generated run (64 MiB float32); epochs repeat
LOADER_BATCHES = 64
TARGET_MATMUL = 0.6  # ours rows/s / matmul-bound rows/s (issue 24)
TARGET_LOADER = 5.0  # loader rows/s / ours rows/s

QUICK = {"d_in": 64, "d_sae": 256, "k": 8, "batch_size": 256, "steps": 40, "run_rows": 4096}


def build_run(folder: Path, d_in: int, rows: int) -> Path:
    """Return a capture run of `rows` random rows of width d_in in 8 shards, written unless cached."""
    from steering_core.synthetic.residual_run import write_rows_run

    run = folder / f"run-{rows}x{d_in}"
    if not (run / "metadata.json").is_file():
        write_rows_run(run, torch.randn(rows, d_in, generator=torch.Generator().manual_seed(0)), episodes=8)
    return run


def matmul_bound(batch: int, d_in: int, d_sae: int, device: torch.device):
    """Return a call doing a TopK step's five products of these shapes into preallocated buffers."""
    x, g_out = (torch.randn(batch, d_in, device=device) for _ in range(2))
    f, g_pre = (torch.randn(batch, d_sae, device=device) for _ in range(2))
    w_enc, w_dec = torch.randn(d_in, d_sae, device=device), torch.randn(d_sae, d_in, device=device)
    pre, out, grad_dec, grad_f, grad_enc = (torch.empty(*shape, device=device) for shape in (
        (batch, d_sae), (batch, d_in), (d_sae, d_in), (batch, d_sae), (d_in, d_sae)))

    def call() -> None:
        torch.matmul(x, w_enc, out=pre)
        torch.matmul(f, w_dec, out=out)
        torch.matmul(f.T, g_out, out=grad_dec)
        torch.matmul(g_out, w_dec.T, out=grad_f)
        torch.matmul(x.T, g_pre, out=grad_enc)

    return call


def measure(folder: Path, sizes: dict[str, int], device: torch.device) -> dict[str, Any]:
    """Train with the bound timed between steps; time the loader alone; return seconds per batch of each."""
    from steering_core.sae.training.rows import RowSource
    from steering_core.sae.training.settings import TrainSettings
    from steering_core.sae.training.trainer import train_sae

    batch, steps = sizes["batch_size"], sizes["steps"]
    source = RowSource(build_run(folder, sizes["d_in"], sizes["run_rows"]), 3)
    stream = source.shuffled(batch, seed=0, buffer_rows=262_144)
    next(stream)
    start = time.perf_counter()
    for _ in range(LOADER_BATCHES):
        next(stream)
    loader_seconds = (time.perf_counter() - start) / LOADER_BATCHES

    bound = matmul_bound(batch, sizes["d_in"], sizes["d_sae"], device)
    step_times: list[float] = []
    bound_times: list[float] = []
    resumed = [0.0]

    def progress(done: int, total: int) -> None:
        synchronize(device)
        if resumed[0]:
            step_times.append(time.perf_counter() - resumed[0])
        if done < total:
            bound_times.append(timed(bound, device)[1])
        resumed[0] = time.perf_counter()

    settings = TrainSettings(d_sae=sizes["d_sae"], k=sizes["k"], batch_size=batch, training_rows=batch * (steps + 1),
                             checkpoints=0, norm_estimate_batches=2, device=str(device))
    out = folder / f"sae-{time.time_ns()}"  # a new folder: a finished one would be returned at once
    start = time.perf_counter()
    train_sae(source, out, settings, layer=3, progress=progress)
    return {"step_seconds": median(step_times[1:]), "bound_seconds": median(bound_times[1:]),
            "loader_seconds": loader_seconds, "total_seconds": time.perf_counter() - start, "steps": len(step_times)}


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark and return its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)
    sizes = {"d_in": D_IN, "d_sae": D_SAE, "k": K, "batch_size": BATCH_SIZE, "steps": STEPS, "run_rows": RUN_ROWS}
    if args.quick:
        sizes = QUICK
    torch.manual_seed(0)
    found = measure(cache_dir(args) / "sae_training", sizes, device)
    batch, d_in, d_sae = sizes["batch_size"], sizes["d_in"], sizes["d_sae"]
    ours, bound, loader = (batch / found[key] for key in ("step_seconds", "bound_seconds", "loader_seconds"))
    flops = 5 * 2 * batch * d_in * d_sae  # five products, 2 FLOPs per multiply-add
    ratio = ours / bound
    table = [
        {"method": "ours: train_sae step (SAELens TopK, loader included)", "rows/s": ours,
         "GFLOP/s": flops / found["step_seconds"] / 1e9, "of bound": ratio, "ms/step": found["step_seconds"] * 1e3},
        {"method": "torch.matmul, the step's five products", "rows/s": bound,
         "GFLOP/s": flops / found["bound_seconds"] / 1e9, "of bound": 1.0, "ms/step": found["bound_seconds"] * 1e3},
        {"method": "RowSource.shuffled alone (the same stream)", "rows/s": loader, "GFLOP/s": "",
         "of bound": "", "ms/step": found["loader_seconds"] * 1e3},
    ]
    result = Result(
        name="sae_training",
        title=f"13. SAE training (TopK, d_in {d_in}, d_sae {d_sae}, k {sizes['k']}, batch {batch})",
        command=command("sae_training", args),
        measured=f"{ours:,.0f} rows/s; loader {loader / ours:.0f}x that",
        baseline=f"matmul bound {bound:,.0f} rows/s",
        ratio=ratio,
        target=f">= {TARGET_MATMUL}x of the bound, loader >= {TARGET_LOADER:.0f}x ours",
        met=ratio >= TARGET_MATMUL and loader >= TARGET_LOADER * ours,
        table=table,
        checks={"loader_over_ours": loader / ours},
        notes=[
            f"{found['steps']} steps of {batch} rows on {device.type}, float32, the first left out as warm-up; medians. "
            f"A step is the time between two calls of `train_sae`'s progress callback (the next batch's loading "
            f"included), less the bound's own time, which runs inside the callback. The whole training, bound "
            f"included, took {found['total_seconds']:.1f} s.",
            f"the bound counts {flops / 1e9:.3g} GFLOP per step; the TopK selection, the auxiliary loss of dead "
            "latents, Adam's update and gradient clipping are the rest of a step.",
            f"the loader reads {sizes['run_rows']} rows of 8 float32 shards (page cache warm) through a shuffle "
            f"buffer holding the whole run: {loader:,.0f} rows/s, {loader / ours:.0f}x what training consumes.",
        ],
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
