"""The seed's capture path as cost-faithful model code: a full pi0.5 inference call (openpi's `sample_actions`).

The research code captured residuals with a forward hook on one PaliGemma decoder layer while running the
whole policy: the prefix over every camera slot (the masked right wrist included) and all 200 language
slots (padding included) through all 18 layers with openpi's explicit (B, 1, 968, 968) additive mask and
eager attention, then the final norm; then 10 Euler denoising steps of the action expert (gemma_300m-shaped
layers with adaRMS time conditioning) whose queries attend to the prefix KV cache. One such call per batch
and per requested layer.

This module does the same amount and kind of work. The prefix is the library's `Pi05Prefix` with its
savings turned off (every camera, no trimming) driven through a KV cache with eager attention; the action
expert is built here from transformers' Gemma attention and MLP blocks and the adaRMS norm openpi adds,
and every weight is read from the same checkpoint, in either layout (openpi's converted folder or lerobot's
PI05Policy folder: each tensor is named by openpi's key and read under the name its file stores,
`steering_core.pi05.layouts.Checkpoint.stored`). It is a benchmark baseline, not a policy: the action
outputs are never checked.
"""

from __future__ import annotations

import math
import os

import torch
from safetensors import safe_open
from torch import nn
from transformers import DynamicCache
from transformers.models.gemma.modeling_gemma import (
    GemmaAttention,
    GemmaMLP,
    GemmaRMSNorm,
    apply_rotary_pos_emb,
    eager_attention_forward,
)

from steering_core.pi05 import Pi05Arch
from steering_core.pi05.arch import ExpertArch
from steering_core.pi05.checkpoint import EXPERT_PREFIX, LM_PREFIX, expert_arch_from_checkpoint
from steering_core.pi05.layouts import Checkpoint, LayoutName, resolve_checkpoint
from steering_core.pi05.model import MASKED_LOGIT, NORM_EPS, Pi05Prefix, attention_mask, gemma_config

DENOISE_STEPS = 10  # sample_actions' default number of Euler steps
ACTION_HORIZON = 10  # pi05_libero
ACTION_DIM = 32  # pi0.5 pads actions to 32
TIME_PERIODS = (4e-3, 4.0)  # min and max period of openpi's sinusoidal time embedding
FINAL_NORM_KEY = LM_PREFIX + "norm.weight"


def expert_arch(arch: Pi05Arch, expert: ExpertArch | None = None) -> Pi05Arch:
    """Return the action expert's dimensions as a Gemma `Pi05Arch`: `expert`'s width and MLP size, or by default
    half the LM width and a quarter of its MLP (gemma_300m vs gemma_2b); depth and attention are the LM's."""
    if expert is None:
        return arch.model_copy(update={"width": arch.width // 2, "mlp_dim": arch.mlp_dim // 4})
    expert.check_pairs_with(arch)
    return arch.model_copy(update={"width": expert.width, "mlp_dim": expert.mlp_dim})


class AdaRMSNorm(nn.Module):
    """openpi's pi0.5 expert norm: RMSNorm whose scale, shift and residual gate come from the time embedding."""

    def __init__(self, width: int):
        super().__init__()
        self.dense = nn.Linear(width, 3 * width)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return (normalised x (B, T, width) in x's dtype, gate (B, 1, width)) for condition (B, width)."""
        hidden = x.float()
        normed = hidden * torch.rsqrt(hidden.pow(2).mean(-1, keepdim=True) + NORM_EPS)
        scale, shift, gate = self.dense(cond.to(self.dense.weight.dtype))[:, None, :].chunk(3, dim=-1)
        return (normed * (1 + scale) + shift).to(x.dtype), gate.to(x.dtype)


class ExpertLayer(nn.Module):
    """One action-expert decoder layer: adaRMS, attention over [prefix cache | suffix], gated residuals."""

    def __init__(self, config, index: int):
        super().__init__()
        self.self_attn = GemmaAttention(config, index)
        self.mlp = GemmaMLP(config)
        self.input_layernorm = AdaRMSNorm(config.hidden_size)
        self.post_attention_layernorm = AdaRMSNorm(config.hidden_size)

    def forward(
        self,
        x: torch.Tensor,
        cond: torch.Tensor,
        rotary: tuple[torch.Tensor, torch.Tensor],
        prefix_kv: tuple[torch.Tensor, torch.Tensor],
        mask: torch.Tensor,
    ) -> torch.Tensor:
        """Return the layer output (B, H, width) for suffix tokens x (B, H, width)."""
        attn = self.self_attn
        hidden, gate = self.input_layernorm(x, cond)
        shape = (*hidden.shape[:-1], -1, attn.head_dim)
        q = attn.q_proj(hidden).view(shape).transpose(1, 2)  # (B, heads, H, head_dim)
        k = attn.k_proj(hidden).view(shape).transpose(1, 2)  # (B, kv_heads, H, head_dim)
        v = attn.v_proj(hidden).view(shape).transpose(1, 2)
        q, k = apply_rotary_pos_emb(q, k, *rotary)
        # the suffix reads the cached prefix keys and values followed by its own: (B, kv_heads, S + H, head_dim)
        k = torch.cat([prefix_kv[0], k], dim=2)
        v = torch.cat([prefix_kv[1], v], dim=2)
        out, _ = eager_attention_forward(attn, q, k, v, mask, scaling=attn.scaling)
        x = x + attn.o_proj(out.reshape(*x.shape[:-1], -1)) * gate
        hidden, gate = self.post_attention_layernorm(x, cond)
        return x + self.mlp(hidden) * gate


class ExpertModel(nn.Module):
    """The action expert's decoder stack and final adaRMS norm (checkpoint names under `gemma_expert.model.`)."""

    def __init__(self, arch: Pi05Arch, expert: ExpertArch | None = None):
        super().__init__()
        config = gemma_config(expert_arch(arch, expert))
        config._attn_implementation = "eager"  # openpi sets eager for the denoising steps
        self.layers = nn.ModuleList(ExpertLayer(config, index) for index in range(arch.depth))
        self.norm = AdaRMSNorm(config.hidden_size)


class SeedPi05(nn.Module):
    """Everything one openpi `sample_actions` call runs, with the prefix's decoder layers hookable as in the seed."""

    def __init__(self, prefix: Pi05Prefix, expert: ExpertArch | None = None):
        """`expert`: the action expert's dimensions (default gemma_300m-shaped beside `prefix.arch`, actions of
        ACTION_DIM)."""
        super().__init__()
        arch = prefix.arch
        width = expert_arch(arch, expert).width
        self.action_dim = ACTION_DIM if expert is None else expert.action_dim
        self.prefix = prefix
        self.final_norm = GemmaRMSNorm(arch.width, eps=NORM_EPS)
        self.gemma_expert = nn.Module()
        self.gemma_expert.model = ExpertModel(arch, expert)
        self.action_in_proj = nn.Linear(self.action_dim, width)
        self.action_out_proj = nn.Linear(width, self.action_dim)
        self.time_mlp_in = nn.Linear(width, width)
        self.time_mlp_out = nn.Linear(width, width)

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike | Checkpoint,
        arch: Pi05Arch,
        device: torch.device,
        dtype: torch.dtype | None = None,
        layout: LayoutName | str = LayoutName.AUTO,
    ) -> SeedPi05:
        """Return the whole policy from a pi0.5 checkpoint (a folder or model.safetensors in openpi's or lerobot's
        layout, detected or `layout` forced; or a resolved `Checkpoint`): every prefix layer plus the expert
        (its dimensions read from the file) and heads."""
        checkpoint = path if isinstance(path, Checkpoint) else resolve_checkpoint(path, layout)
        prefix = Pi05Prefix.from_checkpoint(checkpoint, arch, arch.depth - 1, device, dtype)
        model = cls(prefix, expert_arch_from_checkpoint(checkpoint, arch))
        own = {name: tensor for name, tensor in model.state_dict().items() if not name.startswith("prefix.")}
        keys = {name: _checkpoint_key(name) for name in own}  # canonical (openpi) names
        compute = prefix.compute_dtype
        with safe_open(str(checkpoint.model_file), framework="pt", device="cpu") as handle:
            weights = {
                name: handle.get_tensor(checkpoint.stored(key)).to(
                    device, torch.float32 if _kept_float32(key) else compute)
                for name, key in keys.items()
            }
        model.load_state_dict(weights | {f"prefix.{k}": v for k, v in prefix.state_dict().items()}, assign=True)
        return model.requires_grad_(False).eval()

    @torch.no_grad()
    def sample_actions(
        self,
        images: list[torch.Tensor],
        image_masks: list[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
        steps: int = DENOISE_STEPS,
    ) -> torch.Tensor:
        """Return actions (B, ACTION_HORIZON, action_dim) float32 after `steps` Euler steps from Gaussian noise."""
        pad, cache = self._prefix_cache(images, image_masks, tokens, token_mask)
        batch = tokens.shape[0]
        x_t = torch.randn(batch, ACTION_HORIZON, self.action_dim, device=pad.device)
        dt = -1.0 / steps
        for step in range(steps):
            time = torch.full((batch,), 1.0 + step * dt, device=pad.device)
            x_t = x_t + dt * self._denoise_step(pad, cache, x_t, time)
        return x_t

    def _prefix_cache(
        self,
        images: list[torch.Tensor],
        image_masks: list[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
    ) -> tuple[torch.Tensor, DynamicCache]:
        """Run the whole prefix (every slot, every layer, eager + additive mask, final norm); return (pad, KV cache)."""
        prefix = self.prefix
        device = prefix.device
        image_masks = [mask.to(device) for mask in image_masks]
        tokens, token_mask = tokens.to(device), token_mask.to(device)
        hidden, pad, _ = prefix.embed_prefix(
            images, image_masks, tokens, token_mask, skip_masked_images=False, trim_padding=False
        )
        mask = attention_mask(pad, "eager")  # (B, 1, S, S) float32 additive, openpi's
        position_ids = torch.cumsum(pad, dim=1) - 1
        prefix.lm_config._attn_implementation = "eager"
        hidden = hidden.to(prefix.compute_dtype)
        rotary = prefix.rotary_emb(hidden, position_ids)
        cache = DynamicCache()
        for layer in prefix.layers:
            hidden = layer(hidden, attention_mask=mask, position_ids=position_ids, past_key_values=cache,
                           use_cache=True, position_embeddings=rotary)
        self.final_norm(hidden)  # openpi's prefix forward ends with the LM's final norm; its output is unused
        return pad, cache

    def _denoise_step(
        self, pad: torch.Tensor, cache: DynamicCache, x_t: torch.Tensor, time: torch.Tensor
    ) -> torch.Tensor:
        """Return the velocity (B, H, action_dim) float32 of one denoising step at times (B,)."""
        expert = self.gemma_expert.model
        batch, horizon = x_t.shape[:2]
        dtype = self.action_in_proj.weight.dtype
        cond = self.time_mlp_in(_time_embedding(time, self.action_in_proj.out_features).to(dtype))
        cond = nn.functional.silu(self.time_mlp_out(nn.functional.silu(cond)))  # (B, width)
        x = self.action_in_proj(x_t.to(dtype)).to(self.prefix.compute_dtype)  # (B, H, width)
        # suffix queries see every valid prefix key and every suffix key (one bidirectional action block)
        allowed = torch.cat([pad[:, None, :].expand(batch, horizon, -1), pad.new_ones(batch, horizon, horizon)], dim=2)
        mask = torch.where(allowed[:, None], 0.0, MASKED_LOGIT).to(torch.float32)  # (B, 1, H, S + H)
        position_ids = pad.sum(dim=1, keepdim=True) + torch.arange(horizon, device=pad.device)  # (B, H)
        rotary = self.prefix.rotary_emb(x, position_ids)
        for index, layer in enumerate(expert.layers):
            kv = (cache.layers[index].keys, cache.layers[index].values)
            x = layer(x, cond, rotary, kv, mask)
        x, _ = expert.norm(x, cond)
        return self.action_out_proj(x.to(self.action_out_proj.weight.dtype)).float()


def _time_embedding(time: torch.Tensor, width: int) -> torch.Tensor:
    """Return the sine-cosine embedding (B, width) float32 of times (B,), openpi's periods 4e-3..4."""
    low, high = TIME_PERIODS
    fraction = torch.linspace(0.0, 1.0, width // 2, dtype=torch.float64, device=time.device)
    angle = (2 * math.pi / (low * (high / low) ** fraction))[None, :] * time[:, None].double()
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=1).float()


def _checkpoint_key(name: str) -> str:
    """Return the canonical (openpi) checkpoint key of a SeedPi05 parameter outside the prefix."""
    if name.startswith("final_norm."):
        return FINAL_NORM_KEY
    if name.startswith("gemma_expert."):
        return EXPERT_PREFIX + name.removeprefix("gemma_expert.")
    return name  # action_in_proj, action_out_proj, time_mlp_in, time_mlp_out


def _kept_float32(key: str) -> bool:
    """Return whether openpi keeps this tensor (canonical key) in float32 under a bfloat16 policy (norms and the
    four heads)."""
    return "norm" in key or not key.startswith("paligemma_with_expert.")
