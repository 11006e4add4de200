"""GPU check: pi0.5 speed on a CUDA device against its own matmul peak, and its outputs against float32 on the CPU.

One command on a GPU machine. A random pi0.5 checkpoint with the real layout and sizes (bfloat16 on disk,
7.2 GB; the one `bench.real_size` uses) is written once and cached. Each section is its own function and
measures against a baseline taken in the same run:

- `peak`: the practical peak, a bf16 8192^3 matmul on CUDA (a float32 one on the CPU).
- `capture`: frames/s and MFU of capture's forward (`selected_residuals`, layer 12, batch 32 and 128) against
  the seed's way (`bench.seed_pi05`: a whole `sample_actions` with a hook), the same rows compared.
- `latency`: `sample_actions` time against batch size, and the GPU kernel time of the batch-1 call against its
  wall time (torch.profiler; n/a on the CPU).
- `sweep`: `sample_actions_sweep` of 8 steerings against 8 separate `sample_actions` calls, outputs compared.
- `precision`: float32 and bfloat16 on the device against float32 on the CPU at the mid-size model of
  `bench.capture_throughput` (the real size in float32 is 12.8 GB and slow on a CPU): unsteered actions,
  LM- and expert-steered actions, each steering's effect, an SAE splice, decision rows.
- `sae`: SAE encode + decode (standard, TopK) against torch.matmul of the same shapes, and one SAE training
  step (SAELens, else a plain torch TopK step) against its five-product matmul bound.
- `server`: a steered request with a CPU vector over loopback to the policy server with the policy on the
  device (openpi's client when installed, else the project's codec of its msgpack-numpy format), against a
  direct `infer` of the same observation.

The sections live in `bench.gpu_policy_sections` (capture, latency, sweep, precision, server) and
`bench.gpu_matmul_sections` (peak, sae), on the harness of `bench.gpu_harness` (sizes, tolerances, records, the
run's context); this module runs them through `SECTIONS`.

Each section's peak memory is recorded (`torch.cuda.max_memory_allocated`, reset between sections; peak RSS
on the CPU). Every comparison has a tolerance; the command exits with status 1 when one is exceeded.
`--quick` runs tiny sizes on the CPU to prove the script (its numbers are not benchmarks).

    uv run python -m bench.gpu_check [--quick] [--sections peak capture ...] [--json PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from bench.common import Result, cache_dir, command, finish, machine, parser, peak_rss_mib
from bench.gpu_harness import Comparison, Context, Section
from bench.gpu_matmul_sections import peak, sae
from bench.gpu_policy_sections import capture, latency, precision, server, sweep
from steering_core.devices import resolve_device

SECTIONS: dict[str, Callable[[Context], Section]] = {
    "peak": peak, "capture": capture, "latency": latency, "sweep": sweep, "server": server, "precision": precision,
    "sae": sae,
}
POLICY_SECTIONS = ("latency", "sweep", "server")  # share the loaded real-size policy
CHECKPOINT_SECTIONS = ("capture", *POLICY_SECTIONS)


# ----------------------------------------------------------------------------- memory


def reset_peak_memory(device: torch.device) -> None:
    """Start a section's peak memory: CUDA's peak allocation, or the process's peak RSS (Linux clear_refs)."""
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
        return
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS


def peak_memory(device: torch.device) -> dict[str, Any]:
    """Return the section's peak memory in MiB and what was measured."""
    if device.type == "cuda":
        return {"kind": "torch.cuda.max_memory_allocated", "mib": torch.cuda.max_memory_allocated(device) / 2**20}
    try:
        return {"kind": "peak RSS (VmHWM, whole process)", "mib": peak_rss_mib()}
    except (OSError, RuntimeError):
        return {"kind": "n/a", "mib": None}


# ----------------------------------------------------------------------------- check


def run(args: argparse.Namespace) -> Result:
    """Run the selected sections in order; return the result (met = every comparison within tolerance)."""
    ctx = Context(args)
    selected = [name for name in SECTIONS if name in args.sections]
    if any(name in CHECKPOINT_SECTIONS for name in selected):
        ctx.write_checkpoint()
    table: list[dict[str, Any]] = []
    sections: dict[str, Any] = {}
    figures: dict[str, Any] = {}
    notes: list[str] = []
    comparisons: list[Comparison] = []
    for index, name in enumerate(selected):
        reset_peak_memory(ctx.device)
        start = time.perf_counter()
        section = SECTIONS[name](ctx)
        seconds = time.perf_counter() - start
        memory = peak_memory(ctx.device)
        if not any(later in POLICY_SECTIONS for later in selected[index + 1 :]):
            ctx.release_policy()
        table += [{"section": name, **row, "tolerance": "", "pass": ""} for row in section.measures]
        table += [{"section": name, "measure": f"{c.case} ({c.metric})", "value": c.error, "against": "",
                   "ratio": "", "tolerance": c.tolerance, "pass": c.passed} for c in section.comparisons]
        mib = "n/a" if memory["mib"] is None else f"{memory['mib']:,.0f}"
        table.append({"section": name, "measure": f"peak memory MiB ({memory['kind']})", "value": mib, "against": "",
                      "ratio": "", "tolerance": "", "pass": ""})
        sections[name] = {"seconds": seconds, "peak_memory": memory, "measures": section.measures,
                          "comparisons": [c.to_json() for c in section.comparisons]}
        comparisons += section.comparisons
        notes += section.notes
        figures |= section.figures
    passed = sum(c.passed for c in comparisons)
    failed = [c.case + f" ({c.metric})" for c in comparisons if not c.passed]
    info = machine()
    return Result(
        name="gpu_check",
        title=f"GPU check on {info['gpu'] if ctx.device.type == 'cuda' else 'the CPU'}"
        + (" (quick: tiny sizes, not a benchmark)" if args.quick else ""),
        command=command("gpu_check", args, *(["--sections", *selected] if selected != list(SECTIONS) else [])),
        measured=f"{passed} comparisons within tolerance",
        baseline=f"{len(comparisons)} made",
        ratio=passed / len(comparisons) if comparisons else 1.0,
        target="every comparison within its tolerance",
        met=not failed,
        table=table,
        notes=[f"device {ctx.device}, policy dtype {str(ctx.dtype).removeprefix('torch.')}", *notes,
               *(f"FAILED: {case}" for case in failed)],
        checks={"passed": not failed, "failed": failed, "sections": sections, "figures": figures, "machine": info},
    )


def read_figures(path: Path, *names: str) -> dict[str, Any]:
    """Return the named figures (`checks.figures`) of a GPU check JSON; one ValueError names any that is missing."""
    try:
        figures = json.loads(path.read_text(encoding="utf-8"))["checks"]["figures"]
        return {name: figures[name] for name in names}
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: no figures {list(names)} under checks.figures ({type(err).__name__}: {err}); "
                         "expected the JSON `python -m bench.gpu_check` writes") from None


def main(argv: list[str] | None = None) -> Result:
    """Run the check, print and write its result; exit with status 1 when a comparison exceeds its tolerance."""
    arguments = parser(__doc__.splitlines()[0])
    arguments.set_defaults(device="cuda" if torch.cuda.is_available() else "cpu")
    arguments.add_argument("--sections", nargs="+", choices=list(SECTIONS), default=list(SECTIONS),
                           help="sections to run (default all), in the order " + ", ".join(SECTIONS))
    args = arguments.parse_args(argv)
    if args.json is None:
        args.json = cache_dir(args) / "gpu_check.json"
    if resolve_device(args.device).type != "cuda" and not args.quick:
        raise SystemExit("bench.gpu_check: the real sizes need a CUDA device; on the CPU run it with --quick")
    result = finish(run(args), args)
    print(f"JSON: {args.json}")
    if not result.met:
        raise SystemExit(1)
    return result


if __name__ == "__main__":
    main()
