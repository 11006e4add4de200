"""Steering α sweep: `Pi05Policy.sample_actions_sweep` against one `sample_actions` call per α.

Eight α values of one language-model steering vector at layer 12 on one LIBERO-shaped frame (two cameras,
the masked third skipped, a 16-token prompt in 200 slots), 10 denoising steps each, the same noise. The
baseline calls `sample_actions` once per α: SigLIP, all 18 layers and the expert loop eight times. The sweep
runs SigLIP and layers 0..12 once (steering layer 12's output leaves its own keys and values unchanged),
then layers 13..17 and the expert loop for the eight α values as one batch. Both use the mid-size pi0.5 of
the capture benchmark; rounds alternate the two sides and each side's best round is kept. Their actions are
compared (they must agree to float32 rounding).

Next to the measured ratio: the analytic FLOP ratio (matrix products only) of the same sweep at the real
pi0.5 size, at layer 12 and for an expert-stream sweep (whole prefix shared).

    uv run python -m bench.policy_sweep [--device cuda] [--quick]
"""

from __future__ import annotations

from pathlib import Path

import torch

from bench.capture_throughput import (
    ARCH,
    LIBERO_CAMERAS,
    REAL_PROMPT_TOKENS,
    decoder_layer_flops,
    expert_step_flops,
    siglip_flops,
)
from bench.common import Result, cache_dir, command, finish, parser, timed
from steering_core.devices import resolve_device
from steering_core.pi05 import Pi05Arch, Pi05Policy, Steering
from steering_core.synthetic.pi05 import tiny_arch

# ----------------------------------------------------------------------------- settings

ALPHAS = (-8.0, -4.0, -2.0, -1.0, 1.0, 2.0, 4.0, 8.0)
LAYER = 12  # the seed's SAE layer
PROMPT_TOKENS = REAL_PROMPT_TOKENS  # valid tokens of the frame's prompt
TOKEN_SLOTS = 200  # pi0.5's max_token_len
STEPS = 10
ROUNDS = 2
TARGET = 0.5  # sweep time / separate calls' time

QUICK = {"arch": tiny_arch(), "layer": 1, "rounds": 1}
REAL_ARCH = Pi05Arch()


# ----------------------------------------------------------------------------- analytic FLOPs


def separate_flops(arch: Pi05Arch, alphas: int, prompt_tokens: int) -> float:
    """Return the FLOPs of `alphas` sample_actions calls on one frame (the policy's exact savings included)."""
    tokens = LIBERO_CAMERAS * arch.tokens_per_image + prompt_tokens
    prefix = siglip_flops(arch, LIBERO_CAMERAS) + arch.depth * decoder_layer_flops(arch, tokens, tokens)
    return alphas * (prefix + STEPS * expert_step_flops(arch, tokens))


def sweep_flops(arch: Pi05Arch, alphas: int, prompt_tokens: int, layer: int | None) -> float:
    """Return the FLOPs of one sweep over `alphas` entries steering LM layer `layer` (None: expert only)."""
    tokens = LIBERO_CAMERAS * arch.tokens_per_image + prompt_tokens
    shared_layers = arch.depth if layer is None else layer + 1
    shared = siglip_flops(arch, LIBERO_CAMERAS) + shared_layers * decoder_layer_flops(arch, tokens, tokens)
    per_entry = (arch.depth - shared_layers) * decoder_layer_flops(arch, tokens, tokens)
    return shared + alphas * (per_entry + STEPS * expert_step_flops(arch, tokens))


# ----------------------------------------------------------------------------- inputs


def frame(arch: Pi05Arch, prompt_tokens: int, batch: int = 1) -> tuple[list, list, torch.Tensor, torch.Tensor]:
    """Return `batch` LIBERO-shaped frames on the CPU: two random cameras, the masked third, a prompt in 200 slots."""
    generator = torch.Generator().manual_seed(0)
    side = arch.image_size
    images = [torch.rand(batch, 3, side, side, generator=generator) * 2 - 1 for _ in range(2)]
    images.append(-torch.ones(batch, 3, side, side))
    masks = [torch.ones(batch, dtype=torch.bool), torch.ones(batch, dtype=torch.bool), torch.zeros(batch, dtype=torch.bool)]
    tokens = torch.zeros(batch, TOKEN_SLOTS, dtype=torch.long)
    tokens[:, :prompt_tokens] = torch.randint(3, arch.vocab_size, (batch, prompt_tokens), generator=generator)
    token_mask = torch.zeros(batch, TOKEN_SLOTS, dtype=torch.bool)
    token_mask[:, :prompt_tokens] = True
    return images, masks, tokens, token_mask


def build_checkpoint(folder: Path, arch: Pi05Arch) -> Path:
    """Return a random checkpoint of `arch` (with its expert), writing it unless cached."""
    from steering_core.synthetic.pi05 import write_pi05_checkpoint

    checkpoint = folder / f"checkpoint-{arch.fingerprint()[:12]}"
    if not checkpoint.is_dir():
        write_pi05_checkpoint(checkpoint, arch)
    return checkpoint


# ----------------------------------------------------------------------------- benchmark


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)
    arch, layer, rounds = (QUICK["arch"], QUICK["layer"], QUICK["rounds"]) if args.quick else (ARCH, LAYER, ROUNDS)
    checkpoint = build_checkpoint(cache_dir(args) / "policy-sweep", arch)
    policy = Pi05Policy.from_checkpoint(checkpoint, arch, device=device)
    inputs = frame(arch, PROMPT_TOKENS)
    vector = torch.randn(arch.width, generator=torch.Generator().manual_seed(1))
    vector = vector / vector.norm() * 10.0
    entries = [Steering(layer, vector, alpha) for alpha in ALPHAS]
    noise = torch.randn(1, policy.action_horizon, policy.action_dim, generator=torch.Generator().manual_seed(2))

    def sweep() -> torch.Tensor:
        return policy.sample_actions_sweep(*inputs, entries, noise=noise, num_steps=STEPS)

    def separate() -> torch.Tensor:
        return torch.stack([policy.sample_actions(*inputs, noise=noise, num_steps=STEPS, steering=e) for e in entries])

    sweep()  # warm-up (allocator, kernels)
    sweep_times, separate_times = [], []
    for _ in range(rounds):
        swept, seconds = timed(sweep, device)
        sweep_times.append(seconds)
        one_by_one, seconds = timed(separate, device)
        separate_times.append(seconds)
    difference = float((swept - one_by_one).abs().max())
    spread = float((one_by_one - one_by_one[0]).abs().max())  # the α values really act differently
    ours, baseline = min(sweep_times), min(separate_times)
    ratio = ours / baseline
    n = len(ALPHAS)
    real_lm = sweep_flops(REAL_ARCH, n, REAL_PROMPT_TOKENS, LAYER) / separate_flops(REAL_ARCH, n, REAL_PROMPT_TOKENS)
    real_expert = sweep_flops(REAL_ARCH, n, REAL_PROMPT_TOKENS, None) / separate_flops(REAL_ARCH, n, REAL_PROMPT_TOKENS)
    measured_flops = sweep_flops(arch, n, PROMPT_TOKENS, layer) / separate_flops(arch, n, PROMPT_TOKENS)
    table = [
        {"case": f"measured {device.type}, lm layer {layer}, {n} alphas", "sweep s": ours,
         "separate s": baseline, "ratio": ratio, "FLOP ratio": measured_flops},
        {"case": f"real pi0.5, lm layer {LAYER} (analytic)", "FLOP ratio": real_lm},
        {"case": "real pi0.5, expert stream (analytic)", "FLOP ratio": real_expert},
    ]
    notes = [
        f"sweep vs separate calls: max |Δ action| {difference:.2e} (float32 rounding of a batch of {n} vs 1); "
        f"the α values differ from each other by up to {spread:.3f}",
        f"mid-size model: LM width {arch.width}, {arch.depth} layers; SigLIP width {arch.vision_width}, "
        f"{arch.vision_depth} layers; expert width {policy.expert_arch.width}; {STEPS} denoising steps",
    ]
    result = Result(
        name="policy_sweep",
        title="6. Steering α sweep",
        command=command("policy_sweep", args),
        measured=f"{ours:.2f} s / {n} alphas",
        baseline=f"{baseline:.2f} s",
        ratio=ratio,
        target=f"<= {TARGET}x",
        met=ratio <= TARGET,
        table=table,
        notes=notes,
        checks={"max_abs_difference": difference, "alpha_spread": spread, "real_flop_ratio_lm": real_lm,
                "real_flop_ratio_expert": real_expert},
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
