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

Each section's peak memory is recorded (`torch.cuda.max_memory_allocated`, reset between sections; peak RSS
on the CPU). Every comparison has a tolerance; the command exits with status 1 when one is exceeded.
`--quick` runs tiny sizes on the CPU to prove the script (its numbers are not benchmarks).

    uv run python -m bench.gpu_check [--quick] [--sections peak capture ...] [--json PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import importlib.util
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench import capture_throughput, policy_sweep, sae_encoding, sae_training, serve_latency
from bench.capture_throughput import REAL_PROMPT_TOKENS, ours_flops_selected_queries, seed_flops
from bench.common import (
    Result,
    cache_dir,
    command,
    finish,
    machine,
    median,
    parser,
    peak_rss_mib,
    repeat_timed,
    timed,
)
from bench.policy_latency import measure_latency
from bench.real_size import checkpoint_folder
from steering_core.devices import resolve_device, resolve_dtype
from steering_core.pi05 import Pi05Arch, Pi05Policy, Steering
from steering_core.pi05.steering import Splice
from steering_core.synthetic.pi05 import tiny_arch

# ----------------------------------------------------------------------------- settings

# Tolerances on relative errors (‖got − want‖ / ‖want‖; per row for residual rows; 1 − cosine for a
# steering's effect). float32 on CUDA computes what float32 on the CPU computes in another order: rounding
# alone, ~1e-6 (3e-7 on the first H200 run). bfloat16 keeps 8 significant bits (2^-9 = 0.2% per rounding),
# compounded over 18 layers and 10 Euler steps: the first H200 run saw 0.31% on actions and up to 1.1% per
# captured row; 3% leaves room for that while a real fault (a mask or a steering lost) is off by O(1).
TOLERANCES = {torch.float32: 1e-5, torch.bfloat16: 3e-2}
PROMPT_TOKENS = REAL_PROMPT_TOKENS  # valid tokens of each frame's prompt
STEPS = 10  # denoising steps
BATCH1_TARGET_MS = 40.0  # batch-1 sample_actions on an H100/H200-class GPU (published pi0.5: 22-57 ms on 4090 / L40S)
SWEEP_ALPHAS = policy_sweep.ALPHAS  # 8 steerings
VECTOR_NORM = 10.0  # steering vectors' norm (alpha 1)
# The precision section steers the LM at every prefix position with alpha 16: in the mid-size random model that
# moves the float32 actions by 17%, against bf16's 0.3% rounding; steering the 14 instruction tokens moved them
# by 0.8% at most (whatever alpha), too little for the effect to be compared in bf16.
LM_ALPHA = 16.0
SAE_ARCHITECTURES = ("standard", "topk")
SAE_TOPK_K = 64


@dataclasses.dataclass(frozen=True)
class Sizes:
    """What each section runs at: the real pi0.5 on CUDA, or tiny shapes with --quick."""

    matmul: int  # side of the peak matmul
    arch: Pi05Arch  # the served / timed policy
    layer: int  # captured and steered language-model layer
    capture_batches: tuple[int, ...]
    latency_batches: tuple[int, ...]
    precision_arch: Pi05Arch
    precision_batch: int
    sae: tuple[int, int, int]  # d_in, d_sae, rows per batch
    sae_training: dict[str, int]  # bench.sae_training's sizes
    repeats: int  # timed calls per measurement (median), after one warm-up
    server_rounds: int


REAL = Sizes(matmul=8192, arch=Pi05Arch(), layer=12, capture_batches=(32, 128), latency_batches=(1, 4, 16, 64),
             precision_arch=capture_throughput.ARCH, precision_batch=2, sae=(2048, 16384, 512),
             sae_training={"d_in": sae_training.D_IN, "d_sae": sae_training.D_SAE, "k": sae_training.K,
                           "batch_size": sae_training.BATCH_SIZE, "steps": sae_training.STEPS,
                           "run_rows": sae_training.RUN_ROWS},
             repeats=5, server_rounds=20)
QUICK = Sizes(matmul=512, arch=tiny_arch(), layer=2, capture_batches=(2, 4), latency_batches=(1, 4),
              precision_arch=tiny_arch(), precision_batch=2, sae=(64, 256, 128),
              sae_training={**sae_training.QUICK, "steps": 4}, repeats=2, server_rounds=3)


# ----------------------------------------------------------------------------- records


@dataclasses.dataclass
class Comparison:
    """One output compared with its reference: the error against its tolerance."""

    case: str
    metric: str  # "relative error", "max row relative error" or "1 - cosine"
    error: float
    tolerance: float

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.error)) and self.error <= self.tolerance

    def to_json(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "passed": self.passed}


@dataclasses.dataclass
class Section:
    """A section's measures (each beside its baseline), comparisons and notes."""

    measures: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    comparisons: list[Comparison] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)
    figures: dict[str, Any] = dataclasses.field(default_factory=dict)  # what other benchmarks read (`checks.figures`)

    def measure(self, measure: str, value: Any, against: str = "", ratio: float | str = "") -> None:
        self.measures.append({"measure": measure, "value": value, "against": against, "ratio": ratio})


class Context:
    """The run's device, sizes and generated inputs; the real-size policy loaded once for the sections using it."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.device = resolve_device(args.device)
        self.sizes = QUICK if args.quick else REAL
        self.folder = cache_dir(args) / "gpu_check"
        self.checkpoint = checkpoint_folder(args)  # shared with bench.real_size and bench.policy_real_size
        self.tokenizer = self.checkpoint.parent / "pi05-tokenizer.model"
        self._peak: float | None = None
        self._policy: tuple[Pi05Policy, float] | None = None

    @property
    def dtype(self) -> torch.dtype:
        """Return the policy's compute dtype on this device (as `from_checkpoint` picks it)."""
        return resolve_dtype(None, self.device)

    def write_checkpoint(self) -> None:
        """Write the random bf16 checkpoint and the tokenizer unless cached."""
        from steering_core.synthetic.pi05 import write_pi05_checkpoint
        from steering_core.synthetic.tokenizer import write_tokenizer

        if not (self.checkpoint / "model.safetensors").is_file():
            write_pi05_checkpoint(self.checkpoint, self.sizes.arch, dtype=torch.bfloat16, overwrite=True)
        if not self.tokenizer.is_file():
            write_tokenizer(self.tokenizer)

    def peak_flops(self) -> float:
        """Return the practical peak FLOP/s: the median of a square matmul in the policy's dtype (measured once)."""
        if self._peak is None:
            n = self.sizes.matmul
            a, b = (torch.randn(n, n, device=self.device, dtype=self.dtype) for _ in range(2))
            out = torch.empty(n, n, device=self.device, dtype=self.dtype)
            seconds = median(repeat_timed(lambda: torch.matmul(a, b, out=out), self.device, warmup=3,
                                          repeats=2 * self.sizes.repeats))
            self._peak = 2.0 * n**3 / seconds
        return self._peak

    def policy(self) -> tuple[Pi05Policy, float]:
        """Return (the real-size policy as `from_checkpoint` builds it on the device, its load seconds)."""
        if self._policy is None:
            start = time.perf_counter()
            policy = Pi05Policy.from_checkpoint(self.checkpoint, self.sizes.arch, device=self.device,
                                                tokenizer_path=self.tokenizer)
            self._policy = policy, time.perf_counter() - start
        return self._policy

    def release_policy(self) -> None:
        self._policy = None


# ----------------------------------------------------------------------------- comparisons


def relative_error(got: torch.Tensor, want: torch.Tensor) -> float:
    """Return ‖got − want‖ / ‖want‖ over whole tensors, in float64 on the CPU."""
    got, want = got.detach().double().cpu(), want.detach().double().cpu()
    return float((got - want).norm() / want.norm())


def row_relative_error(got: torch.Tensor, want: torch.Tensor) -> float:
    """Return the largest ‖got_i − want_i‖ / ‖want_i‖ over the rows i of (n, width) tensors."""
    got, want = got.detach().double().cpu(), want.detach().double().cpu()
    return float(((got - want).norm(dim=-1) / want.norm(dim=-1)).max())


def one_minus_cosine(got: torch.Tensor, want: torch.Tensor) -> float:
    """Return 1 − cos(got, want) of the flattened tensors."""
    got, want = got.detach().double().cpu().flatten(), want.detach().double().cpu().flatten()
    return float(1 - got @ want / (got.norm() * want.norm()))


def tolerance(dtype: torch.dtype) -> float:
    """Return the relative tolerance of results computed in `dtype` against float32 on the CPU."""
    return TOLERANCES[dtype]


@contextlib.contextmanager
def full_float32() -> Iterator[None]:
    """Run the block with TF32 off for matmuls and cuDNN convolutions (SigLIP's patches), then restore both:
    float32 on CUDA must round like float32, not like TF32's 10-bit mantissa."""
    matmul, cudnn = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = matmul, cudnn


# ----------------------------------------------------------------------------- inputs


def frames(arch: Pi05Arch, batch: int, device: torch.device) -> tuple[list, list, torch.Tensor, torch.Tensor]:
    """Return `batch` LIBERO-shaped frames (`bench.policy_sweep.frame`) on `device`."""
    images, masks, tokens, token_mask = policy_sweep.frame(arch, PROMPT_TOKENS, batch)
    return ([image.to(device) for image in images], [mask.to(device) for mask in masks], tokens.to(device),
            token_mask.to(device))


def instruction_mask(batch: int) -> torch.Tensor:
    """Return (batch, 200) bool on the CPU: the prompt's instruction tokens (BOS and the closing "\\n" left out)."""
    mask = torch.zeros(batch, policy_sweep.TOKEN_SLOTS, dtype=torch.bool)
    mask[:, 1 : PROMPT_TOKENS - 1] = True
    return mask


def random_vector(width: int, seed: int) -> torch.Tensor:
    """Return a random (width,) float32 CPU vector of norm VECTOR_NORM."""
    vector = torch.randn(width, generator=torch.Generator().manual_seed(seed))
    return vector / vector.norm() * VECTOR_NORM


def noise(policy: Pi05Policy, batch: int) -> torch.Tensor:
    """Return fixed (batch, horizon, action_dim) float32 CPU noise."""
    generator = torch.Generator().manual_seed(3)
    return torch.randn(batch, policy.action_horizon, policy.action_dim, generator=generator)


# ----------------------------------------------------------------------------- sections


def peak(ctx: Context) -> Section:
    """The practical peak: a square matmul in the policy's dtype."""
    section = Section()
    n = ctx.sizes.matmul
    section.measure(f"{str(ctx.dtype).removeprefix('torch.')} matmul {n}^3 TFLOP/s", ctx.peak_flops() / 1e12)
    section.figures["peak_tflops"] = ctx.peak_flops() / 1e12
    return section


def capture(ctx: Context) -> Section:
    """Capture's forward (selected rows) against the seed's whole inference call with a hook, same rows."""
    from bench.seed_pi05 import SeedPi05
    from steering_core.capture.selected_rows import selected_residuals

    section = Section()
    arch, layer, device = ctx.sizes.arch, ctx.sizes.layer, ctx.device
    model = SeedPi05.from_checkpoint(ctx.checkpoint, arch, device)
    ours_flops = ours_flops_selected_queries(arch, layer, PROMPT_TOKENS)
    peak_flops = ctx.peak_flops()
    instruction = torch.arange(1, PROMPT_TOKENS - 1)  # BOS and "\n" are not instruction tokens
    for batch in ctx.sizes.capture_batches:
        inputs = frames(arch, batch, device)
        frame_of_row = torch.arange(batch).repeat_interleave(len(instruction)).to(device)
        positions = (arch.prefix_length(3, 0) + instruction).repeat(batch).to(device)

        def ours() -> torch.Tensor:
            return selected_residuals(model.prefix, *inputs, [layer], frame_of_row, positions)[layer]

        def seed() -> torch.Tensor:  # the seed's hook point: one decoder layer, for one whole inference call
            hooked: list[torch.Tensor] = []
            handle = model.prefix.layers[layer].register_forward_hook(lambda _m, _i, output: hooked.append(output))
            try:
                model.sample_actions(*inputs)
            finally:
                handle.remove()
            return hooked[-1][frame_of_row, positions]

        ours_s = median(repeat_timed(ours, device, warmup=1, repeats=ctx.sizes.repeats))
        seed_s = median(repeat_timed(seed, device, warmup=1, repeats=ctx.sizes.repeats))
        ours_fps, seed_fps = batch / ours_s, batch / seed_s
        section.figures.setdefault("capture_frames_per_s", {})[str(batch)] = ours_fps
        section.measure(f"ours frames/s, layer {layer}, batch {batch}", ours_fps,
                        f"seed {seed_fps:.3g} frames/s", ours_fps / seed_fps)
        section.measure(f"ours TFLOP/s (MFU), batch {batch}", ours_fps * ours_flops / 1e12,
                        f"peak {peak_flops / 1e12:.3g} TFLOP/s", ours_fps * ours_flops / peak_flops)
        section.measure(f"seed TFLOP/s (MFU), batch {batch}", seed_fps * seed_flops(arch, 1) / 1e12,
                        f"peak {peak_flops / 1e12:.3g} TFLOP/s", seed_fps * seed_flops(arch, 1) / peak_flops)
        section.comparisons.append(Comparison(f"capture rows vs seed, batch {batch}", "max row relative error",
                                              row_relative_error(ours(), seed()), tolerance(ctx.dtype)))
    section.notes.append(
        f"capture: {PROMPT_TOKENS}-token prompts in 200 slots, two cameras and the masked third, inputs on the "
        f"device; analytic FLOPs per frame (matrix products): ours {ours_flops / 1e9:.3g} G, the seed's "
        f"{seed_flops(arch, 1) / 1e9:.3g} G; medians of {ctx.sizes.repeats} calls after a warm-up.")
    return section


def policy_latency(policy: Pi05Policy, batches: tuple[int, ...], repeats: int, label: str) -> Section:
    """Time `sample_actions` at each batch size, and the GPU kernel time of the batch-1 call against its wall time.

    Takes any policy, so that eager and compiled builds of the same checkpoint can be measured alike.
    """
    section = Section()
    device = policy.device
    arch = policy.arch
    wall: dict[int, float] = {}
    calls: dict[int, Callable[[], torch.Tensor]] = {}
    for batch in batches:
        inputs, start = frames(arch, batch, device), noise(policy, batch)
        calls[batch] = lambda inputs=inputs, start=start: policy.sample_actions(*inputs, noise=start, num_steps=STEPS)
        wall[batch] = median(repeat_timed(calls[batch], device, warmup=1, repeats=repeats))
        section.figures.setdefault("sample_actions_ms", {})[str(batch)] = wall[batch] * 1e3
        section.measure(f"sample_actions ms, batch {batch} ({label})", wall[batch] * 1e3,
                        f"batch {batches[0]} x {batch}: {wall[batches[0]] * batch * 1e3:.4g} ms",
                        wall[batch] / (wall[batches[0]] * batch))
    kernel = kernel_seconds(calls[batches[0]], device)
    if kernel is None:
        section.measure(f"GPU kernel ms, batch 1 ({label})", "n/a (CPU)", f"wall {wall[batches[0]] * 1e3:.4g} ms")
    else:
        section.measure(f"GPU kernel ms, batch 1 ({label})", kernel * 1e3, f"wall {wall[batches[0]] * 1e3:.4g} ms",
                        kernel / wall[batches[0]])
    return section


def kernel_seconds(call: Callable[[], Any], device: torch.device) -> float | None:
    """Return the summed time of the CUDA kernels (and copies) one call launches, by torch.profiler; None on the CPU."""
    if device.type != "cuda":
        return None
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    call()  # warm: the profiled call launches what a steady call launches
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as profiler:
        timed(call, device)
    kernels = [event for event in profiler.events() if event.device_type == DeviceType.CUDA]
    return sum(event.time_range.elapsed_us() for event in kernels) / 1e6


def latency(ctx: Context) -> Section:
    """Load the policy; time sample_actions against batch size and its kernel time against wall time; then the
    batch-1 call of the other build (compiled denoising against eager), with its actions compared."""
    policy, load_seconds = ctx.policy()
    parameters = sum(p.numel() * p.element_size() for p in policy.parameters()) / 2**30
    build = "compiled" if policy.compiled else "eager"
    section = policy_latency(policy, ctx.sizes.latency_batches, ctx.sizes.repeats, f"as from_checkpoint builds it: {build}")
    section.measures.insert(0, {"measure": "from_checkpoint s", "value": load_seconds,
                                "against": f"{parameters:.3g} GiB of parameters", "ratio": ""})
    other = Pi05Policy(policy.prefix, policy.expert, policy.action_horizon, policy.tokenizer, policy.norm_stats_file,
                       compiled=not policy.compiled)  # the same weights
    mine, theirs = measure_latency(policy, 1, ctx.sizes.repeats), measure_latency(other, 1, ctx.sizes.repeats)
    compiled, eager = (mine, theirs) if policy.compiled else (theirs, mine)
    section.measure("sample_actions ms, batch 1, compiled denoising", compiled["median_ms"],
                    f"eager {eager['median_ms']:.4g} ms", compiled["median_ms"] / eager["median_ms"])
    section.measure("compiled batch-1 ms against the 40 ms target", compiled["median_ms"], "40 ms",
                    compiled["median_ms"] / BATCH1_TARGET_MS)
    section.measure("compilation s (warm-up, batch 1)", compiled["warm_up_s"], "paid once per process and batch size")
    section.comparisons.append(Comparison("compiled vs eager actions, batch 1", "relative error",
                                          relative_error(compiled["actions"], eager["actions"]), tolerance(ctx.dtype)))
    section.figures["compiled_batch1_ms"] = compiled["median_ms"]
    section.notes.append(f"latency: {STEPS} denoising steps, fixed noise, {PROMPT_TOKENS}-token prompts; "
                         "the ratio is the time against batch 1 times the batch (below 1: batching pays); kernel "
                         "time is the sum of the batch-1 call's CUDA kernels and copies (torch.profiler); the "
                         "compiled denoising step (default on CUDA) against eager on the same weights, its first "
                         "call (the compilation) timed apart.")
    return section


def sweep(ctx: Context) -> Section:
    """sample_actions_sweep of 8 steerings (CPU vectors) against 8 separate sample_actions calls."""
    section = Section()
    policy, _ = ctx.policy()
    inputs = frames(policy.arch, 1, ctx.device)
    start = noise(policy, 1)
    vector = random_vector(policy.arch.width, 1)
    entries = [Steering(ctx.sizes.layer, vector, alpha) for alpha in SWEEP_ALPHAS]

    def swept() -> torch.Tensor:
        return policy.sample_actions_sweep(*inputs, entries, noise=start, num_steps=STEPS)

    def separate() -> torch.Tensor:
        return torch.stack([policy.sample_actions(*inputs, noise=start, num_steps=STEPS, steering=e) for e in entries])

    sweep_s = median(repeat_timed(swept, ctx.device, warmup=1, repeats=ctx.sizes.repeats))
    separate_s = median(repeat_timed(separate, ctx.device, warmup=1, repeats=ctx.sizes.repeats))
    section.measure(f"sweep of {len(entries)} steerings s", sweep_s, f"{len(entries)} calls {separate_s:.3g} s",
                    sweep_s / separate_s)
    section.comparisons.append(Comparison("sweep vs separate calls", "relative error",
                                          relative_error(swept(), separate()), tolerance(ctx.dtype)))
    return section


def precision_outputs(policy: Pi05Policy, sae_dir: Path, batch: int) -> dict[str, torch.Tensor]:
    """Return the compared outputs of one policy, float32 on the CPU: actions unsteered, LM-steered,
    expert-steered and SAE-spliced, and the decision rows; steering vectors and masks start on the CPU."""
    from steering_core.capture.action_rows import decision_rows
    from steering_core.sae.model import load_sae

    arch = policy.arch
    layer = arch.depth * 2 // 3  # 12 of 18: the seed's layer
    inputs = frames(arch, batch, policy.device)
    start = noise(policy, batch)
    sae = load_sae(sae_dir, device=policy.device)
    mask = instruction_mask(batch)
    every_position = torch.ones(batch, arch.prefix_length(3, mask.shape[1]), dtype=torch.bool)  # on the CPU

    def actions(**kwargs: Any) -> torch.Tensor:
        return policy.sample_actions(*inputs, noise=start, num_steps=STEPS, **kwargs).float().cpu()

    expert_layer = policy.expert_arch.depth - 1
    rows = decision_rows(policy, *inputs, start, [expert_layer], STEPS)[expert_layer]
    return {
        "unsteered actions": actions(),
        "LM-steered actions": actions(steering=Steering(layer, random_vector(arch.width, 1), LM_ALPHA,
                                                        prefix_mask=every_position)),
        "expert-steered actions": actions(steering=Steering(expert_layer, random_vector(policy.expert_arch.width, 2),
                                                            1.0, stream="expert")),
        "SAE-spliced actions": actions(splice=Splice(layer, lambda x: sae.reconstruct(x)[0], token_mask=mask)),
        "decision rows": rows.float().cpu(),
    }


def precision(ctx: Context) -> Section:
    """float32 and bfloat16 on the device against float32 on the CPU at the mid-size model."""
    from steering_core.synthetic.sae import write_sae_folder

    section = Section()
    arch, batch = ctx.sizes.precision_arch, ctx.sizes.precision_batch
    checkpoint, _ = capture_throughput.model_files(ctx.folder / "precision", arch)
    sae_dir = ctx.folder / "precision" / f"sae-{arch.width}x{4 * arch.width}"
    if not sae_dir.is_dir():
        write_sae_folder(sae_dir, d_in=arch.width, d_sae=4 * arch.width)
    reference = precision_outputs(Pi05Policy.from_checkpoint(checkpoint, arch, device="cpu", dtype="float32"),
                                  sae_dir, batch)
    unsteered = reference["unsteered actions"]
    for dtype in (torch.float32, torch.bfloat16):
        name = str(dtype).removeprefix("torch.")
        with full_float32():
            policy = Pi05Policy.from_checkpoint(checkpoint, arch, device=ctx.device, dtype=dtype)
            got = precision_outputs(policy, sae_dir, batch)
        for case, want in reference.items():
            metric = "max row relative error" if case == "decision rows" else "relative error"
            error = (row_relative_error if case == "decision rows" else relative_error)(got[case], want)
            section.comparisons.append(Comparison(f"{name} {ctx.device.type} vs float32 cpu: {case}", metric, error,
                                                  tolerance(dtype)))
        for case in ("LM-steered actions", "expert-steered actions"):
            effect, want = got[case] - got["unsteered actions"], reference[case] - unsteered
            label = f"{name} {ctx.device.type} vs float32 cpu: effect of {case.split()[0]} steering"
            # the effect carries the rounding of both actions it is the difference of, each within the tolerance
            scale = float((reference[case].norm() + unsteered.norm()) / want.norm())
            section.comparisons.append(Comparison(label, "relative error", relative_error(effect, want),
                                                  tolerance(dtype) * scale))
            section.comparisons.append(Comparison(label, "1 - cosine", one_minus_cosine(effect, want),
                                                  tolerance(dtype)))
    effects = {case.split()[0]: relative_error(reference[case], unsteered)
               for case in ("LM-steered actions", "expert-steered actions", "SAE-spliced actions")}
    section.notes.append(
        f"precision: model width {arch.width} x {arch.depth} layers (SigLIP {arch.vision_width} x "
        f"{arch.vision_depth}, {arch.image_size} px), batch {batch}; TF32 off; LM steering (alpha {LM_ALPHA:g}, "
        f"every prefix position) and the SAE splice (instruction tokens) at LM layer {arch.depth * 2 // 3}, expert "
        "steering (alpha 1) at its last layer, vectors and masks on the CPU; each changes the float32 actions by "
        + ", ".join(f"{case} {value:.3g}" for case, value in effects.items())
        + " (relative), so an effect lost on the device fails its comparison.")
    return section


def saelens_installed() -> bool:
    """Return whether SAELens can be imported (the GPU machine may lack it)."""
    return importlib.util.find_spec("sae_lens") is not None


def torch_topk_step(batch: int, d_in: int, d_sae: int, k: int, device: torch.device) -> Callable[[], None]:
    """Return one TopK SAE training step in plain torch (used when SAELens is absent): encode, top-k, decode,
    squared error, backward, Adam."""
    generator = torch.Generator().manual_seed(0)
    parameters = [(torch.randn(*shape, generator=generator) / shape[0] ** 0.5).to(device).requires_grad_()
                  for shape in ((d_in, d_sae), (1, d_sae), (d_sae, d_in), (1, d_in))]
    w_enc, b_enc, w_dec, b_dec = parameters
    optimizer = torch.optim.Adam(parameters, lr=1e-4)
    x = torch.randn(batch, d_in, generator=generator).to(device)

    def step() -> None:
        pre = x @ w_enc + b_enc
        values, indices = pre.topk(k, dim=-1)
        latents = torch.zeros_like(pre).scatter(-1, indices, values.relu())
        loss = (latents @ w_dec + b_dec - x).pow(2).sum(-1).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return step


def sae(ctx: Context) -> Section:
    """SAE encode + decode against matmul of the same shapes; one training step against its matmul bound."""
    from steering_core.sae.model import load_sae
    from steering_core.synthetic.sae import write_sae_folder

    section = Section()
    d_in, d_sae, batch = ctx.sizes.sae
    device, repeats = ctx.device, 5 * ctx.sizes.repeats
    for architecture in SAE_ARCHITECTURES:
        folder = ctx.folder / f"sae-{architecture}-{d_in}x{d_sae}"
        if not folder.is_dir():
            write_sae_folder(folder, d_in=d_in, d_sae=d_sae, architecture=architecture, k=SAE_TOPK_K)
        calls = sae_encoding.references(load_sae(folder, device=device), batch, device)
        seconds = {name: median(repeat_timed(call, device, warmup=2, repeats=repeats)) for name, call in calls.items()}
        section.measure(f"{architecture} SAE encode + decode rows/s ({d_in} x {d_sae}, batch {batch})",
                        batch / seconds["reconstruct"], f"matmul {batch / seconds['matmul']:,.0f} rows/s",
                        seconds["matmul"] / seconds["reconstruct"])
    sizes = ctx.sizes.sae_training
    if saelens_installed():
        found = sae_training.measure(ctx.folder / "sae_training", sizes, device)
        step_s, bound_s, label = found["step_seconds"], found["bound_seconds"], "SAELens TopK step (train_sae)"
    else:
        step = torch_topk_step(sizes["batch_size"], sizes["d_in"], sizes["d_sae"], sizes["k"], device)
        bound = sae_training.matmul_bound(sizes["batch_size"], sizes["d_in"], sizes["d_sae"], device)
        step_s = median(repeat_timed(step, device, warmup=2, repeats=repeats))
        bound_s = median(repeat_timed(bound, device, warmup=2, repeats=repeats))
        label = "plain torch TopK step (SAELens not installed)"
        section.notes.append("sae: SAELens is not installed here; the training row times a plain torch TopK step "
                             "(encode, top-k, decode, squared error, backward, Adam), not the project's trainer.")
    section.measure(f"{label} ms ({sizes['d_in']} x {sizes['d_sae']}, k {sizes['k']}, batch {sizes['batch_size']})",
                    step_s * 1e3, f"five-product matmul bound {bound_s * 1e3:.3g} ms", bound_s / step_s)
    return section


@contextlib.contextmanager
def openpi_connection(port: int) -> Iterator[tuple[Callable[[dict], dict], str]]:
    """Yield (infer(observation) -> reply, the client's name): openpi-client's WebsocketClientPolicy when
    installed, else the same protocol with the project's codec (msgpack-numpy, metadata first)."""
    if importlib.util.find_spec("openpi_client") is not None:
        from openpi_client.websocket_client_policy import WebsocketClientPolicy

        client = WebsocketClientPolicy("127.0.0.1", port)
        try:
            yield client.infer, "openpi-client WebsocketClientPolicy"
        finally:
            client._ws.close()  # the client has no close(); an open connection would hold the server's shutdown
        return
    from websockets.sync.client import connect

    from steering_core.serve.codec import pack, unpack

    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
        ws.recv()  # the server's metadata

        def infer(observation: dict) -> dict:
            ws.send(pack(observation))
            return unpack(ws.recv())

        yield infer, "the project's codec (openpi-client not installed)"


def server(ctx: Context) -> Section:
    """A steered request (CPU vector, policy on the device) over loopback against a direct infer."""
    from steering_core.serve import PolicyServer, parse_steering
    from steering_core.serve.server import serving_in_thread

    section = Section()
    policy, _ = ctx.policy()
    served, catalog = serve_latency.steered(policy, ctx.checkpoint)
    observation = serve_latency.observation()
    entry = {"pair": serve_latency.PAIR, "layer": serve_latency.LAYER, "alpha": serve_latency.ALPHA,
             "alpha_units": "vector"}
    steering = parse_steering(entry, catalog)
    direct = served.infer(observation, steering)["actions"]  # also the warm-up
    plain = served.infer(observation, ())["actions"]
    direct_s = median(repeat_timed(lambda: served.infer(observation, steering), ctx.device, warmup=0,
                                   repeats=ctx.sizes.server_rounds))
    round_trips = []
    with serving_in_thread(PolicyServer(served, catalog, host="127.0.0.1", port=0)) as running, \
            openpi_connection(running.port) as (infer, client):
        for _ in range(ctx.sizes.server_rounds + 1):  # the first warms up
            start = time.perf_counter()
            remote = infer(observation | {"steering": entry})["actions"]
            round_trips.append(time.perf_counter() - start)
    trip_s = median(round_trips[1:])
    section.measure("steered round trip ms", trip_s * 1e3, f"direct infer {direct_s * 1e3:.3g} ms", trip_s / direct_s)
    remote_t, direct_t, plain_t = (torch.tensor(actions) for actions in (remote, direct, plain))
    section.comparisons.append(Comparison("served steered actions vs direct infer", "relative error",
                                          relative_error(remote_t, direct_t), tolerance(ctx.dtype)))
    change = relative_error(direct_t, plain_t)
    section.notes.append(f"server: client {client}; the vector ({serve_latency.PAIR}, layer {serve_latency.LAYER}, "
                         f"alpha {serve_latency.ALPHA}) is on the CPU and the policy on {ctx.device}; steering "
                         f"changes the actions by {change:.3g} (relative); served == direct bit for bit: "
                         f"{remote.tobytes() == direct.tobytes()}.")
    return section


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
