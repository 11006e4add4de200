"""Policy latency: `sample_actions` at batch 1 and 4, eager against the compiled denoising step.

One LIBERO-shaped frame per row (two cameras, the masked third skipped, a 16-token prompt in 200 slots), 10
denoising steps, the same noise on both sides, on the mid-size pi0.5 of the capture benchmark. The compiled
policy shares the eager one's weights and runs its Euler step through `torch.compile` (`Pi05Policy(...,
compiled=True)`, steering_core.pi05.denoise); its first call per batch size compiles that step, timed as the
warm-up a server pays at start-up. Then each side runs its timed calls, compiled first, and the medians
are compared; the two sides' actions must agree to float32 rounding. On a CPU the denoising loop is a small
part of a call (SigLIP and the prefix dominate, and kernel launches are cheap), so compilation gains little there;
the GPU target, at most 40 ms per batch-1 call on an H100/H200, is measured by the GPU check through
`measure_latency`.

    uv run python -m bench.policy_latency [--device cuda] [--quick]
"""

from __future__ import annotations

from typing import Any

import torch

from bench.capture_throughput import ARCH, REAL_PROMPT_TOKENS
from bench.common import Result, cache_dir, command, finish, median, parser, timed
from bench.policy_sweep import build_checkpoint, frame
from steering_core.devices import resolve_device
from steering_core.pi05 import Pi05Policy
from steering_core.synthetic.pi05 import tiny_arch

# ----------------------------------------------------------------------------- settings

BATCHES = (1, 4)
STEPS = 10
REPEATS = 5  # timed calls per side and batch size, after the warm-up
GPU_TARGET_MS = 40.0  # batch 1 on an H100/H200 (openpi's compiled pi0.5: 22-57 ms on an RTX 4090 / L40S)

QUICK = {"arch": tiny_arch(), "batches": (1,), "repeats": 2}


def frames(arch: Any, batch: int) -> tuple[list, list, torch.Tensor, torch.Tensor]:
    """Return `batch` copies of the LIBERO-shaped frame of bench.policy_sweep."""
    images, masks, tokens, token_mask = frame(arch, REAL_PROMPT_TOKENS)
    return ([image.repeat(batch, 1, 1, 1) for image in images], [mask.repeat(batch) for mask in masks],
            tokens.repeat(batch, 1), token_mask.repeat(batch, 1))


def measure_latency(policy: Pi05Policy, batch: int, repeats: int = REPEATS) -> dict[str, Any]:
    """Return {"warm_up_s", "median_ms", "times_ms", "actions"} of `policy.sample_actions` on `batch` frames.

    The first call (the compilation of a compiled policy's step at this batch size) is timed apart as the
    warm-up; then `repeats` calls, synchronised on CUDA. The noise is fixed, so every call gives the same actions.
    """
    inputs = frames(policy.arch, batch)
    noise = torch.randn(batch, policy.action_horizon, policy.action_dim, generator=torch.Generator().manual_seed(2))

    def call() -> torch.Tensor:
        return policy.sample_actions(*inputs, noise=noise, num_steps=STEPS)

    actions, warm_up = timed(call, policy.device)
    times = [timed(call, policy.device)[1] * 1000.0 for _ in range(repeats)]
    return {"warm_up_s": warm_up, "median_ms": median(times), "times_ms": times, "actions": actions}


# ----------------------------------------------------------------------------- benchmark


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)
    arch, batches, repeats = (QUICK["arch"], QUICK["batches"], QUICK["repeats"]) if args.quick else (ARCH, BATCHES,
                                                                                                        REPEATS)
    checkpoint = build_checkpoint(cache_dir(args) / "policy-sweep", arch)
    eager = Pi05Policy.from_checkpoint(checkpoint, arch, device=device, compiled=False)
    compiled = Pi05Policy(eager.prefix, eager.expert, eager.action_horizon, None, eager.normalization, compiled=True)
    table, difference = [], 0.0
    for batch in batches:
        ours, baseline = measure_latency(compiled, batch, repeats), measure_latency(eager, batch, repeats)
        difference = max(difference, float((ours["actions"] - baseline["actions"]).abs().max()))
        table.append({"batch": batch, "eager ms": baseline["median_ms"], "eager min ms": min(baseline["times_ms"]),
                      "compiled ms": ours["median_ms"], "compiled min ms": min(ours["times_ms"]),
                      "ratio": ours["median_ms"] / baseline["median_ms"], "warm-up s (compile)": ours["warm_up_s"],
                      "eager first call s": baseline["warm_up_s"]})
    first = table[0]
    ratio = first["ratio"]
    on_gpu = device.type == "cuda"
    notes = [
        f"compiled vs eager actions: max |Δ| {difference:.2e} (float32 rounding: inductor fuses and reorders)",
        f"model: LM width {arch.width}, {arch.depth} layers; SigLIP width {arch.vision_width}, {arch.vision_depth} "
        f"layers; expert width {eager.expert_arch.width}; {STEPS} denoising steps; median and min of {repeats} calls",
        f"GPU target: <= {GPU_TARGET_MS:.0f} ms per batch-1 call on an H100/H200 at real size, measured by the GPU "
        "check (bench.policy_latency.measure_latency)",
    ]
    result = Result(
        name="policy_latency",
        title="17. Policy latency (sample_actions, compiled denoising step)",
        command=command("policy_latency", args),
        measured=f"{first['compiled ms']:.1f} ms compiled (batch {first['batch']})",
        baseline=f"{first['eager ms']:.1f} ms eager",
        ratio=ratio,
        target=f"<= {GPU_TARGET_MS:.0f} ms at batch 1" if on_gpu else "<= 1.0x on the CPU (GPU target: GPU check)",
        met=first["compiled ms"] <= GPU_TARGET_MS if on_gpu else ratio <= 1.0,
        table=table,
        notes=notes,
        checks={"max_abs_difference": difference, "batches": list(batches)},
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
