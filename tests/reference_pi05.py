"""A naive float64 pi0.5 prefix, written straight from docs/PI05_SPEC.md section 3, for equivalence tests.

Deliberately different from `steering_core.pi05.model`: it reads the checkpoint with safetensors itself,
uses no transformers code, and runs each sample on its valid tokens only (that is what the bidirectional
pad mask means: valid tokens see exactly the valid tokens, numbered 0..n-1 in prefix order), with explicit
loops over patches, heads, positions and layers.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from safetensors import safe_open

P = "paligemma_with_expert.paligemma."
V = P + "model.vision_tower.vision_model."
LM = P + "model.language_model."
EPS = 1e-6
ROPE_BASE = 10000.0


def read_weights(model_file: Path, prefix: str = P) -> dict[str, torch.Tensor]:
    """Return every tensor under `prefix` of the file as float64."""
    with safe_open(str(model_file), framework="pt") as handle:
        return {name: handle.get_tensor(name).to(torch.float64) for name in handle.keys() if name.startswith(prefix)}


def layer_norm(x, weight, bias):
    mean = x.mean(dim=-1, keepdim=True)
    var = ((x - mean) ** 2).mean(dim=-1, keepdim=True)
    return (x - mean) / torch.sqrt(var + EPS) * weight + bias


def rms_norm(x, weight):
    return x / torch.sqrt((x * x).mean(dim=-1, keepdim=True) + EPS) * (1.0 + weight)


def gelu_tanh(x):
    return 0.5 * x * (1.0 + torch.tanh(math.sqrt(2.0 / math.pi) * (x + 0.044715 * x**3)))


def softmax(scores):
    exp = torch.exp(scores - scores.amax(dim=-1, keepdim=True))  # amax: max(dim) is slow on busy CPUs
    return exp / exp.sum(dim=-1, keepdim=True)


def rope(x, positions):
    """Rotate-half RoPE of x (n, head_dim) at integer positions (n,), one position at a time."""
    half = x.shape[1] // 2
    inv_freq = torch.tensor([ROPE_BASE ** (-2.0 * j / x.shape[1]) for j in range(half)], dtype=torch.float64)
    out = torch.empty_like(x)
    for t, position in enumerate(positions):
        theta = position * inv_freq
        lo, hi = x[t, :half], x[t, half:]
        out[t, :half] = lo * torch.cos(theta) - hi * torch.sin(theta)
        out[t, half:] = hi * torch.cos(theta) + lo * torch.sin(theta)
    return out


def image_tokens(w, arch, image):
    """Return (tokens_per_image, width) for one image (3, H, W) in [-1, 1]."""
    p, heads = arch.patch_size, arch.vision_heads
    kernel = w[V + "embeddings.patch_embedding.weight"].reshape(arch.vision_width, -1)  # (vw, 3*p*p)
    rows = []
    for r in range(arch.grid_size):
        for c in range(arch.grid_size):
            patch = image[:, r * p : (r + 1) * p, c * p : (c + 1) * p].reshape(-1)  # (channel, row, col) order
            rows.append(kernel @ patch + w[V + "embeddings.patch_embedding.bias"])
    h = torch.stack(rows) + w[V + "embeddings.position_embedding.weight"]
    hd = arch.vision_head_dim
    for i in range(arch.vision_depth):
        L = f"{V}encoder.layers.{i}."
        a = layer_norm(h, w[L + "layer_norm1.weight"], w[L + "layer_norm1.bias"])
        q, k, v = (a @ w[f"{L}self_attn.{n}_proj.weight"].T + w[f"{L}self_attn.{n}_proj.bias"] for n in "qkv")
        attended = torch.zeros_like(q)
        for n in range(heads):
            cols = slice(n * hd, (n + 1) * hd)
            attended[:, cols] = softmax(q[:, cols] @ k[:, cols].T / math.sqrt(hd)) @ v[:, cols]
        h = h + attended @ w[L + "self_attn.out_proj.weight"].T + w[L + "self_attn.out_proj.bias"]
        a = layer_norm(h, w[L + "layer_norm2.weight"], w[L + "layer_norm2.bias"])
        hidden = gelu_tanh(a @ w[L + "mlp.fc1.weight"].T + w[L + "mlp.fc1.bias"])
        h = h + hidden @ w[L + "mlp.fc2.weight"].T + w[L + "mlp.fc2.bias"]
    h = layer_norm(h, w[V + "post_layernorm.weight"], w[V + "post_layernorm.bias"])
    proj = P + "model.multi_modal_projector.linear."
    return h @ w[proj + "weight"].T + w[proj + "bias"]


def decoder_layer(w, arch, layer, h, positions, cache=None):
    """Return the output of PaliGemma decoder layer `layer` for valid tokens h (n, width).

    With a `cache` list, appends this layer's rotated keys and values, each (kv_heads, n, head_dim).
    """
    L = f"{LM}layers.{layer}."
    hd, group = arch.head_dim, arch.num_heads // arch.num_kv_heads
    a = rms_norm(h, w[L + "input_layernorm.weight"])
    q = a @ w[L + "self_attn.q_proj.weight"].T
    k = a @ w[L + "self_attn.k_proj.weight"].T
    v = a @ w[L + "self_attn.v_proj.weight"].T
    heads = []
    for n in range(arch.num_heads):
        kv = slice((n // group) * hd, (n // group + 1) * hd)
        qn = rope(q[:, n * hd : (n + 1) * hd], positions)
        kn = rope(k[:, kv], positions)
        heads.append(softmax(qn @ kn.T / math.sqrt(hd)) @ v[:, kv])
    if cache is not None:
        kv_heads = range(arch.num_kv_heads)
        cache.append((
            torch.stack([rope(k[:, j * hd : (j + 1) * hd], positions) for j in kv_heads]),
            torch.stack([v[:, j * hd : (j + 1) * hd] for j in kv_heads]),
        ))
    h = h + torch.cat(heads, dim=1) @ w[L + "self_attn.o_proj.weight"].T
    b = rms_norm(h, w[L + "post_attention_layernorm.weight"])
    gated = gelu_tanh(b @ w[L + "mlp.gate_proj.weight"].T) * (b @ w[L + "mlp.up_proj.weight"].T)
    return h + gated @ w[L + "mlp.down_proj.weight"].T


def valid_prefix(w, arch, images, image_masks, tokens, token_mask, b):
    """Return sample b's valid prefix embeddings (n, width) and their columns in the full prefix."""
    n_img, per_image = len(images), arch.tokens_per_image
    rows, columns = [], []
    for slot in range(n_img):
        if image_masks[slot][b]:
            rows.append(image_tokens(w, arch, images[slot][b].to(torch.float64)))
            columns.extend(range(slot * per_image, (slot + 1) * per_image))
    for t in range(tokens.shape[1]):
        if token_mask[b, t]:
            rows.append(w[P + "lm_head.weight"][int(tokens[b, t])][None] * math.sqrt(arch.width))
            columns.append(n_img * per_image + t)
    return torch.cat(rows), columns


def reference_residuals(model_file, arch, images, image_masks, tokens, token_mask, layers):
    """Return {layer: (B, n_images*tokens_per_image + T, width) float64}, NaN at invalid positions."""
    w = read_weights(model_file)
    batch, n_tokens = tokens.shape
    total = len(images) * arch.tokens_per_image + n_tokens
    out = {layer: torch.full((batch, total, arch.width), math.nan, dtype=torch.float64) for layer in layers}
    for b in range(batch):
        h, columns = valid_prefix(w, arch, images, image_masks, tokens, token_mask, b)
        positions = list(range(len(columns)))
        for layer in range(max(layers) + 1):
            h = decoder_layer(w, arch, layer, h, positions)
            if layer in out:
                out[layer][b, columns] = h
    return out
