"""Capture input: frames/s the capture loader delivers against the frames/s the model takes.

The loader is `steering_core.capture.frames` as capture runs it: DataLoader workers decode a LeRobot dataset's
two 256 px PNG cameras (a synthetic LIBERO demo converted by the library, as physical-intelligence/libero) and
collate uint8 frames; pi0.5's camera slots (antialiased resize-with-pad to 224, scaling to [-1, 1]) are then
computed on the model's device (`slots_on_device`). Timed here: decode alone with 1 and 2 workers, decode plus
the device-side slots with capture's default workers, and, as the baseline of the change, the old path that
resized in the workers. Each loader is timed in steady state: its start-up (forkserver, imports) and the batches
its workers queued meanwhile are left out; the loaders take turns over a few rounds and each keeps its best.

The model's frames/s is --model-fps, or capture's fastest batch in a GPU check JSON (--gpu-check, written by
bench.gpu_check: `checks.figures.capture_frames_per_s`), or else measured here: `selected_residuals` at
layer 12 of bench.capture_throughput's mid-size model. The headline is a 16-core GPU machine's loader, derived
from this machine: the 1-worker decode rate x the workers capture's default starts on 16 cores
(`frame_workers`) x the scaling efficiency measured from 1 to 2 workers (rate(2) / (2 x rate(1))), applied
once; the slots are then a GPU kernel on the main process, which the default leaves a core to.

    uv run python -m bench.capture_input [--device cuda] [--quick] [--model-fps N | --gpu-check FILE]
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench.capture_throughput import ARCH, Inputs, build_inputs
from bench.common import Result, cache_dir, command, finish, parser, repeat_timed, synchronize
from steering_core.capture import frames as capture_frames
from steering_core.devices import resolve_device
from steering_core.pi05 import Pi05Arch, PromptTokenizer, libero_camera_slots
from steering_core.synthetic.pi05 import tiny_arch

# ----------------------------------------------------------------------------- settings

FRAMES = 512  # one synthetic demo of 512 steps, two 256 px cameras per frame
BATCH_SIZE = 32  # capture's default
LAYER = 12  # the seed's SAE layer
MODEL_BATCH = 4  # frames per timed model call on the CPU (the mid-size model takes seconds per frame here)
MODEL_REPEATS = 2
GPU_CORES = 16  # the GPU machine the figure is projected to (H100 / H200 hosts here)
TARGET = 1.2  # loader / model frames/s: the loader must keep ahead of the model
SETTLE_S = 10.0  # most seconds a loader's workers get to fill their queues before the clock starts
ROUNDS = 2  # rounds over every loader, in turn; each loader's best round is kept (other processes' load hits all)

QUICK = {"arch": tiny_arch(), "frames": 48, "batch_size": 8, "layer": 2, "model_batch": 2, "model_repeats": 1,
         "settle_s": 0.0, "rounds": 1}


# ----------------------------------------------------------------------------- the loader


def old_collate(items: list[dict[str, Any]], image_size: int) -> dict[str, Any]:
    """Return a batch with the camera slots computed in the worker: capture's loader before the change."""
    from torch.utils.data import default_collate

    batch = default_collate(items)
    batch["images"], batch["image_masks"] = libero_camera_slots(batch.pop("image"), batch.pop("wrist_image"),
                                                                image_size)
    return batch


def steady_frames_per_s(batches: Iterable[dict[str, Any]], workers: int, device: torch.device,
                        settle_s: float) -> float:
    """Return frames/s over the batches a loader produces once running: after its first batch (start-up), the
    clock waits until each worker could have filled its queue (2 batches) and starts once those are taken."""
    batches = iter(batches)
    start = time.perf_counter()
    next(batches)
    if workers:
        time.sleep(min(settle_s, 2 * (time.perf_counter() - start)))
        for _ in range(2 * workers - 1):
            next(batches)
    synchronize(device)
    start, frames = time.perf_counter(), 0
    for batch in batches:
        frames += len(batch["index"])
    synchronize(device)
    return frames / (time.perf_counter() - start)


def loader_rates(inputs: Inputs, image_size: int, batch_size: int, device: torch.device,
                 settle_s: float, rounds: int) -> dict[str, float]:
    """Return the best frames/s over `rounds` of: the old path (1 worker), decode alone (1 and 2 workers), decode
    plus device slots (capture's default workers here)."""
    from torch.utils.data import DataLoader

    from steering_core.data.dataset import read_meta

    meta = read_meta(inputs.dataset)
    episodes = [e.episode_index for e in meta.episodes]
    frames = capture_frames.frame_source(meta, inputs.repo_id, episodes, None)
    plan = capture_frames.batch_plan(frames, {"0": tuple(episodes)}, batch_size)
    keys = capture_frames.FRAME_KEYS
    dataset = capture_frames.FrameDataset(frames, keys, meta)  # each frame checked as capture checks it
    default = capture_frames.frame_workers(None)
    loaders = {  # name -> (a fresh loader, its workers)
        "old: decode + resize in 1 worker": (lambda: DataLoader(
            dataset, batch_sampler=[p for _, p in plan], num_workers=1,
            multiprocessing_context=capture_frames.worker_start_method(1),
            collate_fn=functools.partial(old_collate, image_size=image_size)), 1),
        "decode, 1 worker": (lambda: capture_frames.frame_loader(frames, plan, keys, 1, False, meta), 1),
        "decode, 2 workers": (lambda: capture_frames.frame_loader(frames, plan, keys, 2, False, meta), 2),
        f"decode + slots on {device.type}, default ({default} worker{'s' if default != 1 else ''})":
            (lambda: capture_frames.frame_batches(frames, plan, keys, image_size, None, device, meta), default),
    }
    best = dict.fromkeys(loaders, 0.0)
    for _ in range(rounds):
        for name, (loader, workers) in loaders.items():
            best[name] = max(best[name], steady_frames_per_s(loader(), workers, device, settle_s))
    return best


# ----------------------------------------------------------------------------- the model


def gpu_check_fps(path: Path) -> float:
    """Return the model's frames/s in a GPU check JSON: capture's fastest batch (`checks.figures`)."""
    from bench.gpu_check import read_figures

    figure = read_figures(path, "capture_frames_per_s")["capture_frames_per_s"]
    values = list(figure.values()) if isinstance(figure, dict) else [figure]
    if not values or not all(isinstance(v, int | float) and v > 0 for v in values):
        raise ValueError(f"{path}: capture_frames_per_s is {figure!r}, expected positive frames/s per batch size")
    return float(max(values))


def measured_model_fps(inputs: Inputs, arch: Pi05Arch, layer: int, batch: int, repeats: int,
                       device: torch.device) -> float:
    """Return frames/s of capture's model call (`selected_residuals`, instruction tokens) on `batch` frames."""
    from steering_core.capture.selected_rows import selected_residuals
    from steering_core.capture.settings import select_tokens
    from steering_core.pi05.model import Pi05Prefix

    model = Pi05Prefix.from_checkpoint(inputs.checkpoint, arch, layer, device)
    generator = torch.Generator().manual_seed(0)
    images, masks = libero_camera_slots(*(torch.rand(batch, 3, 256, 256, generator=generator) for _ in range(2)),
                                        arch.image_size)
    prompt = PromptTokenizer(inputs.tokenizer).tokenize("open the top drawer of the cabinet")
    tokens = torch.from_numpy(np.stack([prompt.ids] * batch))
    token_mask = torch.from_numpy(np.stack([prompt.mask] * batch))
    chosen = torch.from_numpy(select_tokens(prompt, "instructions"))
    frame_of_row = torch.arange(batch).repeat_interleave(len(chosen))
    positions = 3 * arch.tokens_per_image + chosen.repeat(batch)
    with torch.inference_mode():
        seconds = repeat_timed(lambda: selected_residuals(model, images, masks, tokens, token_mask, [layer],
                                                          frame_of_row, positions), device, warmup=1, repeats=repeats)
    return batch / min(seconds)


# ----------------------------------------------------------------------------- benchmark


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return (and print) its result."""
    arguments = parser(__doc__.splitlines()[0])
    source = arguments.add_mutually_exclusive_group()
    source.add_argument("--model-fps", type=float, default=None, help="the model's frames/s (e.g. from a GPU run)")
    source.add_argument("--gpu-check", type=Path, default=None, help="GPU check JSON with capture.frames_per_s")
    args = arguments.parse_args(argv)
    device = resolve_device(args.device)
    arch, frames, batch_size, layer = ARCH, FRAMES, BATCH_SIZE, LAYER
    model_batch, model_repeats, settle_s, rounds = MODEL_BATCH, MODEL_REPEATS, SETTLE_S, ROUNDS
    if args.quick:
        arch, frames, batch_size, layer = QUICK["arch"], QUICK["frames"], QUICK["batch_size"], QUICK["layer"]
        model_batch, model_repeats = QUICK["model_batch"], QUICK["model_repeats"]
        settle_s, rounds = QUICK["settle_s"], QUICK["rounds"]
    inputs = build_inputs(cache_dir(args) / "capture", arch, frames)

    rates = loader_rates(inputs, arch.image_size, batch_size, device, settle_s, rounds)
    if args.model_fps is not None:
        model_fps, model_source, extra = args.model_fps, "given (--model-fps)", [f"--model-fps {args.model_fps:g}"]
    elif args.gpu_check is not None:
        model_fps, model_source = gpu_check_fps(args.gpu_check), f"GPU check {args.gpu_check}"
        extra = [f"--gpu-check {args.gpu_check}"]
    else:
        model_fps = measured_model_fps(inputs, arch, layer, model_batch, model_repeats, device)
        model_source, extra = f"measured here: {device.type}, layer {layer}, batch {model_batch}", []

    one, two = rates["decode, 1 worker"], rates["decode, 2 workers"]
    efficiency = two / (2 * one)
    gpu_workers = min(GPU_CORES - 1, capture_frames.MAX_DEFAULT_WORKERS)
    projected = one * gpu_workers * efficiency
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    rows = [{"case": f"{name} ({cores} cores here)", "frames/s": fps, "/ model": fps / model_fps}
            for name, fps in rates.items()]
    rows.append({"case": f"projected: {GPU_CORES}-core machine, default {gpu_workers} workers", "frames/s": projected,
                 "/ model": projected / model_fps})
    rows.append({"case": f"model ({model_source})", "frames/s": model_fps, "/ model": 1.0})
    result = Result(
        name="capture_input",
        title="15. Capture input (frames/s)",
        command=command("capture_input", args, *extra),
        measured=f"{projected:.0f} frames/s (loader, {GPU_CORES} cores, projected)",
        baseline=f"{model_fps:.1f} frames/s (model)",
        ratio=projected / model_fps,
        target=f">= {TARGET}x",
        met=projected / model_fps >= TARGET,
        table=rows,
        checks={"efficiency": efficiency, "gpu_workers": gpu_workers,
                "default_workers_here": capture_frames.frame_workers(None)},
        notes=[
            f"{frames} frames, batch {batch_size}, two 256 px PNG cameras per frame; steady state (start-up left "
            f"out); best of {rounds} round(s) over the loaders in turn.",
            f"{GPU_CORES}-core figure = decode rate with 1 worker ({one:.0f} frames/s) x {gpu_workers} workers "
            f"(capture's default there: one per core less one, at most {capture_frames.MAX_DEFAULT_WORKERS}) x "
            f"scaling efficiency {efficiency:.2f} (2 workers: {two:.0f} frames/s = {efficiency:.2f} x twice 1 worker).",
            "On CUDA the slots run as GPU kernels after a non-blocking copy from pinned memory; on the CPU they run "
            "in the main process, which is what the default row's rate includes here.",
            f"the model's rate: {model_source}.",
        ],
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
