"""Capture throughput: our prefix-only capture against the seed's hooks on full pi0.5 inference calls.

Ours is `steering_core.capture.capture` end to end (LeRobot frames through its DataLoader workers, the prefix
only, the masked camera skipped, padding trimmed, SDPA, every requested layer in one pass that stops at the
deepest, shards written). The seed's approach (`bench.seed_pi05`) runs openpi's whole `sample_actions` per
batch with a forward hook on one decoder layer, once per requested layer, fed by a DataLoader over the same
LeRobot frames. Both read the same checkpoint, frames and batch size; the model is a mid-size pi0.5 that
fits a small CPU. Rounds alternate the two so that load from other processes hits both alike; each side's
best round is kept.

Next to the measured ratio: an analytic FLOP count per frame (matrix products only) for the mid-size
model and for the real pi0.5 at layer 12, and the frames/s that count implies on an H100 at 40% of its
dense bf16 peak.

    uv run python -m bench.capture_throughput [--device cuda] [--quick]
"""

from __future__ import annotations

import functools
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.common import (
    Result,
    cache_dir,
    command,
    finish,
    parser,
    timed,
)
from steering_core.devices import resolve_device
from steering_core.pi05 import Pi05Arch, PromptTokenizer, libero_camera_slots
from steering_core.synthetic.pi05 import tiny_arch

# ----------------------------------------------------------------------------- settings

# A mid-size pi0.5: the real depths of the language model, sequence lengths (3 x 256 image tokens + 200
# language slots) and head layout, with the widths cut 8x (LM) and 6x (SigLIP) and SigLIP's depth cut to
# 12, which keeps vision at about the real share of the prefix's FLOPs.
ARCH = Pi05Arch(
    width=256, depth=18, mlp_dim=2048, num_heads=8, num_kv_heads=1, head_dim=32, vocab_size=512,
    vision_width=192, vision_depth=12, vision_mlp_dim=768, vision_heads=4, patch_size=14, image_size=224,
)
FRAMES = 8  # one synthetic LIBERO demo of 8 steps (256 x 256 cameras, as physical-intelligence/libero)
BATCH_SIZE = 4  # the seed used 128 on a GPU; equal for both sides is what matters
NUM_WORKERS = 2  # DataLoader workers on both sides (capture passes it; its own default depends on the cores)
LAYER_SETS = ((12,), (4, 8, 12))  # the seed's single SAE layer, then several layers at once
ROUNDS = 2  # alternating ours/seed rounds, best kept
TARGET = 2.5  # ours / seed frames/s, layer 12

# Analytic counts for the real model.
REAL_ARCH = Pi05Arch()
# longest LIBERO prompt in a batch, BOS + instruction + "\n" (assumed: the real tokenizer is not available here)
REAL_PROMPT_TOKENS = 16
LANGUAGE_SLOTS = 200  # pi0.5's max_token_len: the seed runs every slot, padding included
LIBERO_CAMERAS, CAMERA_SLOTS = 2, 3  # LIBERO fills base and left wrist; pi0.5 has three slots
H100_BF16_DENSE_TFLOPS = 989.0  # H100 SXM dense bf16 peak (no sparsity)
MFU = 0.40  # assumed fraction of that peak reached

QUICK = {"arch": tiny_arch(), "frames": 8, "batch_size": 4, "layer_sets": ((2,), (1, 2)), "rounds": 1}

TASK_INDEX = 0  # synthetic LIBERO task used for the frames (drawer opening)


# ----------------------------------------------------------------------------- analytic FLOPs


def _linear(rows: float, fan_in: int, fan_out: int) -> float:
    """Return the FLOPs of a (rows, fan_in) x (fan_in, fan_out) product (2 per multiply-add)."""
    return 2.0 * rows * fan_in * fan_out


def siglip_flops(arch: Pi05Arch, images: int) -> float:
    """Return the FLOPs of SigLIP plus the projector over `images` images."""
    t, d, m = arch.tokens_per_image, arch.vision_width, arch.vision_mlp_dim
    layer = _linear(t, d, 4 * d) + 2 * 2.0 * t * t * d + _linear(t, d, m) + _linear(t, m, d)
    per_image = _linear(t, 3 * arch.patch_size**2, d) + arch.vision_depth * layer + _linear(t, d, arch.width)
    return images * per_image


def decoder_layer_flops(arch: Pi05Arch, queries: float, keys: float) -> float:
    """Return the FLOPs of one Gemma decoder layer for `queries` tokens attending to `keys` keys."""
    q, kv = arch.num_heads * arch.head_dim, arch.num_kv_heads * arch.head_dim
    projections = (
        _linear(queries, arch.width, q) + 2 * _linear(queries, arch.width, kv) + _linear(queries, q, arch.width)
    )
    attention = 2 * 2.0 * queries * keys * q  # q k^T and p v over every head
    return projections + attention + 3 * _linear(queries, arch.width, arch.mlp_dim)


def ours_flops(arch: Pi05Arch, deepest: int, prompt_tokens: int) -> float:
    """Return per-frame FLOPs of our capture: two cameras, trimmed language, layers 0..deepest."""
    tokens = LIBERO_CAMERAS * arch.tokens_per_image + prompt_tokens
    return siglip_flops(arch, LIBERO_CAMERAS) + (deepest + 1) * decoder_layer_flops(arch, tokens, tokens)


def ours_flops_selected_queries(arch: Pi05Arch, deepest: int, prompt_tokens: int) -> float:
    """Return `ours_flops` if the deepest layer ran only the instruction tokens' queries (K/V still for all)."""
    tokens = LIBERO_CAMERAS * arch.tokens_per_image + prompt_tokens
    selected = prompt_tokens - 2  # BOS and "\n" are not instruction tokens
    others = 2 * _linear(tokens - selected, arch.width, arch.num_kv_heads * arch.head_dim)
    last = decoder_layer_flops(arch, selected, tokens) + others
    return ours_flops(arch, deepest - 1, prompt_tokens) + last


def expert_step_flops(arch: Pi05Arch, prefix_keys: float) -> float:
    """Return the FLOPs of one denoising step of the action expert paired with `arch` (gemma_300m-shaped:
    half the width, a quarter of the MLP) whose action tokens attend to `prefix_keys` cached keys."""
    from bench.seed_pi05 import ACTION_DIM, ACTION_HORIZON, expert_arch

    expert = expert_arch(arch)
    width = expert.width
    keys = prefix_keys + ACTION_HORIZON
    per_layer = decoder_layer_flops(expert, ACTION_HORIZON, keys) + 2 * _linear(1, width, 3 * width)
    actions = _linear(ACTION_HORIZON, ACTION_DIM, width) + _linear(ACTION_HORIZON, width, ACTION_DIM)
    heads = actions + 2 * _linear(1, width, width)  # action in/out, time MLP
    return arch.depth * per_layer + _linear(1, width, 3 * width) + heads


def seed_flops(arch: Pi05Arch, passes: int) -> float:
    """Return per-frame FLOPs of `passes` full sample_actions calls (all slots, all layers, 10 expert steps)."""
    from bench.seed_pi05 import DENOISE_STEPS

    tokens = CAMERA_SLOTS * arch.tokens_per_image + LANGUAGE_SLOTS
    prefix = siglip_flops(arch, CAMERA_SLOTS) + arch.depth * decoder_layer_flops(arch, tokens, tokens)
    return passes * (prefix + DENOISE_STEPS * expert_step_flops(arch, tokens))


def sample_flops(arch: Pi05Arch, prompt_tokens: int) -> float:
    """Return per-row FLOPs of our `sample_actions`: two cameras, trimmed language, every layer, 10 expert steps."""
    from bench.seed_pi05 import DENOISE_STEPS

    tokens = LIBERO_CAMERAS * arch.tokens_per_image + prompt_tokens
    return ours_flops(arch, arch.depth - 1, prompt_tokens) + DENOISE_STEPS * expert_step_flops(arch, tokens)


def h100_frames_per_second(flops_per_frame: float) -> float:
    """Return frames/s at MFU of the H100's dense bf16 peak for a per-frame FLOP count."""
    return MFU * H100_BF16_DENSE_TFLOPS * 1e12 / flops_per_frame


# ----------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class Inputs:
    """Generated inputs shared by both sides."""

    dataset: Path
    repo_id: str
    checkpoint: Path
    tokenizer: Path
    prompt_tokens: int  # longest valid prompt among the frames' tasks


def model_files(folder: Path, arch: Pi05Arch, prefix: str = "checkpoint") -> tuple[Path, Path]:
    """Return (a generated checkpoint of `arch`, the generated tokenizer), writing whichever is not cached yet."""
    from steering_core.synthetic.pi05 import write_pi05_checkpoint
    from steering_core.synthetic.tokenizer import TOKENIZER_FILE, write_tokenizer

    checkpoint = folder / f"{prefix}-{arch.fingerprint()[:12]}"
    if not checkpoint.is_dir():
        write_pi05_checkpoint(checkpoint, arch)
    tokenizer = folder / TOKENIZER_FILE
    if not tokenizer.is_file():
        write_tokenizer(tokenizer)
    return checkpoint, tokenizer


def build_inputs(folder: Path, arch: Pi05Arch, frames: int) -> Inputs:
    """Return the LeRobot dataset, checkpoint and tokenizer, generating whatever is not cached yet."""
    from steering_core.data.convert import ConvertSettings, convert_libero
    from steering_core.synthetic.libero import DEMO_SUITE_TASKS, SyntheticSettings, write_libero_file
    task = DEMO_SUITE_TASKS[TASK_INDEX]
    demos = folder / f"libero-{frames}"
    if not (demos / task.file_name).is_file():
        write_libero_file(demos, task, num_demos=1, settings=SyntheticSettings(num_steps=frames))
    repo_id = f"bench/capture-{frames}"
    dataset = folder / f"lerobot-{frames}"
    convert_libero([demos], dataset, ConvertSettings(repo_id=repo_id))  # a no-op once converted
    checkpoint, tokenizer = model_files(folder, arch)
    prompt_tokens = PromptTokenizer(tokenizer).tokenize(task.instruction).n_valid
    return Inputs(dataset, repo_id, checkpoint, tokenizer, prompt_tokens)


# ----------------------------------------------------------------------------- the two sides


def run_ours(inputs: Inputs, run_dir: Path, arch: Pi05Arch, layers: tuple[int, ...], batch_size: int,
             device: torch.device) -> None:
    """Capture the dataset's frames into a fresh `run_dir` with the library's capture."""
    from steering_core.capture import CaptureSettings, capture
    from steering_core.pi05.spec import ModelSpec

    shutil.rmtree(run_dir, ignore_errors=True)
    settings = CaptureSettings(
        model=ModelSpec(checkpoint=inputs.checkpoint, tokenizer=inputs.tokenizer, arch=arch), layers=layers,
        batch_size=batch_size, device=str(device), num_workers=NUM_WORKERS,
    )
    capture(inputs.dataset, inputs.repo_id, run_dir, settings)


def seed_collate(items: list[dict[str, Any]], image_size: int) -> dict[str, Any]:
    """Return a batch of whole LeRobot items with the three camera slots resized (in a loader worker)."""
    from torch.utils.data import default_collate

    batch = default_collate(items)
    images, wrist = batch.pop("image"), batch.pop("wrist_image")
    batch["images"], batch["image_masks"] = libero_camera_slots(images, wrist, image_size)
    return batch


def run_seed(model: Any, inputs: Inputs, layers: tuple[int, ...], batch_size: int,
             max_batches: int | None = None) -> dict[int, torch.Tensor]:
    """Return layer -> instruction-token rows (n, width) float32 the seed's way: one full pass per layer."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from torch.utils.data import DataLoader

    from steering_core.capture.frames import worker_start_method
    from steering_core.capture.settings import select_tokens

    tokenizer = PromptTokenizer(inputs.tokenizer)
    language_start = CAMERA_SLOTS * model.prefix.arch.tokens_per_image
    captured: dict[int, torch.Tensor] = {}
    for layer in layers:
        frames = LeRobotDataset(inputs.repo_id, root=inputs.dataset)
        loader = DataLoader(frames, batch_size=batch_size, num_workers=NUM_WORKERS,
                            multiprocessing_context=worker_start_method(NUM_WORKERS),  # as capture starts them
                            collate_fn=functools.partial(seed_collate, image_size=model.prefix.arch.image_size))
        hooked: list[torch.Tensor] = []
        hook = model.prefix.layers[layer]  # the seed's hook point: one PaliGemma decoder layer
        handle = hook.register_forward_hook(lambda _m, _i, output, into=hooked: into.append(output))
        rows = []
        try:
            for number, batch in enumerate(loader):
                if max_batches is not None and number == max_batches:
                    break
                prompts = [tokenizer.tokenize(task) for task in batch["task"]]
                tokens = torch.from_numpy(np.stack([p.ids for p in prompts]))
                mask = torch.from_numpy(np.stack([p.mask for p in prompts]))
                model.sample_actions(batch["images"], batch["image_masks"], tokens, mask)
                output = hooked.pop()
                for b, prompt in enumerate(prompts):
                    rows.append(output[b, language_start + torch.from_numpy(select_tokens(prompt, "instructions"))])
        finally:
            handle.remove()
        captured[layer] = torch.cat(rows).float().cpu()
    return captured


def ours_rows(run_dir: Path, layer: int) -> torch.Tensor:
    """Return every captured row of one layer (n, width) float32, in shard order."""
    from steering_core.capture.shards import open_shard, read_run_metadata

    parts = []
    for record in read_run_metadata(run_dir).layer_shards(layer):
        with open_shard(run_dir / record.file) as reader:
            parts.append(reader.residuals().float())
    return torch.cat(parts)


# ----------------------------------------------------------------------------- benchmark


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return (and print) its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    device = resolve_device(args.device)
    folder = cache_dir(args) / "capture"
    arch, frames, batch_size = ARCH, FRAMES, BATCH_SIZE
    layer_sets, rounds = LAYER_SETS, ROUNDS
    if args.quick:
        arch, frames, batch_size = QUICK["arch"], QUICK["frames"], QUICK["batch_size"]
        layer_sets, rounds = QUICK["layer_sets"], QUICK["rounds"]
    inputs = build_inputs(folder, arch, frames)

    from bench.seed_pi05 import SeedPi05

    seed_model = SeedPi05.from_checkpoint(inputs.checkpoint, arch, device)
    # warm-up: imports, worker start-up, first-call allocations, on both sides
    run_dir = folder / "run"
    run_ours(inputs, run_dir, arch, layer_sets[0], batch_size, device)
    run_seed(seed_model, inputs, layer_sets[0][:1], batch_size, max_batches=1)

    # Rounds alternate the two sides. The seed's passes for several layers are the single-layer pass
    # repeated with the hook moved (identical work), so it is timed for one layer and counted per layer.
    single = layer_sets[0]
    ours_times: dict[tuple[int, ...], list[float]] = {layers: [] for layers in layer_sets}
    seed_times: list[float] = []
    differences: list[float] = []
    for _ in range(rounds):
        for layers in layer_sets:
            _, seconds = timed(lambda got=layers: run_ours(inputs, run_dir, arch, got, batch_size, device), device)
            ours_times[layers].append(seconds)
            if max(layers) == max(single):
                mine = ours_rows(run_dir, max(layers))
        seed_rows, seconds = timed(lambda: run_seed(seed_model, inputs, single, batch_size), device)
        seed_times.append(seconds)
        differences.append(float((mine - seed_rows[max(single)]).abs().max()))
    seed_pass = min(seed_times)
    rows: list[dict[str, Any]] = []
    for layers in layer_sets:
        deepest, passes = max(layers), len(layers)
        ours_fps, seed_fps = frames / min(ours_times[layers]), frames / (passes * seed_pass)
        seed_note = "" if passes == 1 else f" (seed: {passes} x its measured pass)"
        rows.append({
            "case": f"measured {device.type}, {_layers(layers)}{seed_note}",
            "frames": frames,
            "ours frames/s": ours_fps,
            "seed frames/s": seed_fps,
            "ratio": ours_fps / seed_fps,
            "FLOP ratio": seed_flops(arch, passes) / ours_flops_selected_queries(arch, deepest, inputs.prompt_tokens),
            "ours GFLOP/frame": ours_flops_selected_queries(arch, deepest, inputs.prompt_tokens) / 1e9,
            "seed GFLOP/frame": seed_flops(arch, passes) / 1e9,
            "H100 ours frames/s": "",
            "H100 seed frames/s": "",
        })
    for layers in LAYER_SETS:  # the real model's counts, for the full-size layer sets whatever the run size
        real_ours = ours_flops_selected_queries(REAL_ARCH, max(layers), REAL_PROMPT_TOKENS)
        real_seed = seed_flops(REAL_ARCH, len(layers))
        rows.append({
            "case": f"real pi0.5, {_layers(layers)} (analytic)",
            "frames": "",
            "ours frames/s": "",
            "seed frames/s": "",
            "ratio": "",
            "FLOP ratio": real_seed / real_ours,
            "ours GFLOP/frame": real_ours / 1e9,
            "seed GFLOP/frame": real_seed / 1e9,
            "H100 ours frames/s": h100_frames_per_second(real_ours),
            "H100 seed frames/s": h100_frames_per_second(real_seed),
        })
    headline = rows[0]
    real_layer = max(LAYER_SETS[0])
    real_ratio = seed_flops(REAL_ARCH, 1) / ours_flops(REAL_ARCH, real_layer, REAL_PROMPT_TOKENS)
    real_selected = ours_flops_selected_queries(REAL_ARCH, real_layer, REAL_PROMPT_TOKENS)
    real_ratio_selected = seed_flops(REAL_ARCH, 1) / real_selected
    result = Result(
        name="capture",
        title="1. Capture throughput (frames/s)",
        command=command("capture_throughput", args),
        measured=f"{headline['ours frames/s']:.2f} frames/s",
        baseline=f"{headline['seed frames/s']:.2f} frames/s",
        ratio=headline["ratio"],
        target=f">= {TARGET}x (layer {max(layer_sets[0])})",
        met=headline["ratio"] >= TARGET,
        table=rows,
        checks={"max_abs_difference": max(differences), "seed_flop_ratio_real": real_ratio_selected,
                "seed_flop_ratio_real_all_queries": real_ratio},
        notes=[
            f"mid-size model: LM width {arch.width} x depth {arch.depth} (MLP {arch.mlp_dim}), SigLIP width "
            f"{arch.vision_width} x depth {arch.vision_depth}, {arch.image_size} px, {LANGUAGE_SLOTS} language slots; "
            f"batch {batch_size}, "
            f"{NUM_WORKERS} loader workers, best of {rounds} alternating round(s); times include dataset open and "
            "loader start-up (both), checkpoint load and shard writing (ours).",
            f"same rows on both sides: max |ours - seed| over every layer-{max(single)} row = {max(differences):.2e}.",
            "FLOPs count matrix products only. At the mid-size widths attention is a larger share of the work "
            "than at the real widths, and the seed's eager attention over 968 tokens with a dense additive mask "
            "is slow on CPU, so the measured ratio exceeds the real model's FLOP ratio.",
            f"ours runs the deepest layer's queries, attention output and MLP for the captured rows only "
            f"(`capture.selected_rows.selected_residuals`; keys and values still from every token): the real layer-{real_layer} "
            f"FLOP ratio is {real_ratio_selected:.2f}x, against {real_ratio:.2f}x when every token runs the whole "
            "deepest layer (bench.real_size times both calls at the real size).",
            f"H100: {H100_BF16_DENSE_TFLOPS:.0f} TFLOP/s dense bf16 peak at {MFU:.0%} MFU; real prompt assumed "
            f"{REAL_PROMPT_TOKENS} tokens (batch max); the seed runs all {LANGUAGE_SLOTS} slots and 3 cameras.",
        ],
    )
    return finish(result, args)


def _layers(layers: tuple[int, ...]) -> str:
    """Return `layer 12` or `layers 4,8,12`."""
    return f"layer{'s' if len(layers) > 1 else ''} {','.join(map(str, layers))}"


if __name__ == "__main__":
    main()
