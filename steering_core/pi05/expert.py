"""pi0.5's action expert: a Gemma (gemma_300m) with adaRMS time conditioning over the action tokens.

Written from the spec (PI05_SPEC.md section 10): each expert layer attends to the language model's cached
keys/values of the same layer index and to the action tokens; its norms take scale, shift and a residual
gate from the flow-matching time; the heads map actions in and velocities out. Submodules are named after
the checkpoint's keys so loading is an explicit prefix mapping (`expert_checkpoint_key`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from transformers.models.gemma.modeling_gemma import apply_rotary_pos_emb

from steering_core.pi05.arch import ExpertArch
from steering_core.pi05.checkpoint import EXPERT_PREFIX
from steering_core.pi05.model import NORM_EPS
from steering_core.pi05.steering import Clamp, apply_clamp

TIME_MIN_PERIOD, TIME_MAX_PERIOD = 4e-3, 4.0  # openpi's sinusoidal time embedding (spec 10.3)

KeyValues = Sequence[tuple[torch.Tensor, torch.Tensor]]  # per layer (B, kv_heads, S, head_dim) keys, values


def expert_checkpoint_key(parameter: str) -> str:
    """Return the checkpoint key of an `ActionExpert` parameter name (heads keep their names)."""
    if parameter.startswith(("layers.", "norm.")):
        return EXPERT_PREFIX + "model." + parameter
    return parameter


def time_embedding(time: torch.Tensor, width: int) -> torch.Tensor:
    """Return (B, width) sin/cos features of flow time (B,) float32, periods 4e-3..4.0 (spec 10.3).

    Frequencies in float64 as openpi computes them; all sines first, then all cosines; cast to time's dtype.
    """
    fraction = torch.linspace(0.0, 1.0, width // 2, dtype=torch.float64, device=time.device)
    period = TIME_MIN_PERIOD * (TIME_MAX_PERIOD / TIME_MIN_PERIOD) ** fraction
    angle = (2.0 * math.pi / period)[None, :] * time[:, None]
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=1).to(time.dtype)


def euler_times(num_steps: int, device: torch.device, accumulate: bool = True) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Return the step dt = -1/num_steps and the flow times the checkpoint's library evaluates, float32 0-d tensors.

    openpi (`accumulate`): from 1.0, `t += dt` accumulated in float32 while t >= -dt/2 (1.0, 0.9, 0.79999995, ... for
    10 steps; not 1 - k/num_steps, spec 10.4). lerobot: t = 1 + k * dt computed in float64, then rounded to float32
    (1.0, 0.9, 0.8, ...; spec 17.7).
    """
    if isinstance(num_steps, bool) or not isinstance(num_steps, int) or num_steps < 1:
        raise ValueError(f"num_steps {num_steps!r} must be a positive integer")
    dt = torch.tensor(-1.0 / num_steps, dtype=torch.float32, device=device)
    if not accumulate:
        return dt, [torch.tensor(1.0 + k * (-1.0 / num_steps), dtype=torch.float32, device=device)
                    for k in range(num_steps)]
    time = torch.tensor(1.0, dtype=torch.float32, device=device)
    times = []
    while time >= -dt / 2:
        times.append(time)
        time = time + dt
    return dt, times


class AdaRMSNorm(nn.Module):
    """RMSNorm whose scale, shift and residual gate are a dense map of the time conditioning (spec 10.2)."""

    def __init__(self, width: int):
        super().__init__()
        self.dense = nn.Linear(width, 3 * width)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return (normalised x, gate), both in x's dtype, for x (B, S, W) and cond (B, W) float32."""
        scale, shift, gate = self.dense(cond)[:, None, :].chunk(3, dim=-1)
        # x itself is not upcast: the float32 rsqrt promotes the product, as in openpi
        normed = x * torch.rsqrt(x.float().pow(2).mean(dim=-1, keepdim=True) + NORM_EPS)
        out = normed * (1.0 + scale.float()) + shift.float()
        return out.to(x.dtype), gate.to(x.dtype)


class ExpertAttention(nn.Module):
    """Multi-query attention of the action tokens over [cached prefix keys | action keys] (eager, openpi's)."""

    def __init__(self, expert: ExpertArch):
        super().__init__()
        self.num_heads, self.num_kv_heads, self.head_dim = expert.num_heads, expert.num_kv_heads, expert.head_dim
        q, kv = expert.num_heads * expert.head_dim, expert.num_kv_heads * expert.head_dim
        self.q_proj = nn.Linear(expert.width, q, bias=False)
        self.k_proj = nn.Linear(expert.width, kv, bias=False)
        self.v_proj = nn.Linear(expert.width, kv, bias=False)
        self.o_proj = nn.Linear(q, expert.width, bias=False)

    def forward(
        self,
        x: torch.Tensor,
        rotary: tuple[torch.Tensor, torch.Tensor],
        prefix: tuple[torch.Tensor, torch.Tensor],
        mask: torch.Tensor,
    ) -> torch.Tensor:
        """Return the attention output (B, H, W) for normalised action tokens x (B, H, W).

        rotary: cos, sin (B, H, head_dim) at the action positions; prefix: this layer's cached (post-RoPE)
        keys and values (B, kv_heads, P, head_dim); mask: (B, 1, 1 or H, P + H) float32 additive.
        """
        batch, horizon, _ = x.shape
        q = self.q_proj(x).view(batch, horizon, self.num_heads, self.head_dim).transpose(1, 2)
        k = self.k_proj(x).view(batch, horizon, self.num_kv_heads, self.head_dim).transpose(1, 2)
        v = self.v_proj(x).view(batch, horizon, self.num_kv_heads, self.head_dim).transpose(1, 2)
        q, k = apply_rotary_pos_emb(q, k, *rotary)
        k = torch.cat([prefix[0], k], dim=2)  # the cache is read, never extended: every step sees the prefix only
        v = torch.cat([prefix[1], v], dim=2)
        # query heads sharing one KV head are stacked along the query axis instead of repeating the keys
        group = self.num_heads // self.num_kv_heads
        q = q.reshape(batch, self.num_kv_heads, group * horizon, self.head_dim)
        scores = torch.matmul(q, k.transpose(2, 3)) * self.head_dim**-0.5
        scores = scores.unflatten(2, (group, horizon)) + mask[:, :, None]  # (B, kv, group, H, P + H), float32
        weights = torch.softmax(scores, dim=-1, dtype=torch.float32).to(q.dtype).flatten(2, 3)
        out = torch.matmul(weights, v).view(batch, self.num_heads, horizon, self.head_dim)
        return self.o_proj(out.transpose(1, 2).reshape(batch, horizon, -1))


class ExpertMLP(nn.Module):
    """Gemma's gated MLP: down(gelu_tanh(gate(x)) * up(x)), no biases."""

    def __init__(self, expert: ExpertArch):
        super().__init__()
        self.gate_proj = nn.Linear(expert.width, expert.mlp_dim, bias=False)
        self.up_proj = nn.Linear(expert.width, expert.mlp_dim, bias=False)
        self.down_proj = nn.Linear(expert.mlp_dim, expert.width, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.down_proj(F.gelu(self.gate_proj(x), approximate="tanh") * self.up_proj(x))


class ExpertLayer(nn.Module):
    """One expert decoder layer: x + attn(norm(x)) * gate1, then + mlp(norm(x)) * gate2 (raw gates)."""

    def __init__(self, expert: ExpertArch):
        super().__init__()
        self.input_layernorm = AdaRMSNorm(expert.width)
        self.self_attn = ExpertAttention(expert)
        self.post_attention_layernorm = AdaRMSNorm(expert.width)
        self.mlp = ExpertMLP(expert)

    def forward(self, x, cond, rotary, prefix, mask) -> torch.Tensor:
        h, gate = self.input_layernorm(x, cond)
        x = x + self.self_attn(h, rotary, prefix, mask) * gate
        h, gate = self.post_attention_layernorm(x, cond)
        return x + self.mlp(h) * gate


class ActionExpert(nn.Module):
    """The expert's layers and final adaRMS norm plus pi0.5's action and time heads.

    Build it on the meta device and load a state dict with `assign=True` (`Pi05Policy.from_checkpoint`).
    """

    def __init__(self, expert: ExpertArch):
        super().__init__()
        self.expert_arch = expert
        self.layers = nn.ModuleList(ExpertLayer(expert) for _ in range(expert.depth))
        self.norm = AdaRMSNorm(expert.width)
        self.action_in_proj = nn.Linear(expert.action_dim, expert.width)
        self.action_out_proj = nn.Linear(expert.width, expert.action_dim)
        self.time_mlp_in = nn.Linear(expert.width, expert.width)
        self.time_mlp_out = nn.Linear(expert.width, expert.width)

    @property
    def compute_dtype(self) -> torch.dtype:
        """Return the dtype of the expert's residual stream (its projections' dtype)."""
        return self.layers[0].self_attn.q_proj.weight.dtype

    def condition(self, time: torch.Tensor) -> torch.Tensor:
        """Return the adaRMS conditioning (B, W) float32 for flow time (B,): swish after both time MLPs."""
        embedded = time_embedding(time, self.expert_arch.width).to(self.time_mlp_in.weight.dtype)
        return F.silu(self.time_mlp_out(F.silu(self.time_mlp_in(embedded))))

    def velocity(
        self,
        actions: torch.Tensor,
        cond: torch.Tensor,
        rotary: tuple[torch.Tensor, torch.Tensor],
        prefix: KeyValues,
        mask: torch.Tensor,
        additions: Mapping[int, torch.Tensor] | None = None,
        clamps: Mapping[int, Clamp] | None = None,
    ) -> torch.Tensor:
        """Return the flow velocity (B, H, action_dim) float32 for noisy actions (B, H, action_dim) float32.

        additions: {layer: tensor broadcastable to (B, H, W)} added to that layer's output (steering);
        clamps: {layer: `Clamp`} of that layer's output, applied before its addition.
        """
        hidden = self.action_in_proj(actions.to(self.action_in_proj.weight.dtype)).to(self.compute_dtype)
        for index, layer in enumerate(self.layers):
            hidden = layer(hidden, cond, rotary, prefix[index], mask)
            if clamps and index in clamps:
                hidden = apply_clamp(hidden, clamps[index])
            if additions and index in additions:
                hidden = hidden + additions[index]
        hidden, _ = self.norm(hidden, cond)  # the final norm's gate is unused
        return self.action_out_proj(hidden.to(self.action_out_proj.weight.dtype)).float()

    def euler_step(
        self,
        actions: torch.Tensor,
        time: torch.Tensor,
        dt: torch.Tensor,
        rotary: tuple[torch.Tensor, torch.Tensor],
        prefix: KeyValues,
        mask: torch.Tensor,
        additions: Mapping[int, torch.Tensor] | None = None,
        clamps: Mapping[int, Clamp] | None = None,
    ) -> torch.Tensor:
        """Return actions + dt * velocity (B, H, action_dim) float32 at flow time `time` (0-d float32, spec 10.4)."""
        cond = self.condition(time.expand(actions.shape[0]))
        return actions + dt * self.velocity(actions, cond, rotary, prefix, mask, additions, clamps)
