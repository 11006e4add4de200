"""A concept planted in the tiny model, so the evaluation has a right answer to find.

Two instructions whose tokens pair up one to one. Layer 0 of the language model is made the identity (its
attention output and MLP down projections zeroed), so resid_post[0] at a language position is the token's
embedding times √width; its key and value projections are zeroed too, because the action expert attends to
every layer's keys and values and layer 0's come from its input, which steering its output cannot change. The paired tokens' embedding rows are rewritten as u_i ∓ v/2 with u_i ⟂ v and
‖u_i‖ = (√3/2)‖v‖: every instruction row then has the same norm √width·‖v‖, the two tasks' rows differ by
exactly d = √width·v at every instruction position, and ‖d‖ equals R, the mean row norm. Adding d at the
instruction tokens of layer 0 turns one task's prefix into the other's exactly, so the mean-difference
direction at α = 1 (in units of R, or of ‖d‖) reproduces the instruction swap on both sides, whatever the
random weights do downstream. Nothing else of the checkpoint changes.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import torch
from safetensors.torch import load_file

from steering_core.pi05.arch import Pi05Arch
from steering_core.pi05.checkpoint import EMBEDDING_KEY, LM_PREFIX, MODEL_FILE
from steering_core.pi05.tokenizer import PromptTokenizer
from steering_core.synthetic.libero import MotionSpec, SyntheticTask
from steering_core.tensor_files import save_safetensors

PLANTED_LAYER = 0
PLANTED_POSITIVE = "advance"
PLANTED_NEGATIVE = "retreat"
# Opposite motions on one position axis, so the contrast manifest finds its axis as for any real pair.
PLANTED_TASKS = (
    SyntheticTask(instruction=PLANTED_POSITIVE, scene="KITCHEN_SCENE2", motion=MotionSpec(axis=1, direction=1)),
    SyntheticTask(instruction=PLANTED_NEGATIVE, scene="KITCHEN_SCENE4", motion=MotionSpec(axis=1, direction=-1)),
)
# Repeated in the tokenizer's training text, so each instruction is whole-word pieces of its own.
PLANTED_CORPUS = tuple(text for text in (PLANTED_POSITIVE, PLANTED_NEGATIVE) for _ in range(50))
LAYER0_ZEROED = ("self_attn.k_proj.weight", "self_attn.v_proj.weight", "self_attn.o_proj.weight",
                 "mlp.down_proj.weight")


def instruction_pairs(tokenizer: PromptTokenizer, positive: str, negative: str) -> list[tuple[int, int]]:
    """Return the (positive id, negative id) of each instruction position; refuse instructions whose tokens
    do not pair up one to one (different lengths, a shared token, or a token paired two ways)."""
    ids = []
    for task in (positive, negative):
        prompt = tokenizer.tokenize(task)
        ids.append(prompt.ids[prompt.instruction[0] : prompt.instruction[1]].tolist())
    if len(ids[0]) != len(ids[1]):
        raise ValueError(f"{positive!r} and {negative!r} tokenize to {len(ids[0])} and {len(ids[1])} instruction "
                         f"tokens ({ids[0]} vs {ids[1]}); a planted concept needs the same count")
    pairs = sorted(set(zip(*ids, strict=True)))
    firsts, seconds = [p for p, _ in pairs], [n for _, n in pairs]
    if len(set(firsts)) != len(pairs) or len(set(seconds)) != len(pairs) or set(firsts) & set(seconds):
        raise ValueError(f"the tokens of {positive!r} {ids[0]} and {negative!r} {ids[1]} do not pair up one to one")
    return pairs


def plant_concept(
    checkpoint: str | os.PathLike, tokenizer_path: str | os.PathLike, arch: Pi05Arch, *,
    positive: str = PLANTED_POSITIVE, negative: str = PLANTED_NEGATIVE, seed: int = 1,
) -> torch.Tensor:
    """Rewrite the checkpoint folder's weights so `positive` and `negative` differ by one residual direction at
    layer 0 (module docstring); return that direction d = resid_post[0](positive) − resid_post[0](negative)."""
    path = Path(checkpoint) / MODEL_FILE
    tensors = load_file(path)
    generator = torch.Generator().manual_seed(seed)
    embedding = tensors[EMBEDDING_KEY].clone()
    v = torch.randn(arch.width, generator=generator, dtype=torch.float64)
    v /= v.norm()
    for positive_id, negative_id in instruction_pairs(PromptTokenizer(tokenizer_path), positive, negative):
        u = torch.randn(arch.width, generator=generator, dtype=torch.float64)
        u -= (u @ v) * v
        u *= (math.sqrt(3) / 2) / u.norm()
        embedding[positive_id] = (u + v / 2).to(embedding.dtype)
        embedding[negative_id] = (u - v / 2).to(embedding.dtype)
    tensors[EMBEDDING_KEY] = embedding
    for name in LAYER0_ZEROED:
        key = f"{LM_PREFIX}layers.{PLANTED_LAYER}.{name}"
        tensors[key] = torch.zeros_like(tensors[key])
    save_safetensors(tensors, path)
    return (math.sqrt(arch.width) * v).float()
