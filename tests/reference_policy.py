"""A naive float64 pi0.5 action expert and Euler sampler, written from PI05_SPEC.md section 10.

Independent of `steering_core.pi05.expert`/`policy` (no steering_core or transformers imports): one sample
at a time, the prefix on its valid tokens only (`reference_pi05`), explicit loops over heads, frequencies
and steps, flow times accumulated with numpy float32 scalars, steering written as "add alpha * v to the
rows at these prefix columns / to every action row".
"""

from __future__ import annotations

import math

import numpy as np
import torch
from reference_pi05 import decoder_layer, gelu_tanh, read_weights, rope, softmax, valid_prefix

E = "paligemma_with_expert.gemma_expert.model."
EPS = 1e-6


def ada_rms(w, name, x, cond):
    """Return (normalised x, gate) of adaRMS norm `name` for x (n, W) and cond (W,)."""
    width = x.shape[1]
    mod = w[name + ".dense.weight"] @ cond + w[name + ".dense.bias"]
    scale, shift, gate = mod[:width], mod[width : 2 * width], mod[2 * width :]
    normed = x / torch.sqrt((x * x).mean(dim=-1, keepdim=True) + EPS)
    return normed * (1.0 + scale) + shift, gate


def time_features(t: float, width: int) -> torch.Tensor:
    half = width // 2
    out = torch.empty(width, dtype=torch.float64)
    for i in range(half):
        period = 4e-3 * (4.0 / 4e-3) ** (i / (half - 1))
        out[i] = math.sin(2 * math.pi / period * t)
        out[half + i] = math.cos(2 * math.pi / period * t)
    return out


def silu(x):
    return x / (1.0 + torch.exp(-x))


def expert_layer(w, arch, layer, x, cond, positions, prefix_kv):
    """One expert layer for the action rows x (H, We) attending to [prefix keys | own keys]."""
    L = f"{E}layers.{layer}."
    hd, group = arch.head_dim, arch.num_heads // arch.num_kv_heads
    a, gate = ada_rms(w, L + "input_layernorm", x, cond)
    q = a @ w[L + "self_attn.q_proj.weight"].T
    k = a @ w[L + "self_attn.k_proj.weight"].T
    v = a @ w[L + "self_attn.v_proj.weight"].T
    keys, values = prefix_kv
    heads = []
    for n in range(arch.num_heads):
        j = n // group
        qn = rope(q[:, n * hd : (n + 1) * hd], positions)
        kn = torch.cat([keys[j], rope(k[:, j * hd : (j + 1) * hd], positions)])
        vn = torch.cat([values[j], v[:, j * hd : (j + 1) * hd]])
        heads.append(softmax(qn @ kn.T / math.sqrt(hd)) @ vn)
    x = x + (torch.cat(heads, dim=1) @ w[L + "self_attn.o_proj.weight"].T) * gate
    b, gate = ada_rms(w, L + "post_attention_layernorm", x, cond)
    hidden = gelu_tanh(b @ w[L + "mlp.gate_proj.weight"].T) * (b @ w[L + "mlp.up_proj.weight"].T)
    return x + (hidden @ w[L + "mlp.down_proj.weight"].T) * gate


def linear(w, name, x):
    return x @ w[name + ".weight"].T + w[name + ".bias"]


def reference_actions(model_file, arch, images, image_masks, tokens, token_mask, noise, num_steps=10, steering=(),
                      record=None):
    """Return (B, H, A) float64 actions.

    steering: dicts {"stream": "lm" | "expert", "layer", "vector", "alpha", "columns": (B, P) bool (lm)}.
    record: a dict that receives ("decision", b, step, layer) -> the layer's output at the last action row
    and ("adarms", step) -> the conditioning vector, both float64 (W,); also ("layer", b, step, layer) -> the
    layer's output at every action row (H, W) and ("velocity", b, step) -> the step's velocity (H, A).
    """
    w = read_weights(model_file, prefix="")
    batch, horizon, _ = noise.shape
    depth = sum(1 for name in w if name.startswith(E + "layers.") and name.endswith("q_proj.weight"))
    expert_width = w["time_mlp_in.weight"].shape[1]
    out = torch.empty(noise.shape, dtype=torch.float64)
    for b in range(batch):
        h, columns = valid_prefix(w, arch, images, image_masks, tokens, token_mask, b)
        n_valid = len(columns)
        cache = []
        for layer in range(arch.depth):
            h = decoder_layer(w, arch, layer, h, list(range(n_valid)), cache)
            for s in steering:
                if s["stream"] == "lm" and s["layer"] == layer:
                    rows = [i for i, column in enumerate(columns) if s["columns"][b, column]]
                    h[rows] += s["alpha"] * s["vector"].double()
        positions = list(range(n_valid, n_valid + horizon))
        x = noise[b].double()
        t, dt = np.float32(1.0), np.float32(-1.0 / num_steps)
        step = 0
        while t >= -dt / 2:
            features = time_features(float(t), expert_width)
            cond = silu(linear(w, "time_mlp_out", silu(linear(w, "time_mlp_in", features))))
            a = linear(w, "action_in_proj", x)
            for layer in range(depth):
                a = expert_layer(w, arch, layer, a, cond, positions, cache[layer])
                if record is not None:
                    record["decision", b, step, layer] = a[-1].clone()
                    record["layer", b, step, layer] = a.clone()
                    record["adarms", step] = cond.clone()
                for s in steering:
                    if s["stream"] == "expert" and s["layer"] == layer:
                        a = a + s["alpha"] * s["vector"].double()
            a, _ = ada_rms(w, E + "norm", a, cond)
            velocity = linear(w, "action_out_proj", a)
            if record is not None:
                record["velocity", b, step] = velocity
            x = x + float(dt) * velocity
            t = np.float32(t + dt)
            step += 1
        out[b] = x
    return out
