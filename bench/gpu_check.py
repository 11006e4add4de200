"""GPU check: pi0.5 speed on a CUDA device against its own matmul peak, and its outputs against float32 on the CPU.

One command on a GPU machine. A random pi0.5 checkpoint with the real layout and sizes (bfloat16 on disk,
7.2 GB; the one `bench.real_size` uses) is written once and cached; or `--checkpoint` names a real pi0.5 checkpoint
(see "A given checkpoint" below). Each section is its own function and measures against a baseline taken in the
same run:

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
- `render`: LIBERO's simulator steps/s with both 256 px cameras rendered every step, MuJoCo's EGL on the GPU against
  the software renderer (Mesa's llvmpipe), each in its own process, the same episode. It uses no CUDA: where
  NVIDIA's EGL is missing it measures the software side and says so in a note (`--sections render --quick` on
  the CPU).

The sections live in `bench.gpu_policy_sections` (capture, latency, sweep, precision, server),
`bench.gpu_matmul_sections` (peak, sae) and `bench.gpu_render_section` (render), on the harness of
`bench.gpu_harness` (sizes, tolerances, records, the run's context); this module runs them through `SECTIONS`.

Each section's peak memory is recorded (`torch.cuda.max_memory_allocated`, reset between sections; peak RSS
on the CPU). Every comparison has a tolerance; the command exits with status 1 when one is exceeded.
`--quick` runs tiny sizes on the CPU to prove the script (its numbers are not benchmarks).

A given checkpoint: `--checkpoint PATH` (a pi0.5 folder in openpi's converted PyTorch layout or lerobot's
PI05Policy layout, or its model.safetensors) with `--tokenizer PATH` (PaliGemma's SentencePiece model or
tokenizer.json; required with it), `--layout auto|openpi|lerobot` (default auto: detected from the folder; a forced
layout is checked against it) and `--arch-file PATH` (JSON of `Pi05Arch` fields, read by
`steering_core.pi05.arch.read_arch`; default the real pi0.5, or `tiny_arch()` under --quick). Then nothing is
generated for the policy sections: capture (our forward and the seed's, both read from it through its layout),
latency, sweep and server load that checkpoint, capturing and steering the language-model layer two thirds deep.
peak, sae and precision (its mid-size generated model, compared on the device against the CPU) keep their own
generated inputs. The result's notes and `checks.checkpoint` record the checkpoint, its layout, the tokenizer, the
dimensions and which sections used it; without --checkpoint the output is as before.

    uv run python -m bench.gpu_check [--quick] [--sections peak capture ...] [--json PATH]
        [--checkpoint PATH --tokenizer PATH [--layout auto|openpi|lerobot] [--arch-file PATH]]
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

from bench import serve_latency
from bench.common import Result, cache_dir, command, finish, machine, parser, peak_rss_mib
from bench.gpu_harness import Comparison, Context, Section
from bench.gpu_matmul_sections import peak, sae
from bench.gpu_policy_sections import capture, latency, precision, server, sweep
from bench.gpu_render_section import render
from steering_core.devices import resolve_device
from steering_core.pi05.layouts import LayoutName

SECTIONS: dict[str, Callable[[Context], Section]] = {
    "peak": peak, "capture": capture, "latency": latency, "sweep": sweep, "server": server, "precision": precision,
    "sae": sae, "render": render,
}
POLICY_SECTIONS = ("latency", "sweep", "server")  # share the loaded real-size policy
CHECKPOINT_SECTIONS = ("capture", *POLICY_SECTIONS)  # read the checkpoint: the generated one or --checkpoint


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


# ----------------------------------------------------------------------------- a given checkpoint


def given_context(args: argparse.Namespace, selected: list[str]) -> Context:
    """Return the run's context; with --checkpoint, refuse (one line, SystemExit) a checkpoint, tokenizer or arch
    file that cannot be read, or a section that cannot run on the checkpoint."""
    if args.checkpoint is None:
        return Context(args)
    try:
        ctx = Context(args)
    except (OSError, ValueError) as err:
        raise SystemExit(f"bench.gpu_check: --checkpoint {args.checkpoint}: {err}") from None
    if not ctx.tokenizer.exists():
        raise SystemExit(f"bench.gpu_check: --tokenizer {ctx.tokenizer}: not found; pass PaliGemma's SentencePiece "
                         "model or its tokenizer.json")
    if "server" in selected and ctx.sizes.arch.depth <= serve_latency.LAYER:
        raise SystemExit(f"bench.gpu_check: the server section steers language-model layer {serve_latency.LAYER}, "
                         f"but the checkpoint's model has {ctx.sizes.arch.depth} layer(s): leave server out")
    return ctx


def checkpoint_record(args: argparse.Namespace, ctx: Context, selected: list[str]) -> tuple[dict[str, Any], str]:
    """Return (`checks.checkpoint`, the note) of a run with --checkpoint: the checkpoint, its layout, the tokenizer,
    the dimensions and which sections read it."""
    assert ctx.given is not None
    used = [name for name in selected if name in CHECKPOINT_SECTIONS]
    generated = [name for name in selected if name not in CHECKPOINT_SECTIONS]
    record = {"path": str(args.checkpoint), "model_file": str(ctx.given.model_file),
              "layout": ctx.given.layout.name.value, "layout_option": args.layout, "tokenizer": str(ctx.tokenizer),
              "arch_file": None if args.arch_file is None else str(args.arch_file),
              "arch": ctx.sizes.arch.model_dump(), "layer": ctx.sizes.layer, "sections": used,
              "generated_input_sections": generated}
    arch = f"--arch-file {args.arch_file}" if args.arch_file is not None else (
        "the quick tiny sizes" if args.quick else "the real pi0.5 sizes")
    note = (f"checkpoint: {ctx.given.describe}, given with --checkpoint (layout {args.layout}), tokenizer "
            f"{ctx.tokenizer}, dimensions from {arch}, layer {ctx.sizes.layer}; read by "
            + (", ".join(used) or "no selected section")
            + ("; own generated inputs (not the checkpoint) in " + ", ".join(generated) if generated else "")
            + ".")
    return record, note


# ----------------------------------------------------------------------------- check


def run(args: argparse.Namespace) -> Result:
    """Run the selected sections in order; return the result (met = every comparison within tolerance)."""
    selected = [name for name in SECTIONS if name in args.sections]
    ctx = given_context(args, selected)
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
    given: dict[str, Any] = {}
    if ctx.given is not None:
        record, note = checkpoint_record(args, ctx, selected)
        given, notes = {"checkpoint": record}, [note, *notes]
    return Result(
        name="gpu_check",
        title=f"GPU check on {info['gpu'] if ctx.device.type == 'cuda' else 'the CPU'}"
        + (" (quick: tiny sizes, not a benchmark)" if args.quick else ""),
        command=command("gpu_check", args, *(["--sections", *selected] if selected != list(SECTIONS) else []),
                        *checkpoint_flags(args)),
        measured=f"{passed} comparisons within tolerance",
        baseline=f"{len(comparisons)} made",
        ratio=passed / len(comparisons) if comparisons else 1.0,
        target="every comparison within its tolerance",
        met=not failed,
        table=table,
        notes=[f"device {ctx.device}, policy dtype {str(ctx.dtype).removeprefix('torch.')}", *notes,
               *(f"FAILED: {case}" for case in failed)],
        checks={"passed": not failed, "failed": failed, "sections": sections, "figures": figures, "machine": info,
                **given},
    )


def checkpoint_flags(args: argparse.Namespace) -> list[str]:
    """Return the --checkpoint flags that reproduce the run (none without --checkpoint)."""
    if args.checkpoint is None:
        return []
    flags = ["--checkpoint", str(args.checkpoint), "--tokenizer", str(args.tokenizer)]
    flags += ["--layout", args.layout] if args.layout != LayoutName.AUTO.value else []
    return flags + (["--arch-file", str(args.arch_file)] if args.arch_file is not None else [])


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
    arguments.add_argument("--checkpoint", type=Path, default=None,
                           help="a pi0.5 checkpoint folder (openpi's converted PyTorch layout or lerobot's "
                           "PI05Policy layout) or its model.safetensors, read by the sections that load the policy "
                           "or the checkpoint (" + ", ".join(CHECKPOINT_SECTIONS) + "); default: a random "
                           "checkpoint generated into the cache. peak, sae and precision (a mid-size generated "
                           "model) use their own generated inputs either way")
    arguments.add_argument("--tokenizer", type=Path, default=None,
                           help="PaliGemma's SentencePiece model or tokenizer.json; required with --checkpoint")
    arguments.add_argument("--layout", choices=[layout.value for layout in LayoutName], default=LayoutName.AUTO.value,
                           help="the --checkpoint's layout: auto (default, detected from the folder), openpi or "
                           "lerobot (then checked against the folder)")
    arguments.add_argument("--arch-file", type=Path, default=None,
                           help="JSON of Pi05Arch fields: the --checkpoint's dimensions (default the real pi0.5, or "
                           "the tiny quick sizes with --quick)")
    args = arguments.parse_args(argv)
    if args.checkpoint is None:
        extra = [flag for flag, given in (("--tokenizer", args.tokenizer is not None),
                                          ("--layout", args.layout != LayoutName.AUTO.value),
                                          ("--arch-file", args.arch_file is not None)) if given]
        if extra:
            arguments.error(f"{' and '.join(extra)} describe a --checkpoint; pass --checkpoint too")
    elif args.tokenizer is None:
        arguments.error("--checkpoint needs --tokenizer (PaliGemma's SentencePiece model or tokenizer.json)")
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
