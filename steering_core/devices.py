"""Devices, dtypes and cores: one definition of how a device or dtype name becomes a torch object, and of the cores a
process may use."""

from __future__ import annotations

import functools
import os

import torch

# Floating-point dtypes by the names configs and CLI flags use.
DTYPES: dict[str, torch.dtype] = {
    "float32": torch.float32,
    "float64": torch.float64,
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
}
# safetensors header dtype names of the same dtypes.
SAFETENSORS_DTYPES: dict[str, torch.dtype] = {"F32": torch.float32, "F64": torch.float64, "F16": torch.float16,
                                              "BF16": torch.bfloat16}
DTYPE_NAMES: dict[torch.dtype, str] = {dtype: name for name, dtype in DTYPES.items()}
DEVICE_HELP = "auto (CUDA when available), cuda, cuda:1, cpu, or mps or xpu where torch has them."  # what a device setting accepts
ACCELERATORS = {"cuda": "CUDA", "mps": "MPS", "xpu": "XPU"}  # device types besides cpu, used only where torch finds them


def parse_device(device: str | torch.device) -> torch.device:
    """Return the torch device named `device`; a name torch does not know is a ValueError."""
    try:
        return torch.device(device)
    except RuntimeError as error:
        raise ValueError(f"device {device!r} is not a torch device; expected cpu, cuda, cuda:N or auto") from error


def usable_cores() -> int:
    """Return the cores this process may run on (its CPU affinity)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@functools.cache
def fix_cpu_threads() -> None:
    """Keep this process's CPU thread count fixed, once: the same inputs then give the same float32 bits however
    busy the machine is.

    oneMKL's default (MKL_DYNAMIC=TRUE) lets it run a gemm on fewer threads than asked, and the thread count
    changes how sums split, so the last bits of float32 results. `torch.set_num_threads` turns that off (at the
    count torch already chose). The count itself still differs between machines of other core counts.
    """
    torch.set_num_threads(torch.get_num_threads())


def resolve_device(device: str | torch.device | None) -> torch.device:
    """Return `device`; None or "auto" picks CUDA when available, else CPU. An accelerator (CUDA, MPS, XPU) this
    machine does not have, or an index beyond its count, is an error, as is any other device type.

    Every step that computes resolves its device first, so this also fixes the CPU threads (`fix_cpu_threads`).
    """
    fix_cpu_threads()
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    resolved = parse_device(device)
    if resolved.type == "cpu":
        return resolved
    if resolved.type not in ACCELERATORS:
        raise ValueError(f"device {device!r}: expected cpu, auto or one of {', '.join(ACCELERATORS)} (with an index)")
    backend = getattr(torch, resolved.type)
    if not backend.is_available():
        raise ValueError(f"device {device!r} requested but {ACCELERATORS[resolved.type]} is not available here (torch "
                         f"{torch.__version__}); use --device cpu or auto")
    count = backend.device_count()
    if resolved.index is not None and resolved.index >= count:
        raise ValueError(f"device {device!r} requested but this machine has {count} {ACCELERATORS[resolved.type]} device(s) "
                         f"(0..{count - 1}); use one of them, or --device cpu or auto")
    return resolved


def resolve_dtype(dtype: str | torch.dtype | None, device: torch.device) -> torch.dtype:
    """Return the compute dtype: `dtype`, or openpi's bfloat16 on CUDA and float32 elsewhere."""
    if dtype is None:
        return torch.bfloat16 if device.type == "cuda" else torch.float32
    resolved = DTYPES.get(dtype) if isinstance(dtype, str) else dtype
    if not isinstance(resolved, torch.dtype) or not resolved.is_floating_point:
        raise ValueError(f"dtype {dtype!r} is not a floating-point dtype; expected one of {sorted(DTYPES)}")
    return resolved
