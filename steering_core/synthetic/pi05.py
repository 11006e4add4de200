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
from safetensors.torch import save_file

from steering_core.fileio import atomic_dir
from steering_core.pi05.arch import Pi05Arch
from steering_core.pi05.checkpoint import (
    CONFIG_FILE,
    EXPERT_PREFIX,
    LM_PREFIX,
    MODEL_FILE,
    Shape,
    prefix_tensor_shapes,
)
from steering_core.pi05.norm_stats import ASSETS_DIR, LIBERO_ASSET_ID, NORM_STATS_FILE

ACTION_DIM = 32  # pi0.5 pads actions and state to 32
ACTION_HORIZON = 10  # pi05_libero
LIBERO_STATE_DIM = 8  # eef position 3, axis-angle 3, gripper qpos 2
LIBERO_ACTION_DIM = 7


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


def expert_tensor_shapes(arch: Pi05Arch, action_dim: int = ACTION_DIM) -> dict[str, Shape]:
    """Return name -> shape of the action expert, its adaRMS norms and lm_head, and the pi0.5 heads.

    The expert is half as wide as the language model with a quarter of its MLP (gemma_300m: 1024, 4096)
    and shares its heads and head_dim, so its queries are as wide as the LM's (spec 1.2).
    """
    width, mlp = arch.width // 2, arch.mlp_dim // 4
    q, kv = arch.num_heads * arch.head_dim, arch.num_kv_heads * arch.head_dim
    shapes: dict[str, Shape] = {
        EXPERT_PREFIX + "model.norm.dense.weight": (3 * width, width),
        EXPERT_PREFIX + "model.norm.dense.bias": (3 * width,),
        EXPERT_PREFIX + "lm_head.weight": (arch.vocab_size, width),
        "action_in_proj.weight": (width, action_dim),
        "action_in_proj.bias": (width,),
        "action_out_proj.weight": (action_dim, width),
        "action_out_proj.bias": (action_dim,),
        "time_mlp_in.weight": (width, width),
        "time_mlp_in.bias": (width,),
        "time_mlp_out.weight": (width, width),
        "time_mlp_out.bias": (width,),
    }
    for layer in range(arch.depth):
        prefix = f"{EXPERT_PREFIX}model.layers.{layer}."
        shapes.update({
            prefix + "self_attn.q_proj.weight": (q, width),
            prefix + "self_attn.k_proj.weight": (kv, width),
            prefix + "self_attn.v_proj.weight": (kv, width),
            prefix + "self_attn.o_proj.weight": (width, q),
            prefix + "mlp.gate_proj.weight": (mlp, width),
            prefix + "mlp.up_proj.weight": (mlp, width),
            prefix + "mlp.down_proj.weight": (width, mlp),
        })
        for norm in ("input_layernorm", "post_attention_layernorm"):
            shapes[f"{prefix}{norm}.dense.weight"] = (3 * width, width)
            shapes[f"{prefix}{norm}.dense.bias"] = (3 * width,)
    return shapes


def checkpoint_tensor_shapes(arch: Pi05Arch, action_dim: int = ACTION_DIM) -> dict[str, Shape]:
    """Return name -> shape of a whole converted pi0.5 checkpoint (812 tensors at the real size)."""
    shapes = prefix_tensor_shapes(arch, arch.depth - 1)
    shapes[LM_PREFIX + "norm.weight"] = (arch.width,)
    shapes.update(expert_tensor_shapes(arch, action_dim))
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
    """
    generator = torch.Generator().manual_seed(seed)
    tensors = {
        name: _random_tensor(name, shape, generator).to(dtype)
        for name, shape in checkpoint_tensor_shapes(arch).items()
    }
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
        save_file(tensors, str(tmp / MODEL_FILE), metadata={"format": "pt"})
        (tmp / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n", encoding="utf-8")
        (stats_dir / NORM_STATS_FILE).write_text(json.dumps(random_norm_stats(seed), indent=2) + "\n", encoding="utf-8")
    return folder
