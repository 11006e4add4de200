"""The GPU check's harness: its sizes, tolerances and error metrics, the records a section returns, and the run's
context every section takes (`bench.gpu_check` runs the sections; they live in `bench.gpu_policy_sections`,
`bench.gpu_matmul_sections` and `bench.gpu_render_section`)."""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench import capture_throughput, sae_training
from bench.common import cache_dir, median, repeat_timed
from bench.real_size import checkpoint_folder
from steering_core.devices import resolve_device, resolve_dtype
from steering_core.pi05 import Pi05Arch, Pi05Policy
from steering_core.pi05.arch import read_arch
from steering_core.pi05.layouts import Checkpoint, LayoutName, resolve_checkpoint
from steering_core.synthetic.pi05 import tiny_arch

# ----------------------------------------------------------------------------- settings

# Tolerances on relative errors (‖got − want‖ / ‖want‖; per row for residual rows; 1 − cosine for a
# steering's effect). float32 on CUDA computes what float32 on the CPU computes in another order: rounding
# alone, ~1e-6 (3e-7 on the first H200 run). bfloat16 keeps 8 significant bits (2^-9 = 0.2% per rounding),
# compounded over 18 layers and 10 Euler steps: the first H200 run saw 0.31% on actions and up to 1.1% per
# captured row; 3% leaves room for that while a real fault (a mask or a steering lost) is off by O(1).
TOLERANCES = {torch.float32: 1e-5, torch.bfloat16: 3e-2}


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
    render: dict[str, int]  # bench.rollout_throughput.step_rates's settings, per renderer


REAL = Sizes(matmul=8192, arch=Pi05Arch(), layer=12, capture_batches=(32, 128), latency_batches=(1, 4, 16, 64),
             precision_arch=capture_throughput.ARCH, precision_batch=2, sae=(2048, 16384, 512),
             sae_training={"d_in": sae_training.D_IN, "d_sae": sae_training.D_SAE, "k": sae_training.K,
                           "batch_size": sae_training.BATCH_SIZE, "steps": sae_training.STEPS,
                           "run_rows": sae_training.RUN_ROWS},
             repeats=5, server_rounds=20, render={"rounds": 2, "plain_steps": 50, "render_steps": 50})
QUICK = Sizes(matmul=512, arch=tiny_arch(), layer=2, capture_batches=(2, 4), latency_batches=(1, 4),
              precision_arch=tiny_arch(), precision_batch=2, sae=(64, 256, 128),
              sae_training={**sae_training.QUICK, "steps": 4}, repeats=2, server_rounds=3,
              render={"rounds": 1, "plain_steps": 5, "render_steps": 3})


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


def given_sizes(sizes: Sizes, arch: Pi05Arch) -> Sizes:
    """Return `sizes` for a given checkpoint of `arch`: its policy, and the layer two thirds deep (the seed's 12 of
    18, 2 of the tiny model's 4) captured and steered."""
    return dataclasses.replace(sizes, arch=arch, layer=arch.depth * 2 // 3)


class Context:
    """The run's device, sizes and generated inputs; the real-size policy loaded once for the sections using it.

    The policy sections read `checkpoint` (with `layout`) and `tokenizer`: the random checkpoint generated into the
    cache (`write_checkpoint`), or the user's checkpoint given with --checkpoint (`given` is then its resolved
    `Checkpoint`, and `sizes.arch` the --arch-file's dimensions).
    """

    def __init__(self, args: argparse.Namespace) -> None:
        self.device = resolve_device(args.device)
        self.sizes = QUICK if args.quick else REAL
        self.folder = cache_dir(args) / "gpu_check"
        self.given: Checkpoint | None = None
        self.layout = LayoutName.AUTO
        if getattr(args, "checkpoint", None) is None:
            self.checkpoint = checkpoint_folder(args)  # shared with bench.real_size and bench.policy_real_size
            self.tokenizer = self.checkpoint.parent / "pi05-tokenizer.model"
        else:
            self.layout = LayoutName(args.layout)
            self.given = resolve_checkpoint(args.checkpoint, self.layout)  # refuses a folder of the wrong layout
            self.checkpoint, self.tokenizer = Path(args.checkpoint), Path(args.tokenizer)
            arch = self.sizes.arch if args.arch_file is None else read_arch(args.arch_file)
            self.sizes = given_sizes(self.sizes, arch)
        self._peak: float | None = None
        self._policy: tuple[Pi05Policy, float] | None = None

    @property
    def dtype(self) -> torch.dtype:
        """Return the policy's compute dtype on this device (as `from_checkpoint` picks it)."""
        return resolve_dtype(None, self.device)

    def write_checkpoint(self) -> None:
        """Write the random bf16 checkpoint and the tokenizer unless cached (nothing when one was given)."""
        from steering_core.synthetic.pi05 import write_pi05_checkpoint
        from steering_core.synthetic.tokenizer import write_tokenizer

        if self.given is not None:
            return
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
                                                tokenizer_path=self.tokenizer, layout=self.layout)
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

