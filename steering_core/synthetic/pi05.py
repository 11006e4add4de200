"""A random pi0.5 checkpoint folder in openpi's exact PyTorch layout, at any (tiny) size.

Holds every tensor a converted openpi checkpoint has (spec 1.2), including the action expert, its dead
lm_head and the action/time heads, which the prefix loader must never read; plus `config.json` and
`assets/<asset_id>/norm_stats.json`.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import torch

from steering_core.pi05.arch import ExpertArch, Pi05Arch
from steering_core.pi05.checkpoint import (
    CONFIG_FILE,
    EXPERT_PREFIX,
    LM_PREFIX,
    MODEL_FILE,
    Shape,
    expert_tensor_shapes,
    prefix_tensor_shapes,
)
from steering_core.pi05.norm_stats import ASSETS_DIR, LIBERO_ASSET_ID, NORM_STATS_FILE
from steering_core.storage.fileio import atomic_dir
from steering_core.tensor_files import safetensors_layout

ACTION_DIM = 32  # pi0.5 pads actions and state to 32
ACTION_HORIZON = 10  # pi05_libero
LIBERO_STATE_DIM = 8  # eef position 3, axis-angle 3, gripper qpos 2
LIBERO_ACTION_DIM = 7
GENERATE_VALUES = 1 << 24  # values per generated block (64 MiB of float32 noise)


def tiny_arch(vocab_size: int = 512) -> Pi05Arch:
    """Return a tiny Pi05Arch: openpi's "dummy" Gemma (64 wide, 8 heads of 16) and a 2-layer 32-wide SigLIP."""
    return Pi05Arch(
        width=64,
        depth=4,
        mlp_dim=128,
        num_heads=8,
        num_kv_heads=1,
        head_dim=16,
        vocab_size=vocab_size,
        vision_width=32,
        vision_depth=2,
        vision_mlp_dim=64,
        vision_heads=2,
        patch_size=14,
        image_size=28,  # 2 x 2 patches: 4 tokens per image
    )


def tiny_expert_arch(arch: Pi05Arch, action_dim: int = ACTION_DIM) -> ExpertArch:
    """Return the expert that pairs with `arch` the way gemma_300m pairs with gemma_2b: half the width, a
    quarter of the MLP, the same depth and attention layout."""
    return ExpertArch(
        width=arch.width // 2, depth=arch.depth, mlp_dim=arch.mlp_dim // 4, num_heads=arch.num_heads,
        num_kv_heads=arch.num_kv_heads, head_dim=arch.head_dim, action_dim=action_dim,
    )


def checkpoint_tensor_shapes(arch: Pi05Arch, expert: ExpertArch | None = None) -> dict[str, Shape]:
    """Return name -> shape of a whole converted pi0.5 checkpoint (812 tensors at the real size).

    Includes the two tensors no inference reads: the language model's final norm and the expert's lm_head.
    """
    expert = expert or (ExpertArch() if arch == Pi05Arch() else tiny_expert_arch(arch))
    shapes = prefix_tensor_shapes(arch, arch.depth - 1)
    shapes[LM_PREFIX + "norm.weight"] = (arch.width,)
    shapes.update(expert_tensor_shapes(expert))
    shapes[EXPERT_PREFIX + "lm_head.weight"] = (arch.vocab_size, expert.width)
    return shapes


def _random_tensor(name: str, shape: Shape, generator: torch.Generator) -> torch.Tensor:
    """Return a float32 tensor with a scale that keeps activations O(1) through the tiny model."""
    noise = torch.randn(shape, generator=generator)
    if name.endswith(("layernorm.weight", "layer_norm1.weight", "layer_norm2.weight")) and "language_model" not in name:
        return 1.0 + 0.1 * noise  # SigLIP LayerNorm scale
    if name.endswith("layernorm.weight") or name.endswith("norm.weight"):
        return 0.1 * noise  # Gemma RMSNorm scales by (1 + w)
    if name.endswith("lm_head.weight"):
        return noise / math.sqrt(shape[1])  # embedding rows are scaled by sqrt(width) at run time
    if name.endswith("position_embedding.weight"):
        return 0.5 * noise
    if len(shape) == 1:
        return 0.05 * noise  # biases
    fan_in = math.prod(shape[1:])
    return noise / math.sqrt(fan_in)


def random_norm_stats(seed: int = 0) -> dict:
    """Return a plausible LIBERO norm_stats.json payload: state (8) and actions (7), q01 < mean < q99."""
    rng = np.random.default_rng(seed)
    stats = {}
    for name, dim in (("state", LIBERO_STATE_DIM), ("actions", LIBERO_ACTION_DIM)):
        mean = rng.normal(0.0, 0.5, dim)
        std = rng.uniform(0.05, 0.5, dim)
        stats[name] = {
            "mean": mean.tolist(),
            "std": std.tolist(),
            "q01": (mean - 2.3 * std).tolist(),
            "q99": (mean + 2.3 * std).tolist(),
        }
    return {"norm_stats": stats}


def _variant(width: int, real_width: int, real_name: str) -> str:
    """Return openpi's variant name for a Gemma of `width`: the real one at full size, else "dummy"."""
    return real_name if width == real_width else "dummy"


def write_pi05_checkpoint(
    folder: str | os.PathLike,
    arch: Pi05Arch,
    *,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    asset_id: str = LIBERO_ASSET_ID,
    overwrite: bool = False,
) -> Path:
    """Write a random pi0.5 checkpoint folder (model.safetensors, config.json, norm stats); return it.

    `dtype` is the storage dtype of every tensor (float32, or bfloat16 like openpi's converter default).
    Tensors are generated and written in blocks of at most GENERATE_VALUES values straight to their place
    in the file, so any size, the real one included (7.2 GB in bfloat16), is written in bounded memory.
    A tensor that fits one block gets the values of one `torch.randn` call, and the file is the one
    safetensors' `save_file` would write.
    """
    shapes = checkpoint_tensor_shapes(arch)
    config = {
        "action_dim": ACTION_DIM,
        "action_horizon": ACTION_HORIZON,
        "paligemma_variant": _variant(arch.width, Pi05Arch().width, "gemma_2b"),
        "action_expert_variant": _variant(arch.width, Pi05Arch().width, "gemma_300m"),
        "precision": "bfloat16" if dtype == torch.bfloat16 else "float32",
    }
    folder = Path(folder)
    with atomic_dir(folder, overwrite=overwrite) as tmp:
        stats_dir = tmp / ASSETS_DIR / asset_id
        stats_dir.mkdir(parents=True)
        _write_random_tensors(tmp / MODEL_FILE, shapes, dtype, torch.Generator().manual_seed(seed))
        (tmp / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n", encoding="utf-8")
        (stats_dir / NORM_STATS_FILE).write_text(json.dumps(random_norm_stats(seed), indent=2) + "\n", encoding="utf-8")
    return folder


def _write_random_tensors(
    path: Path, shapes: dict[str, Shape], dtype: torch.dtype, generator: torch.Generator
) -> None:
    """Write a safetensors file of random tensors (`_random_tensor`) block by block, in `shapes` order."""
    header, offsets = safetensors_layout({name: (dtype, shape) for name, shape in shapes.items()}, {"format": "pt"})
    with open(path, "wb", buffering=0) as handle:
        handle.write(header)
        for name, shape in shapes.items():
            rows = shape[0] if shape else 1
            per_block = max(1, GENERATE_VALUES // max(math.prod(shape[1:]), 1))
            for first in range(0, rows, per_block):
                block_shape = (min(per_block, rows - first), *shape[1:]) if shape else shape
                block = _random_tensor(name, block_shape, generator).to(dtype)
                row_bytes = math.prod(shape[1:]) * dtype.itemsize
                os.pwrite(handle.fileno(), block.reshape(-1).view(torch.uint8).numpy(), offsets[name] + first * row_bytes)
