"""Real size: loading the pi0.5 prefix from a real-layout checkpoint, its peak memory, and its forward speed.

A random checkpoint with openpi's real layout and sizes (812 tensors, 3.6 B values, bfloat16 on disk, 7.2 GB)
is generated once, block by block (`steering_core.synthetic.pi05.write_pi05_checkpoint`), and cached. A fresh
process then loads `Pi05Prefix` through layer 12 on the CPU in float32 and reports the load time and its peak
resident memory (VmHWM) against the bytes of the parameters it loaded (target: at most 1.1x). It then times
`Pi05Prefix.residuals` on one LIBERO frame (two 224 px cameras, the third masked, a 16-token prompt) and, in
alternating rounds, `torch.nn.functional.linear` over exactly the matrix products of that forward with the
model's own weights: GFLOP/s of ours (analytic FLOPs, attention included) against GFLOP/s of linear().
It also times capture's call, `capture.selected_rows.selected_residuals` of the 14 instruction rows, whose deepest layer
runs queries, attention output and MLP for those rows only.

Opt-in (`bench.run_all --real-size`): it needs about 11 GB of free memory and 8 GB of disk, and is skipped,
with a note saying so, on a machine with less than 20 GiB of RAM.

    uv run python -m bench.real_size [--quick]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import torch

from bench.capture_throughput import (
    LIBERO_CAMERAS,
    REAL_PROMPT_TOKENS,
    _linear,
    ours_flops,
    ours_flops_selected_queries,
    seed_flops,
)
from bench.common import (
    Result,
    cache_dir,
    command,
    finish,
    parser,
    peak_rss_mib,
    print_child_result,
    rss_mib,
    run_child,
)

LAYER = 12  # the seed's SAE layer: the prefix is loaded through it
ROUNDS = 2  # alternating rounds of ours and linear(), best kept
MIN_RAM_GIB = 20.0  # below this the real-size section is skipped
TARGET = 1.1  # peak RSS / loaded parameter bytes, at most
QUICK_LAYER = 2


def memory_gib(field: str) -> float:
    """Return a /proc/meminfo field in GiB (0 when unknown)."""
    meminfo = Path("/proc/meminfo")
    if not meminfo.is_file():
        return 0.0
    for line in meminfo.read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024**2
    return 0.0


def products(model: Any, frames: int, prompt_tokens: int) -> list[tuple[int, torch.Tensor]]:
    """Return (rows, weight (out, in)) of every matrix product of `Pi05Prefix.residuals` on `frames` frames."""
    arch = model.arch
    vision_rows = frames * LIBERO_CAMERAS * arch.tokens_per_image
    lm_rows = frames * (LIBERO_CAMERAS * arch.tokens_per_image + prompt_tokens)
    vision = model.vision_model
    found = [(vision_rows, vision.embeddings.patch_embedding.weight.flatten(1))]
    for layer in vision.encoder.layers:
        attention, mlp = layer.self_attn, layer.mlp
        found += [(vision_rows, m.weight) for m in (attention.q_proj, attention.k_proj, attention.v_proj,
                                                     attention.out_proj, mlp.fc1, mlp.fc2)]
    found.append((vision_rows, model.multi_modal_projector.linear.weight))
    for layer in model.layers:
        attention, mlp = layer.self_attn, layer.mlp
        found += [(lm_rows, m.weight) for m in (attention.q_proj, attention.k_proj, attention.v_proj,
                                                 attention.o_proj, mlp.gate_proj, mlp.up_proj, mlp.down_proj)]
    return found


def child(checkpoint: Path, arch_json: str, layer: int) -> dict[str, Any]:
    """Load the prefix in this fresh process, then time ours and linear(); return the measurements."""
    from steering_core.capture.selected_rows import selected_residuals
    from steering_core.pi05 import Pi05Arch, Pi05Prefix

    arch = Pi05Arch.model_validate_json(arch_json)
    before = rss_mib()
    start = time.perf_counter()
    model = Pi05Prefix.from_checkpoint(checkpoint, arch, max_layer=layer, device="cpu", dtype="float32")
    load_seconds = time.perf_counter() - start
    load_peak = peak_rss_mib()
    loaded = sum(p.numel() * p.element_size() for p in model.parameters())

    generator = torch.Generator().manual_seed(0)
    side = arch.image_size
    images = [torch.rand(1, 3, side, side, generator=generator) * 2 - 1 for _ in range(3)]
    masks = [torch.ones(1, dtype=torch.bool), torch.ones(1, dtype=torch.bool), torch.zeros(1, dtype=torch.bool)]
    tokens = torch.randint(0, arch.vocab_size, (1, REAL_PROMPT_TOKENS), generator=generator)
    token_mask = torch.ones(1, REAL_PROMPT_TOKENS, dtype=torch.bool)
    matrices = products(model, 1, REAL_PROMPT_TOKENS)
    inputs = {(rows, w.shape[1]): torch.randn(rows, w.shape[1], generator=generator) for rows, w in matrices}

    language_start = arch.prefix_length(3, 0)
    instruction = torch.arange(1, REAL_PROMPT_TOKENS - 1)  # BOS and the closing "\n" are not instruction tokens
    frame_of_row, positions = torch.zeros(len(instruction), dtype=torch.long), language_start + instruction

    def ours() -> None:
        model.residuals(images, masks, tokens, token_mask, [layer])

    def selected() -> None:  # what capture calls: the instruction rows only
        selected_residuals(model, images, masks, tokens, token_mask, [layer], frame_of_row, positions)

    def linear() -> None:
        for rows, weight in matrices:
            torch.nn.functional.linear(inputs[(rows, weight.shape[1])], weight)

    times: dict[str, list[float]] = {"ours": [], "selected": [], "linear": []}
    with torch.no_grad():
        ours()  # warm-up: first-call costs of every kernel
        for _ in range(ROUNDS):
            for name, fn in (("ours", ours), ("selected", selected), ("linear", linear)):
                start = time.perf_counter()
                fn()
                times[name].append(time.perf_counter() - start)
    return {
        "rss_before_mib": before,
        "load_seconds": load_seconds,
        "load_peak_rss_mib": load_peak,
        "loaded_bytes": loaded,
        "ours_seconds": min(times["ours"]),
        "selected_seconds": min(times["selected"]),
        "selected_flops": ours_flops_selected_queries(arch, layer, REAL_PROMPT_TOKENS),
        "linear_seconds": min(times["linear"]),
        "ours_flops": ours_flops(arch, layer, REAL_PROMPT_TOKENS),
        "linear_flops": sum(_linear(rows, w.shape[1], w.shape[0]) for rows, w in matrices),
        "final_peak_rss_mib": peak_rss_mib(),
    }


def checkpoint_folder(args: argparse.Namespace) -> Path:
    """Return the cached real-layout bf16 checkpoint folder (tiny with --quick), shared with bench.policy_real_size."""
    return cache_dir(args) / ("pi05-tiny-bf16" if args.quick else "pi05-real-bf16")


def main(argv: list[str] | None = None) -> Result | None:
    """Run the real-size section (or, with --child, its measurement in this process); return the result."""
    from steering_core.pi05 import Pi05Arch
    from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint

    arguments = parser(__doc__.splitlines()[0])
    arguments.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    arguments.add_argument("--checkpoint", type=Path, help=argparse.SUPPRESS)
    arguments.add_argument("--arch-json", help=argparse.SUPPRESS)
    arguments.add_argument("--layer", type=int, help=argparse.SUPPRESS)
    args = arguments.parse_args(argv)
    if args.child:
        print_child_result(child(args.checkpoint, args.arch_json, args.layer))
        return None

    arch, layer = (tiny_arch(), QUICK_LAYER) if args.quick else (Pi05Arch(), LAYER)
    title = f"10. Real size: load and forward through layer {layer} (CPU)"
    ram = memory_gib("MemTotal")
    if not args.quick and ram < MIN_RAM_GIB:
        note = (f"skipped: this machine has {ram:.1f} GiB of RAM, the real-size section needs {MIN_RAM_GIB:.0f} GiB "
                "(the float32 prefix through layer 12 alone is 9.4 GB)")
        result = Result(name="real_size", title=title, command=command("real_size", args), measured="skipped",
                        baseline="skipped", ratio=float("nan"), target=f"<= {TARGET}x", met=False, table=[],
                        notes=[note])
        return finish(result, args)
    folder = checkpoint_folder(args)
    generated = 0.0
    if not (folder / "model.safetensors").is_file():
        start = time.perf_counter()
        write_pi05_checkpoint(folder, arch, dtype=torch.bfloat16, overwrite=True)
        generated = time.perf_counter() - start
    measured = run_child("real_size", [f"--cache-dir={folder.parent}", "--child", f"--checkpoint={folder}",
                                       f"--arch-json={arch.model_dump_json()}", f"--layer={layer}"])
    loaded_mib = measured["loaded_bytes"] / 2**20
    peak_ratio = measured["load_peak_rss_mib"] / loaded_mib
    working_ratio = (measured["load_peak_rss_mib"] - measured["rss_before_mib"]) / loaded_mib
    ours_rate = measured["ours_flops"] / measured["ours_seconds"] / 1e9
    linear_rate = measured["linear_flops"] / measured["linear_seconds"] / 1e9
    file_gb = (folder / "model.safetensors").stat().st_size / 1e9
    table = [
        {"measure": "load time s", "value": measured["load_seconds"]},
        {"measure": "loaded parameter MiB (float32)", "value": loaded_mib},
        {"measure": "RSS before load MiB (imports)", "value": measured["rss_before_mib"]},
        {"measure": "peak RSS after load MiB", "value": measured["load_peak_rss_mib"]},
        {"measure": "peak RSS / loaded bytes", "value": peak_ratio},
        {"measure": "(peak - before) / loaded bytes", "value": working_ratio},
        {"measure": "ours frames/s (1 frame)", "value": 1 / measured["ours_seconds"]},
        {"measure": "ours GFLOP/s (analytic, attention included)", "value": ours_rate},
        {"measure": "linear() GFLOP/s, same products", "value": linear_rate},
        {"measure": "ours / linear() GFLOP/s", "value": ours_rate / linear_rate},
        {"measure": "capture's call (selected rows) frames/s", "value": 1 / measured["selected_seconds"]},
        {"measure": "capture's call / every row, time", "value": measured["selected_seconds"] / measured["ours_seconds"]},
        {"measure": "capture's call / every row, analytic FLOPs",
         "value": measured["selected_flops"] / measured["ours_flops"]},
        {"measure": "seed's FLOPs / capture's call (analytic)", "value": seed_flops(arch, 1) / measured["selected_flops"]},
        {"measure": "peak RSS with the forward MiB", "value": measured["final_peak_rss_mib"]},
    ]
    result = Result(
        name="real_size",
        title=title,
        command=command("real_size", args),
        measured=f"peak RSS {measured['load_peak_rss_mib']:,.0f} MiB",
        baseline=f"loaded parameters {loaded_mib:,.0f} MiB",
        ratio=peak_ratio,
        target=f"<= {TARGET}x (peak RSS / loaded parameter bytes)",
        met=peak_ratio <= TARGET,
        table=table,
        checks={"peak_ratio": peak_ratio, "ours_vs_linear": ours_rate / linear_rate},
        notes=[
            f"checkpoint: {file_gb:.2f} GB bfloat16 on disk, openpi's layout"
            + (f", generated in {generated:.0f} s this run" if generated else ", generated by an earlier run")
            + f"; loaded through layer {layer} in float32 on the CPU in a fresh process.",
            f"forward: {ours_rate:.0f} GFLOP/s for {measured['ours_flops'] / 1e9:,.0f} GFLOP per frame; linear() "
            f"replays the same {measured['linear_flops'] / 1e9:,.0f} GFLOP of matrix products with the model's "
            f"weights; best of {ROUNDS} alternating rounds after a warm-up.",
        ],
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
