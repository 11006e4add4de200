"""pi0.5 checkpoints: parameter names, expected shapes and lazy, validated reading, in either layout.

Every tensor is named by openpi's key (the canonical name, spec 1.2); `steering_core.pi05.layouts.Checkpoint`
maps it to the name its file stores (lerobot prefixes `model.` and embeds with `embed_tokens`). The prefix (SigLIP
tower, projector, token embedding, language-model layers 0..max_layer) and the action expert with its heads are
read separately, each after checking its names and shapes in the file header. The language model's final norm,
lerobot's unused `lm_head` and the expert's lm_head are never read: no output depends on them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from typing import Any

import torch
from safetensors import safe_open
from tqdm.auto import tqdm

from steering_core.pi05.arch import ExpertArch, Pi05Arch
from steering_core.pi05.layouts import (
    CONFIG_FILE,
    EMBEDDING_KEY,
    LM_PREFIX,
    MODEL_FILE,
    PALIGEMMA,
    Checkpoint,
    resolve_checkpoint,
    resolve_model_file,
)
from steering_core.tensor_files import (
    check_safetensors,
    read_tensor,
    require_finite,
    require_finite_file,
    staging_buffer,
    tensor_locations,
)

logger = logging.getLogger(__name__)

__all__ = ["CONFIG_FILE", "MODEL_FILE", "Checkpoint", "resolve_checkpoint", "resolve_model_file"]

# Name prefixes of openpi's module tree (spec 1.2), concatenated directly with the suffixes below.
VISION_PREFIX = PALIGEMMA + "model.vision_tower.vision_model."
PROJECTOR_PREFIX = PALIGEMMA + "model.multi_modal_projector."
EXPERT_PREFIX = "paligemma_with_expert.gemma_expert."
EXPERT_LAYERS = EXPERT_PREFIX + "model.layers."
ACTION_IN_KEY = "action_in_proj.weight"  # (expert width, action_dim): its presence marks a full checkpoint
HEADS = ("action_in_proj", "action_out_proj", "time_mlp_in", "time_mlp_out")
ADARMS_NORMS = ("input_layernorm", "post_attention_layernorm")

CHECKPOINT_FIX = "the checkpoint is damaged; re-download or re-convert it"
_FLOAT_DTYPES = {"BF16", "F16", "F32", "F64"}  # a converted file is uniform, a training file mixed (spec 1.4)

Shape = tuple[int, ...]
Placement = Callable[[str], tuple[torch.device, torch.dtype]]  # canonical name -> run-time (device, dtype)


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


def header_depths(checkpoint: Checkpoint) -> dict[str, int]:
    """Return the layers the file's header holds, by stack: `lm` (decoder layers 0..n-1 present), `vision` (SigLIP
    encoder layers) and `expert` (action expert layers); names only, no tensor read."""
    stacks = {"lm": LM_PREFIX + "layers.", "vision": VISION_PREFIX + "encoder.layers.", "expert": EXPERT_LAYERS}
    found: dict[str, set[str]] = {stack: set() for stack in stacks}
    for name in check_safetensors(checkpoint.model_file):
        canonical = checkpoint.canonical(name)
        for stack, prefix in stacks.items():
            if canonical.startswith(prefix):
                found[stack].add(canonical[len(prefix):].split(".")[0])
    return {stack: len(indices) for stack, indices in found.items()}


def check_depths(checkpoint: Checkpoint, arch: Pi05Arch, max_layer: int) -> None:
    """Raise unless the arch's depths agree with the layers in the file's header, before anything is built from
    them: SigLIP's `vision_depth` is the file's (the whole tower is read), decoder layer `max_layer` is in the file,
    and `depth` is the action expert's layer count where the file holds one (pi0.5 pairs them layer by layer)."""
    held = header_depths(checkpoint)
    problems = []
    if arch.vision_depth != held["vision"]:
        problems.append(f"vision_depth {arch.vision_depth}, but it holds {held['vision']} SigLIP encoder layers")
    if held["expert"] and arch.depth != held["expert"]:
        problems.append(f"depth {arch.depth}, but it holds {held['expert']} action expert layers (one per "
                        "language-model layer)")
    elif max_layer >= held["lm"]:
        problems.append(f"decoder layers up to {max_layer} (depth {arch.depth}), but it holds {held['lm']}")
    if problems:
        raise ValueError(f"{checkpoint.model_file}: the Pi05Arch asks for " + "; ".join(problems) + " (header); "
                         "pass the Pi05Arch this checkpoint was built with (model.arch, --arch-file)")


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


def _problems(handle: Any, checkpoint: Checkpoint, expected: dict[str, Shape]) -> list[tuple[str, str, str]]:
    """Return sorted (stored name, found, expected) for every needed tensor that is missing or malformed."""
    stored = set(handle.keys())
    problems = []
    for canonical, shape in expected.items():
        name = checkpoint.stored(canonical)
        if name not in stored:
            problems.append((name, "missing", str(shape)))
            continue
        header = handle.get_slice(name)
        found_shape, found_dtype = tuple(header.get_shape()), header.get_dtype()
        if found_shape != shape or found_dtype not in _FLOAT_DTYPES:
            problems.append((name, f"{found_shape} {found_dtype}", f"{shape} floating point"))
    return sorted(problems)


def expert_tensor_shapes(expert: ExpertArch) -> dict[str, Shape]:
    """Return checkpoint name -> shape of the action expert, its adaRMS norms and the four pi0.5 heads.

    adaRMS norms have no scale weight: a dense map of the time conditioning gives scale, shift and gate
    (3 x width rows, spec 10.2). The expert's dead lm_head is not listed.
    """
    w, mlp, a = expert.width, expert.mlp_dim, expert.action_dim
    q, kv = expert.num_heads * expert.head_dim, expert.num_kv_heads * expert.head_dim
    shapes: dict[str, Shape] = {
        EXPERT_PREFIX + "model.norm.dense.weight": (3 * w, w),
        EXPERT_PREFIX + "model.norm.dense.bias": (3 * w,),
        "action_in_proj.weight": (w, a),
        "action_in_proj.bias": (w,),
        "action_out_proj.weight": (a, w),
        "action_out_proj.bias": (a,),
        "time_mlp_in.weight": (w, w),
        "time_mlp_in.bias": (w,),
        "time_mlp_out.weight": (w, w),
        "time_mlp_out.bias": (w,),
    }
    for layer in range(expert.depth):
        prefix = f"{EXPERT_LAYERS}{layer}."
        shapes.update({
            prefix + "self_attn.q_proj.weight": (q, w),
            prefix + "self_attn.k_proj.weight": (kv, w),
            prefix + "self_attn.v_proj.weight": (kv, w),
            prefix + "self_attn.o_proj.weight": (w, q),
            prefix + "mlp.gate_proj.weight": (mlp, w),
            prefix + "mlp.up_proj.weight": (mlp, w),
            prefix + "mlp.down_proj.weight": (w, mlp),
        })
        for norm in ADARMS_NORMS:
            shapes[f"{prefix}{norm}.dense.weight"] = (3 * w, w)
            shapes[f"{prefix}{norm}.dense.bias"] = (3 * w,)
    return shapes


def expert_arch_from_checkpoint(checkpoint: Checkpoint, arch: Pi05Arch) -> ExpertArch:
    """Return the expert's dimensions: gemma_300m beside the real language model, else read from the header.

    Width and action_dim come from `action_in_proj`, the MLP size from layer 0, the depth from the layer
    names; heads and head_dim are the language model's (the two must pair, `ExpertArch.check_pairs_with`).
    """
    if arch == Pi05Arch():
        return ExpertArch()
    check_depths(checkpoint, arch, arch.depth - 1)
    with safe_open(str(checkpoint.model_file), framework="pt", device="cpu") as handle:
        names = {checkpoint.canonical(name) for name in handle.keys()}
        if ACTION_IN_KEY not in names:
            raise ValueError(
                f"{checkpoint.model_file}: no action expert ({checkpoint.stored(ACTION_IN_KEY)} missing): this looks "
                "like a prefix-only checkpoint; sampling actions needs the whole pi0.5 checkpoint"
            )
        width, action_dim = handle.get_slice(checkpoint.stored(ACTION_IN_KEY)).get_shape()
        gate = f"{EXPERT_LAYERS}0.mlp.gate_proj.weight"
        mlp_dim = handle.get_slice(checkpoint.stored(gate)).get_shape()[0] if gate in names else 1
    depth = len({name[len(EXPERT_LAYERS) :].split(".")[0] for name in names if name.startswith(EXPERT_LAYERS)})
    return ExpertArch(
        width=width, depth=max(depth, 1), mlp_dim=mlp_dim, num_heads=arch.num_heads,
        num_kv_heads=arch.num_kv_heads, head_dim=arch.head_dim, action_dim=action_dim,
    )


def check_tensors(checkpoint: Checkpoint, expected: dict[str, Shape], what: str, hint: str) -> None:
    """Raise one ValueError listing every tensor of `expected` that is missing or malformed in the header.

    `expected` is keyed by canonical names; the message names the stored ones. `what` names the part ("action
    expert tensors"), `hint` says how to fix it. A file that is not safetensors is refused before the reader trusts
    its header length.
    """
    model_file = checkpoint.model_file
    check_safetensors(model_file)
    with safe_open(str(model_file), framework="pt", device="cpu") as handle:
        problems = _problems(handle, checkpoint, expected)
    if problems:
        lines = "\n".join(
            f"  {name}: {'' if found == 'missing' else 'found '}{found}, expected {want}"
            for name, found, want in problems
        )
        raise ValueError(
            f"{model_file}: {len(problems)} of {len(expected)} {what} are missing or do not match (the file is in "
            f"{checkpoint.layout.name.value}'s layout):\n{lines}\n{hint}"
        )


def read_tensors(
    checkpoint: Checkpoint,
    expected: dict[str, Shape],
    placement: Placement,
    what: str,
    hint: str,
) -> dict[str, torch.Tensor]:
    """Return canonical name -> tensor for the names of `expected`, read after `check_tensors`.

    `placement(name)` gives each tensor's run-time (device, dtype). Each tensor is allocated there and
    filled by plain file reads (`steering_core.tensor_files`): no memory map keeps the file's pages resident,
    and converted tensors pass through one staging buffer of 16 MiB, so peak memory is the converted
    tensors plus that buffer.
    """
    check_tensors(checkpoint, expected, what, hint)
    model_file = checkpoint.model_file
    locations = tensor_locations(model_file)
    staging = staging_buffer()  # one buffer for every converted tensor: no allocator churn
    tensors = {}
    with open(model_file, "rb", buffering=0) as handle:
        for name in tqdm(expected, desc="loading pi0.5 tensors", unit="tensor", leave=False, disable=None):
            device, dtype = placement(name)
            stored = checkpoint.stored(name)
            tensors[name] = read_tensor(handle, locations[stored], device, dtype, staging)
            require_finite(tensors[name], model_file, stored, CHECKPOINT_FIX)
    logger.info("%s: read %d %s", checkpoint.describe, len(tensors), what)
    return tensors


def check_finite(checkpoint: Checkpoint, names: Iterable[str]) -> None:
    """Raise naming the file and tensor unless every tensor of canonical `names` is finite (read in chunks)."""
    names = [checkpoint.stored(name) for name in names]
    logger.info("%s: checking %d tensors for NaN and Inf", checkpoint.model_file, len(names))
    require_finite_file(checkpoint.model_file, names, CHECKPOINT_FIX)


def _prefix_what_hint(arch: Pi05Arch, max_layer: int) -> tuple[str, str]:
    """Return how prefix tensor problems are named and fixed."""
    return (f"prefix tensors (up to decoder layer {max_layer})",
            f"They do not match {arch!r}. Pass the Pi05Arch this checkpoint was built with (its tensors' shapes, "
            "whatever config.json's variant names say).")


def check_prefix_layout(checkpoint: Checkpoint, arch: Pi05Arch, max_layer: int) -> None:
    """Raise unless the file holds every prefix tensor up to `max_layer` with the arch's shapes (header only)."""
    check_depths(checkpoint, arch, max_layer)
    check_tensors(checkpoint, prefix_tensor_shapes(arch, max_layer), *_prefix_what_hint(arch, max_layer))


def read_prefix_tensors(
    checkpoint: Checkpoint,
    arch: Pi05Arch,
    max_layer: int,
    placement: Placement,
) -> dict[str, torch.Tensor]:
    """Return canonical name -> tensor for the prefix up to `max_layer` (`read_tensors`; `check_depths` first)."""
    return read_tensors(checkpoint, prefix_tensor_shapes(arch, max_layer), placement, *_prefix_what_hint(arch, max_layer))


EXPERT_WHAT = "action expert tensors"


def expert_hint(expert: ExpertArch) -> str:
    """Return how to fix an expert that does not match the file."""
    return (
        f"They do not match {expert!r}. Sampling actions needs the whole pi0.5 checkpoint "
        "(a prefix-only file has no expert)."
    )


def check_expert_tensors(checkpoint: Checkpoint, expert: ExpertArch) -> None:
    """Raise unless the file holds the action expert and heads of `expert` (header only, no data read)."""
    check_tensors(checkpoint, expert_tensor_shapes(expert), EXPERT_WHAT, expert_hint(expert))


def read_expert_tensors(
    checkpoint: Checkpoint,
    expert: ExpertArch,
    placement: Placement,
) -> dict[str, torch.Tensor]:
    """Return canonical name -> tensor for the action expert and the heads (`read_tensors`)."""
    return read_tensors(checkpoint, expert_tensor_shapes(expert), placement, EXPERT_WHAT, expert_hint(expert))
