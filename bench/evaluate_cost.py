"""Evaluation cost: the dose-response sweep against the naive loop of full `sample_actions` calls.

Ours is `steering_core.evaluate.sweep.run_sweep`: per frame and noise seed, one `sample_actions_sweep` call
per chunk of (direction, α) entries, the prefix below the steered layer computed once per call and the
unsteered α = 0 entry shared by every direction, plus one call with the other task's instruction (the
swap reference). The naive loop runs one full `sample_actions` per frame × α × direction × seed (and the
same swap calls); every such call costs the same, so it is timed on `NAIVE_DIRECTIONS` of the directions
and its time scaled by the ratio of call counts (35 directions would take the naive loop half an hour). Both steer a frame of each task toward the other one (the positive one at −α) and
carry 3 named + 32 null directions (the default null). Both use the same mid-size pi0.5 (as the capture benchmark), frames, prompts, noise and
directions, and must give the same actions.

Next to the measured ratio: the analytic FLOPs (matrix products) and H100 time of one pair at one layer
at the real size with the default evaluate settings, for both.

Methods head to head: the same sweep with `METHODS` methods in both modes (add and clamp) beside the 32 random
null directions, against one method (add) with the same null, timed on the same policy and frames. Evaluated one
at a time, each method × mode would carry its own sweep and null: the comparison's cost is read against that
(`METHODS` × 2 times the single run), target at most half of it.

    uv run python -m bench.evaluate_cost [--device cuda] [--quick]
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.capture_throughput import (
    ARCH,
    CAMERA_SLOTS,
    H100_BF16_DENSE_TFLOPS,
    LANGUAGE_SLOTS,
    MFU,
    REAL_ARCH,
    decoder_layer_flops,
    model_files,
    seed_flops,
    siglip_flops,
)
from bench.common import Result, cache_dir, command, finish, parser, timed
from steering_core.devices import resolve_device
from steering_core.evaluate import EvaluateSettings
from steering_core.evaluate.frames import EvalFrame
from steering_core.evaluate.sweep import frame_noise, run_sweep
from steering_core.pairs import toward_sign
from steering_core.pi05 import Pi05Arch, PromptTokenizer, libero_camera_slots
from steering_core.synthetic.pi05 import tiny_arch

# ----------------------------------------------------------------------------- settings

LAYER = 12                      # the seed's SAE layer
FRAMES = 2                      # one frame of each task: both sides steered toward the other
NOISE_SEEDS = 1
DIRECTIONS = 3 + 32             # residual, mean difference, top-k and the 32 random null directions
ALPHAS = (-4.0, -2.0, 0.0, 2.0, 4.0)
NUM_STEPS = 10                  # openpi's denoising steps
NAIVE_DIRECTIONS = 4            # directions the naive loop is timed on (its calls all cost the same)
METHODS = 4                     # the default methods: sae, mean_difference, sae_top_k, probe
NULLS = 32                      # the random null every method shares
METHODS_TARGET = 0.5            # all methods x modes together / (methods x modes) separate runs, at most
ROUNDS = 2                      # alternating ours/naive rounds, best kept (load from other jobs hits both)
TARGET = 0.4                    # ours / naive wall time at most
POSITIVE, NEGATIVE = "open the top drawer of the cabinet", "close the top drawer of the cabinet"
QUICK = {"arch": tiny_arch(), "layer": 2, "frames": 2, "directions": 4, "alphas": (-2.0, 0.0, 2.0)}


# ----------------------------------------------------------------------------- analytic cost


def call_flops(arch: Pi05Arch) -> dict[str, float]:
    """Return the FLOPs of one frame's pieces: vision, one prefix decoder layer, the expert's denoising loop."""
    tokens = CAMERA_SLOTS * arch.tokens_per_image + LANGUAGE_SLOTS
    vision = siglip_flops(arch, CAMERA_SLOTS)
    layer = decoder_layer_flops(arch, tokens, tokens)
    expert = seed_flops(arch, 1) - vision - arch.depth * layer
    return {"vision": vision, "layer": layer, "expert": expert, "full": seed_flops(arch, 1)}


def pair_layer_flops(arch: Pi05Arch, layer: int, settings: EvaluateSettings, directions: int) -> dict[str, float]:
    """Return (ours, naive) FLOPs of one pair at one layer: every frame, seed, direction and α, plus the swap."""
    parts = call_flops(arch)
    steered = directions * (len(settings.alphas) - 1)
    chunks = math.ceil(steered / settings.entries_per_call)
    shared = parts["vision"] + (layer + 1) * parts["layer"]           # once per sweep call
    per_entry = (arch.depth - layer - 1) * parts["layer"] + parts["expert"]
    per_frame_seed_ours = chunks * shared + (1 + steered) * per_entry + parts["full"]
    per_frame_seed_naive = directions * len(settings.alphas) * parts["full"] + parts["full"]
    runs = settings.max_frames * settings.noise_seeds
    return {"ours": runs * per_frame_seed_ours, "naive": runs * per_frame_seed_naive}


def h100_seconds(flops: float) -> float:
    """Return seconds on an H100 at MFU of its dense bf16 peak."""
    return flops / (MFU * H100_BF16_DENSE_TFLOPS * 1e12)


# ----------------------------------------------------------------------------- inputs and the two sides


def build_policy(folder: Path, arch: Pi05Arch, device: torch.device) -> tuple[Any, Path]:
    """Return (the policy of a generated checkpoint of `arch`, written once; the generated tokenizer file)."""
    from steering_core.pi05.policy import Pi05Policy

    # "policy-": checkpoints cached before the action expert was written lack its tensors
    checkpoint, tokenizer = model_files(folder, arch, prefix="policy")
    return Pi05Policy.from_checkpoint(checkpoint, arch=arch, device=device, tokenizer_path=tokenizer), tokenizer


def frame_inputs(arch: Pi05Arch, frames: int) -> dict[str, Any]:
    """Return random 256 px LIBERO cameras of `frames` frames in pi0.5's three slots."""
    generator = torch.Generator().manual_seed(0)
    image, wrist = (torch.rand(frames, 3, 256, 256, generator=generator) for _ in range(2))
    images, masks = libero_camera_slots(image, wrist, arch.image_size)
    return {"images": images, "image_masks": masks}


def run_naive(policy: Any, inputs: dict[str, Any], frames: list[EvalFrame], prompts: Any,
              directions: dict[str, torch.Tensor], layer: int, alphas: tuple[float, ...], seeds: int) -> torch.Tensor:
    """Return robot actions (directions, alphas, frames, seeds, H, 7): one full sample_actions each, plus swaps."""
    from steering_core.pi05.steering import Steering

    out = torch.zeros(len(directions), len(alphas), len(frames), seeds, policy.action_horizon, 7, dtype=torch.float64)
    device = policy.device
    for f, frame in enumerate(frames):
        own, other = prompts.prompts[frame.side], prompts.prompts["positive" if frame.side == "negative" else "negative"]
        toward = toward_sign(frame.side)
        images = [t[f : f + 1].to(device) for t in inputs["images"]]
        masks = [t[f : f + 1].to(device) for t in inputs["image_masks"]]
        for s in range(seeds):
            noise = frame_noise(frame, s, 0, policy.action_horizon, policy.action_dim)[None].to(device)
            for d, vector in enumerate(directions.values()):
                unit = (vector / vector.norm()).to(device)
                for a, alpha in enumerate(alphas):
                    steering = None if alpha == 0 else Steering(layer=layer, vector=unit, alpha=toward * alpha,
                                                                token_mask=own.instruction_mask.to(device))
                    actions = policy.sample_actions(images, masks, own.tokens.to(device), own.token_mask.to(device),
                                                    noise=noise, num_steps=NUM_STEPS, steering=steering)
                    out[d, a, f, s] = torch.from_numpy(np.asarray(policy.robot_actions(actions), np.float64))[0]
            policy.sample_actions(images, masks, other.tokens.to(device), other.token_mask.to(device), noise=noise,
                                  num_steps=NUM_STEPS)
    return out


def methods_cost(sweep: Any, width: int, nulls: int) -> dict[str, float]:
    """Return the seconds of one sweep with METHODS methods in both modes plus `nulls` null directions, of one
    method (add) plus the same nulls, and their ratio to METHODS × 2 separate runs. `sweep(directions, clamps)`
    runs `run_sweep`."""
    generator = torch.Generator().manual_seed(2)
    null = {f"random_{i:02d}": torch.randn(width, generator=generator) for i in range(nulls)}
    methods = {f"m{i}": torch.randn(width, generator=generator) for i in range(METHODS)}
    both = {f"{name}{suffix}": vector for name, vector in methods.items() for suffix in ("", ":clamp")}
    clamps = {f"{name}:clamp": (-1.0, 1.0) for name in methods}
    sweep(both | null, clamps)  # warm-up
    _, together = timed(lambda: sweep(both | null, clamps), torch.device("cpu"))
    _, single = timed(lambda: sweep({"m0": methods["m0"]} | null, {}), torch.device("cpu"))
    return {"together": together, "single": single, "ratio": together / (len(both) * single)}


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return (and print) its result."""
    from steering_core.evaluate.run import task_prompts
    from steering_core.pi05.steering import Steering

    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)
    arch, layer, n_frames, n_directions, alphas = ARCH, LAYER, FRAMES, DIRECTIONS, ALPHAS
    if args.quick:
        arch, layer, n_frames = QUICK["arch"], QUICK["layer"], QUICK["frames"]
        n_directions, alphas = QUICK["directions"], QUICK["alphas"]
    policy, tokenizer = build_policy(cache_dir(args) / "evaluate", arch, device)
    prompts = task_prompts(PromptTokenizer(tokenizer), POSITIVE, NEGATIVE)
    inputs = frame_inputs(arch, n_frames)
    frames = [EvalFrame("positive" if i % 2 else "negative", i, i, i) for i in range(n_frames)]
    generator = torch.Generator().manual_seed(1)
    directions = {f"d{i}": torch.randn(arch.width, generator=generator) for i in range(n_directions)}

    def sweep(chosen: dict[str, torch.Tensor], clamps: dict[str, tuple[float, float]]) -> torch.Tensor:
        return run_sweep(policy, Steering, frames, lambda _: inputs, prompts, chosen, layer=layer, alphas=alphas,
                         mean_residual_norm=1.0, noise_seeds=NOISE_SEEDS, seed=0, num_steps=NUM_STEPS,
                         batch_size=n_frames, entries_per_call=EvaluateSettings().entries_per_call,
                         clamps=clamps).steered

    def ours() -> torch.Tensor:
        return sweep(directions, {})

    step = max(1, n_directions // NAIVE_DIRECTIONS)
    sampled = list(directions)[::step][:NAIVE_DIRECTIONS]
    rows_sampled = [list(directions).index(name) for name in sampled]

    def naive() -> torch.Tensor:
        return run_naive(policy, inputs, frames, prompts, {k: directions[k] for k in sampled}, layer, alphas,
                         NOISE_SEEDS)

    ours()  # warm-up: first-call allocations
    ours_times, naive_times, differences = [], [], []
    for _ in range(ROUNDS):
        mine, seconds = timed(ours, device)
        ours_times.append(seconds)
        reference, seconds = timed(naive, device)
        naive_times.append(seconds)
        differences.append(float((mine[rows_sampled] - reference).abs().max()))
    calls = n_frames * NOISE_SEEDS * (n_directions * len(alphas) + 1)
    timed_calls = n_frames * NOISE_SEEDS * (len(sampled) * len(alphas) + 1)
    naive_seconds = min(naive_times) * calls / timed_calls
    ratio = min(ours_times) / naive_seconds
    methods = methods_cost(sweep, arch.width, 4 if args.quick else NULLS)
    defaults = EvaluateSettings()
    real_directions = METHODS * len(defaults.modes) + defaults.random_directions + defaults.permutations
    real = pair_layer_flops(REAL_ARCH, LAYER, defaults, real_directions)
    rows = [
        {"case": f"measured {device.type}, layer {layer}", "frames x seeds": f"{n_frames} x {NOISE_SEEDS}",
         "directions x alphas": f"{n_directions} x {len(alphas)}", "ours s": min(ours_times),
         "naive s": naive_seconds, "ratio": ratio, "ours TFLOP": "", "naive TFLOP": "", "H100 ours s": "",
         "H100 naive s": ""},
        {"case": f"real pi0.5, layer {LAYER}, one pair (analytic)", "frames x seeds":
         f"{EvaluateSettings().max_frames} x {EvaluateSettings().noise_seeds}",
         "directions x alphas": f"{real_directions} x {len(defaults.alphas)}",
         "ours s": "", "naive s": "", "ratio": real["ours"] / real["naive"], "ours TFLOP": real["ours"] / 1e12,
         "naive TFLOP": real["naive"] / 1e12, "H100 ours s": h100_seconds(real["ours"]),
         "H100 naive s": h100_seconds(real["naive"])},
        {"case": f"methods: {METHODS} x 2 modes + null vs 1 method + null, layer {layer}",
         "frames x seeds": f"{n_frames} x {NOISE_SEEDS}",
         "directions x alphas": f"{METHODS * 2}+{4 if args.quick else NULLS} vs 1+{4 if args.quick else NULLS} x "
                                f"{len(alphas)}",
         "ours s": methods["together"], "naive s": METHODS * 2 * methods["single"], "ratio": methods["ratio"],
         "ours TFLOP": "", "naive TFLOP": "", "H100 ours s": "", "H100 naive s": ""},
    ]
    result = Result(
        name="evaluate",
        title="9. Steering evaluation cost (one pair, one layer)",
        command=command("evaluate_cost", args),
        measured=f"{min(ours_times):.1f} s",
        baseline=f"{naive_seconds:.1f} s",
        ratio=ratio,
        target=f"<= {TARGET}x (layer {layer})",
        met=ratio <= TARGET,
        table=rows,
        checks={"max_abs_difference": max(differences), "naive_calls": calls, "naive_calls_timed": timed_calls,
                "methods_ratio": methods["ratio"], "methods_target_met": methods["ratio"] <= METHODS_TARGET},
        notes=[
            f"model{'' if args.quick else ' (the capture benchmark mid-size pi0.5)'}: LM width {arch.width} x depth {arch.depth}, SigLIP width "
            f"{arch.vision_width} x depth {arch.vision_depth}; {NUM_STEPS} denoising steps; naive: {calls} full "
            f"sample_actions calls, timed on {timed_calls} of them ({len(sampled)} of {n_directions} directions: "
            f"{min(naive_times):.1f} s) and scaled; best of {ROUNDS} round(s) after a warm-up.",
            f"same actions on both sides: max |ours - naive| over every robot action of the {len(sampled)} "
            f"timed directions = {max(differences):.2e}.",
            f"methods: {METHODS} methods x 2 modes with the shared null in one sweep took {methods['together']:.1f} s, "
            f"one method with the same null {methods['single']:.1f} s: {methods['ratio']:.2f}x of {METHODS * 2} "
            f"separate runs (target <= {METHODS_TARGET}x: "
            f"{'met' if methods['ratio'] <= METHODS_TARGET else 'not met'}).",
            f"real size: the default evaluate settings ({METHODS} methods x 2 modes + {defaults.random_directions} random + "
            f"{defaults.permutations} permuted directions, 9 alphas, 32 frames, 4 seeds, "
            f"{EvaluateSettings().entries_per_call} entries per sweep call) and {LANGUAGE_SLOTS} language slots; "
            f"FLOPs count matrix products only; H100 at {MFU:.0%} of {H100_BF16_DENSE_TFLOPS:.0f} TFLOP/s dense bf16.",
        ],
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
