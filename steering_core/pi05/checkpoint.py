"""openpi PyTorch pi0.5 checkpoints: parameter names, expected shapes and lazy, validated reading.

Only the prefix is ever read: the SigLIP tower, the projector, the token embedding and language-model
layers 0..max_layer. The action expert, later layers, the final norm and the heads stay on disk.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from tqdm.auto import tqdm

from steering_core.fileio import read_json
from steering_core.pi05.arch import Pi05Arch
from steering_core.tensor_files import check_safetensors

logger = logging.getLogger(__name__)

MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"

# Name prefixes of openpi's module tree (spec 1.2), concatenated directly with the suffixes below.
PALIGEMMA = "paligemma_with_expert.paligemma."
VISION_PREFIX = PALIGEMMA + "model.vision_tower.vision_model."
PROJECTOR_PREFIX = PALIGEMMA + "model.multi_modal_projector."
LM_PREFIX = PALIGEMMA + "model.language_model."
EXPERT_PREFIX = "paligemma_with_expert.gemma_expert."
# The embedding table is tied to PaliGemma's lm_head; safetensors keeps only the alphabetically first
# name of a shared group, so the file stores it as lm_head.weight and has no embed_tokens (spec 1.3).
EMBEDDING_KEY = PALIGEMMA + "lm_head.weight"

_FLOAT_DTYPES = {"BF16", "F16", "F32", "F64"}  # a converted file is uniform, a training file mixed (spec 1.4)

Shape = tuple[int, ...]


def resolve_model_file(path: str | os.PathLike) -> Path:
    """Return the `model.safetensors` of a checkpoint folder, or `path` itself if it is that file."""
    path = Path(path)
    if path.is_dir():
        path = path / MODEL_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: pi0.5 checkpoint not found; pass a converted openpi PyTorch checkpoint folder "
            f"(holding {MODEL_FILE}) or the .safetensors file itself"
        )
    return path


def read_checkpoint_config(model_file: Path) -> dict[str, Any] | None:
    """Return the checkpoint's `config.json` beside `model_file` (action_dim, variants, precision), if any."""
    config_file = model_file.parent / CONFIG_FILE
    if not config_file.is_file():
        return None
    config = read_json(config_file)
    if not isinstance(config, dict):
        raise ValueError(f"{config_file}: expected a JSON object, found {type(config).__name__}")
    return config


def check_max_layer(arch: Pi05Arch, max_layer: int | None) -> int:
    """Return the deepest decoder layer to load: `max_layer`, or the last layer when None."""
    if max_layer is None:
        return arch.depth - 1
    if isinstance(max_layer, bool) or not isinstance(max_layer, int) or not 0 <= max_layer < arch.depth:
        raise ValueError(
            f"max_layer {max_layer!r} is out of range: the language model has {arch.depth} decoder layers "
            f"(0..{arch.depth - 1}); pass a layer in that range"
        )
    return max_layer


def vision_tensor_shapes(arch: Pi05Arch) -> dict[str, Shape]:
    """Return checkpoint name -> shape of the SigLIP tower and the projector."""
    w, m, lm = arch.vision_width, arch.vision_mlp_dim, arch.width
    shapes: dict[str, Shape] = {
        VISION_PREFIX + "embeddings.patch_embedding.weight": (w, 3, arch.patch_size, arch.patch_size),
        VISION_PREFIX + "embeddings.patch_embedding.bias": (w,),
        VISION_PREFIX + "embeddings.position_embedding.weight": (arch.tokens_per_image, w),
        VISION_PREFIX + "post_layernorm.weight": (w,),
        VISION_PREFIX + "post_layernorm.bias": (w,),
        PROJECTOR_PREFIX + "linear.weight": (lm, w),
        PROJECTOR_PREFIX + "linear.bias": (lm,),
    }
    for i in range(arch.vision_depth):
        layer = f"{VISION_PREFIX}encoder.layers.{i}."
        for norm in ("layer_norm1", "layer_norm2"):
            shapes[f"{layer}{norm}.weight"] = (w,)
            shapes[f"{layer}{norm}.bias"] = (w,)
        for proj in ("q_proj", "k_proj", "v_proj", "out_proj"):
            shapes[f"{layer}self_attn.{proj}.weight"] = (w, w)
            shapes[f"{layer}self_attn.{proj}.bias"] = (w,)
        shapes[f"{layer}mlp.fc1.weight"] = (m, w)
        shapes[f"{layer}mlp.fc1.bias"] = (m,)
        shapes[f"{layer}mlp.fc2.weight"] = (w, m)
        shapes[f"{layer}mlp.fc2.bias"] = (w,)
    return shapes


def decoder_layer_shapes(arch: Pi05Arch, layer: int) -> dict[str, Shape]:
    """Return checkpoint name -> shape of one PaliGemma language-model decoder layer (no biases)."""
    prefix = f"{LM_PREFIX}layers.{layer}."
    w, q, kv = arch.width, arch.num_heads * arch.head_dim, arch.num_kv_heads * arch.head_dim
    return {
        prefix + "self_attn.q_proj.weight": (q, w),
        prefix + "self_attn.k_proj.weight": (kv, w),
        prefix + "self_attn.v_proj.weight": (kv, w),
        prefix + "self_attn.o_proj.weight": (w, q),
        prefix + "mlp.gate_proj.weight": (arch.mlp_dim, w),
        prefix + "mlp.up_proj.weight": (arch.mlp_dim, w),
        prefix + "mlp.down_proj.weight": (w, arch.mlp_dim),
        prefix + "input_layernorm.weight": (w,),
        prefix + "post_attention_layernorm.weight": (w,),
    }


def prefix_tensor_shapes(arch: Pi05Arch, max_layer: int) -> dict[str, Shape]:
    """Return checkpoint name -> shape of every tensor the prefix up to decoder layer `max_layer` needs."""
    shapes = vision_tensor_shapes(arch)
    shapes[EMBEDDING_KEY] = (arch.vocab_size, arch.width)
    for layer in range(max_layer + 1):
        shapes.update(decoder_layer_shapes(arch, layer))
    return shapes


def _problems(handle: Any, expected: dict[str, Shape]) -> list[tuple[str, str, str]]:
    """Return sorted (name, found, expected) for every needed tensor that is missing or malformed."""
    stored = set(handle.keys())
    problems = []
    for name, shape in expected.items():
        if name not in stored:
            problems.append((name, "missing", str(shape)))
            continue
        header = handle.get_slice(name)
        found_shape, found_dtype = tuple(header.get_shape()), header.get_dtype()
        if found_shape != shape or found_dtype not in _FLOAT_DTYPES:
            problems.append((name, f"{found_shape} {found_dtype}", f"{shape} floating point"))
    return sorted(problems)


def check_prefix_layout(model_file: Path, arch: Pi05Arch, max_layer: int) -> None:
    """Raise one ValueError listing every prefix tensor (up to `max_layer`) missing or malformed in the header.

    Reads only the file's header: a file that is not safetensors is refused before the reader trusts it.
    """
    check_safetensors(model_file)
    expected = prefix_tensor_shapes(arch, max_layer)
    with safe_open(str(model_file), framework="pt", device="cpu") as handle:
        problems = _problems(handle, expected)
    if problems:
        lines = "\n".join(
            f"  {name}: {'' if found == 'missing' else 'found '}{found}, expected {want}"
            for name, found, want in problems
        )
        raise ValueError(
            f"{model_file}: {len(problems)} of {len(expected)} prefix tensors (up to decoder layer "
            f"{max_layer}) are missing or do not match {arch!r}:\n{lines}\n"
            "Pass the Pi05Arch this checkpoint was built with, or re-convert it with openpi's "
            "convert_jax_model_to_pytorch.py."
        )


def read_prefix_tensors(
    model_file: Path,
    arch: Pi05Arch,
    max_layer: int,
    convert: Callable[[str, torch.Tensor], torch.Tensor],
) -> dict[str, torch.Tensor]:
    """Return checkpoint name -> tensor for the prefix up to `max_layer`, read lazily and validated first.

    Every needed tensor's presence, shape and dtype is checked from the file header before any data is
    read (`check_prefix_layout`). `convert(name, tensor)` moves each tensor to its run-time device and
    dtype as soon as it is read, so peak memory is the converted prefix plus one stored tensor.
    """
    check_prefix_layout(model_file, arch, max_layer)
    expected = prefix_tensor_shapes(arch, max_layer)
    with safe_open(str(model_file), framework="pt", device="cpu") as handle:
        tensors = {}
        for name in tqdm(expected, desc="loading pi0.5 prefix", unit="tensor", leave=False, disable=None):
            tensors[name] = convert(name, handle.get_tensor(name))
    logger.info("%s: read %d prefix tensors (decoder layers 0..%d)", model_file, len(tensors), max_layer)
    return tensors
