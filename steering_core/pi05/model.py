"""pi0.5's prefix forward: SigLIP image tokens + Gemma-2B over images and language, up to a chosen layer.

Built from transformers' SigLIP and Gemma blocks, which compute exactly what openpi's patched copies
compute for the prefix; the prefix assembly (embedding scales, masks, positions) is written here from
the spec (docs/PI05_SPEC.md section 3). Submodules are named after the checkpoint's keys so loading
is an explicit prefix mapping.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import torch
from torch import nn
from transformers import GemmaConfig, SiglipVisionConfig
from transformers.models.gemma.modeling_gemma import (
    GemmaDecoderLayer,
    GemmaRotaryEmbedding,
)
from transformers.models.siglip.modeling_siglip import SiglipEncoder

from steering_core.devices import resolve_device, resolve_dtype
from steering_core.pi05.arch import Pi05Arch
from steering_core.pi05.checkpoint import (
    EMBEDDING_KEY,
    LM_PREFIX,
    PROJECTOR_PREFIX,
    VISION_PREFIX,
    check_depths,
    check_max_layer,
    read_prefix_tensors,
)
from steering_core.pi05.layouts import OPENPI, Checkpoint, CheckpointLayout, LayoutName, resolve_checkpoint
from steering_core.pi05.steering import Clamp, apply_clamp

logger = logging.getLogger(__name__)

Attention = Literal["sdpa", "eager"]

NORM_EPS = 1e-6  # both Gemma's RMSNorm and SigLIP's LayerNorm
ROPE_THETA = 10000.0
ACTIVATION = "gelu_pytorch_tanh"  # GELU with the tanh approximation, in both towers
# openpi's additive mask value for disallowed pairs, added before a float32 softmax (spec 3.4)
MASKED_LOGIT = -2.3819763e38

# Module parameter prefix -> checkpoint key prefix (spec 1.2); the rest of each name is identical.
PARAMETER_PREFIXES = (
    ("vision_model.", VISION_PREFIX),
    ("multi_modal_projector.", PROJECTOR_PREFIX),
    ("layers.", LM_PREFIX + "layers."),
    ("embed_tokens.weight", EMBEDDING_KEY),
)


def checkpoint_key(parameter: str) -> str:
    """Return the checkpoint key of a `Pi05Prefix` parameter name."""
    for local, stored in PARAMETER_PREFIXES:
        if parameter.startswith(local):
            return stored + parameter[len(local) :]
    raise KeyError(f"parameter {parameter!r} has no checkpoint key mapping")


def gemma_config(arch: Pi05Arch) -> GemmaConfig:
    """Return the transformers config of the PaliGemma language model (pi0.5's, without adaRMS)."""
    config = GemmaConfig(
        vocab_size=arch.vocab_size,
        hidden_size=arch.width,
        intermediate_size=arch.mlp_dim,
        num_hidden_layers=arch.depth,
        num_attention_heads=arch.num_heads,
        num_key_value_heads=arch.num_kv_heads,
        head_dim=arch.head_dim,
        hidden_act=ACTIVATION,
        hidden_activation=ACTIVATION,
        rms_norm_eps=NORM_EPS,
        rope_theta=ROPE_THETA,
        attention_bias=False,
        attention_dropout=0.0,
    )
    config._attn_implementation = "sdpa"
    return config


def siglip_config(arch: Pi05Arch) -> SiglipVisionConfig:
    """Return the transformers config of the SigLIP vision tower."""
    config = SiglipVisionConfig(
        hidden_size=arch.vision_width,
        intermediate_size=arch.vision_mlp_dim,
        num_hidden_layers=arch.vision_depth,
        num_attention_heads=arch.vision_heads,
        num_channels=3,
        image_size=arch.image_size,
        patch_size=arch.patch_size,
        hidden_act=ACTIVATION,
        layer_norm_eps=NORM_EPS,
        attention_dropout=0.0,
    )
    # Image tokens attend to each other without a mask, so fused attention equals eager attention.
    config._attn_implementation = "sdpa"
    return config


def parameter_dtype(key: str, dtype: torch.dtype, layout: CheckpointLayout = OPENPI) -> torch.dtype:
    """Return the run-time dtype of canonical tensor `key` under compute dtype `dtype`: the layout's library keeps
    some parameters in float32 under a half-precision policy (spec 1.4, 17.6)."""
    half = dtype in (torch.bfloat16, torch.float16)
    return torch.float32 if half and any(selector in key for selector in layout.float32_selectors) else dtype


class SiglipEmbeddings(nn.Module):
    """Patch convolution plus learned position embedding (no class token, no interpolation)."""

    def __init__(self, arch: Pi05Arch):
        super().__init__()
        self.patch_embedding = nn.Conv2d(3, arch.vision_width, kernel_size=arch.patch_size, stride=arch.patch_size)
        self.position_embedding = nn.Embedding(arch.tokens_per_image, arch.vision_width)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Return patch tokens (batch, grid*grid, vision_width) in the embedding dtype (float32 in openpi)."""
        patches = self.patch_embedding(images.to(self.patch_embedding.weight.dtype))  # (B, vw, grid, grid)
        patches = patches.flatten(2).transpose(1, 2)  # (B, grid*grid, vw), row-major over (row, column)
        return patches + self.position_embedding.weight  # (tokens, vw) broadcast over the batch


class SiglipTower(nn.Module):
    """SigLIP vision model without its pooling head: embeddings, pre-LN encoder, post_layernorm."""

    def __init__(self, arch: Pi05Arch, config: SiglipVisionConfig):
        super().__init__()
        self.embeddings = SiglipEmbeddings(arch)
        self.encoder = SiglipEncoder(config)
        self.post_layernorm = nn.LayerNorm(arch.vision_width, eps=NORM_EPS)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Return image features (batch, tokens_per_image, vision_width) in the encoder's dtype."""
        hidden = self.embeddings(images)
        # openpi runs the embeddings in float32, then casts to the encoder's dtype (spec 3.6)
        hidden = hidden.to(self.post_layernorm.weight.dtype)
        hidden = self.encoder(inputs_embeds=hidden).last_hidden_state
        return self.post_layernorm(hidden)


class Projector(nn.Module):
    """PaliGemma's multi-modal projector: one biased linear map, no activation."""

    def __init__(self, arch: Pi05Arch):
        super().__init__()
        self.linear = nn.Linear(arch.vision_width, arch.width)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Return image tokens (..., width) from SigLIP features (..., vision_width)."""
        return self.linear(features)


class Pi05Prefix(nn.Module):
    """pi0.5's prefix (images + language) through the PaliGemma language model up to `max_layer`.

    Build it with `Pi05Prefix.from_checkpoint`: the constructor allocates no weights (meta tensors).
    """

    def __init__(self, arch: Pi05Arch, n_layers: int):
        super().__init__()
        self.arch = arch
        self.lm_config = gemma_config(arch)
        self.vision_config = siglip_config(arch)
        with torch.device("meta"):  # the checkpoint supplies every weight; skip random initialisation
            self.vision_model = SiglipTower(arch, self.vision_config)
            self.multi_modal_projector = Projector(arch)
            self.embed_tokens = nn.Embedding(arch.vocab_size, arch.width)
            self.layers = nn.ModuleList(GemmaDecoderLayer(self.lm_config, index) for index in range(n_layers))
        self.rotary_emb = GemmaRotaryEmbedding(self.lm_config)
        self.checkpoint: Checkpoint | None = None

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike | Checkpoint,
        arch: Pi05Arch | None = None,
        max_layer: int | None = None,
        device: str | torch.device | None = None,
        dtype: str | torch.dtype | None = None,
        layout: LayoutName | str = LayoutName.AUTO,
    ) -> Pi05Prefix:
        """Return the prefix model of a pi0.5 checkpoint (openpi's or lerobot's layout), loaded up to decoder
        layer `max_layer`.

        Args:
            path: checkpoint folder holding `model.safetensors` (and `config.json`), the file itself, or a
                resolved `Checkpoint`.
            arch: dimensions to check the checkpoint against; default the real pi0.5.
            max_layer: deepest decoder layer that will be captured; default the last. Deeper layers, the
                final norm, the action expert and the heads are never read.
            device: default CUDA when available, else CPU.
            dtype: compute dtype; default the layout's library's policy on CUDA (bfloat16 with its float32
                parameters, `CheckpointLayout.float32_selectors`), float32 on CPU.
            layout: `auto` (detected from the folder), `openpi` or `lerobot` (then checked against the folder).
        """
        arch = arch or Pi05Arch()
        checkpoint = path if isinstance(path, Checkpoint) else resolve_checkpoint(path, layout)
        max_layer = check_max_layer(arch, max_layer)
        check_depths(checkpoint, arch, max_layer)  # the layers built below are the file's
        device = resolve_device(device)
        dtype = resolve_dtype(dtype, device)
        model = cls(arch, max_layer + 1)
        local_names = {checkpoint_key(name): name for name, _ in model.named_parameters()}
        tensors = read_prefix_tensors(
            checkpoint,
            arch,
            max_layer,
            lambda key: (device, parameter_dtype(key, dtype, checkpoint.layout)),
        )
        model.load_state_dict({local_names[key]: tensor for key, tensor in tensors.items()}, strict=True, assign=True)
        model.rotary_emb.to(device)
        model.requires_grad_(False).eval()
        model.checkpoint = checkpoint
        logger.info("pi0.5 prefix from %s: layers 0..%d on %s in %s", checkpoint.describe, max_layer, device, dtype)
        return model

    @property
    def model_file(self) -> Path | None:
        """Return the weights file the model was loaded from."""
        return None if self.checkpoint is None else self.checkpoint.model_file

    @property
    def checkpoint_config(self) -> dict[str, Any] | None:
        """Return the checkpoint's `config.json`, if its folder has one."""
        return None if self.checkpoint is None else self.checkpoint.config

    @property
    def device(self) -> torch.device:
        """Return the device holding the weights."""
        return self.embed_tokens.weight.device

    @property
    def compute_dtype(self) -> torch.dtype:
        """Return the dtype of the residual stream (bfloat16 under openpi's CUDA policy)."""
        return self.embed_tokens.weight.dtype

    @property
    def max_layer(self) -> int:
        """Return the deepest loaded decoder layer."""
        return len(self.layers) - 1

    def embed_images(self, images: torch.Tensor) -> torch.Tensor:
        """Return image tokens (batch, tokens_per_image, width) for images (batch, 3, H, W) in [-1, 1].

        No 1/sqrt(width) scaling: openpi removed stock PaliGemma's division (spec 3.2).
        """
        return self.multi_modal_projector(self.vision_model(images))

    def embed_language(self, tokens: torch.Tensor) -> torch.Tensor:
        """Return language tokens (batch, T, width): embedding rows times sqrt(width), applied once (spec 3.3)."""
        return self.embed_tokens(tokens) * math.sqrt(self.arch.width)

    def on_device(
        self,
        images: Sequence[torch.Tensor],
        image_masks: Sequence[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
    ) -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor, torch.Tensor]:
        """Return the inputs moved to the model's device (tokens as int64): a caller's tensors may be on any
        device, and every entry point moves them here, once, before anything is computed from them."""
        device = self.device
        return ([image.to(device) for image in images], [mask.to(device) for mask in image_masks],
                tokens.to(device, torch.long), token_mask.to(device))

    def embed_prefix(
        self,
        images: Sequence[torch.Tensor],
        image_masks: Sequence[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
        *,
        skip_masked_images: bool = True,
        trim_padding: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return the computed prefix columns: embeddings (B, S, width), pad mask (B, S) bool, and each
        column's index (S,) int64 in the full prefix [camera 0 | camera 1 | ... | language T].

        Valid tokens never attend to invalid ones and position ids count only valid tokens, so dropping a
        camera masked for the whole batch and the language columns after the longest prompt changes no
        valid token's residual (spec 3.4). The inputs are on the model's device (`on_device`).
        """
        batch, n_tokens = tokens.shape
        per_image = self.arch.tokens_per_image
        slots = [slot for slot, mask in enumerate(image_masks) if not skip_masked_images or bool(mask.any())]
        n_lang = n_tokens
        if trim_padding:
            valid_columns = token_mask.any(dim=0).nonzero()
            n_lang = int(valid_columns[-1]) + 1 if len(valid_columns) else 0

        parts, pads, columns = [], [], []
        if slots:
            # one SigLIP pass over every computed camera: (n_slots * B, 3, H, W) -> (n_slots, B, tokens, width)
            stacked = torch.cat([images[slot] for slot in slots])
            image_tokens = self.embed_images(stacked).unflatten(0, (len(slots), batch))
            for slot, slot_tokens in zip(slots, image_tokens, strict=True):
                parts.append(slot_tokens)
                pads.append(image_masks[slot][:, None].expand(batch, per_image))
                columns.append(torch.arange(slot * per_image, (slot + 1) * per_image))
        parts.append(self.embed_language(tokens[:, :n_lang]))
        pads.append(token_mask[:, :n_lang])
        columns.append(torch.arange(n_lang) + len(images) * per_image)
        embeddings = torch.cat([part.to(self.compute_dtype) for part in parts], dim=1)
        return embeddings, torch.cat(pads, dim=1), torch.cat(columns).to(self.device)

    def decode(
        self,
        hidden: torch.Tensor,
        pad: torch.Tensor,
        layers: Iterable[int],
        attention: Attention = "sdpa",
        *,
        start: int = 0,
        cache: KeyValueRecorder | None = None,
        additions: Mapping[int, torch.Tensor] | None = None,
        replace: Mapping[int, Callable[[torch.Tensor], torch.Tensor]] | None = None,
        clamps: Mapping[int, Clamp] | None = None,
    ) -> dict[int, torch.Tensor]:
        """Return {layer: residual stream (B, S, width) after that decoder layer} for prefix embeddings.

        Args:
            hidden: prefix embeddings (B, S, width), or the output of layer `start - 1`.
            pad: (B, S) bool, True for valid tokens; valid tokens attend bidirectionally to valid tokens.
            layers: decoder layers to return; the loop stops after the deepest.
            attention: "sdpa" (fused, key-padding mask) or "eager" (openpi's explicit additive (S, S) mask).
            start: first decoder layer to run (the layers before it were run by an earlier call).
            cache: records every run layer's post-RoPE keys and values (the action expert's KV cache).
            additions: {layer: tensor broadcastable to (B, S, width)} added to that layer's output (steering).
            replace: {layer: function of that layer's output (B, S, width) returning its replacement}, applied
                before the layer's clamp and addition (a splice, e.g. an SAE's reconstruction at chosen positions).
            clamps: {layer: `Clamp`} of that layer's output (steering), applied before its addition.
        """
        wanted = set(layers)
        deepest = max(wanted)
        hidden, mask, position_ids, position_embeddings = self.layer_inputs(hidden, pad, attention)
        captured = {}
        for index in range(start, deepest + 1):
            hidden = self.layers[index](
                hidden,
                attention_mask=mask,
                position_ids=position_ids,
                position_embeddings=position_embeddings,
                past_key_values=cache,
            )
            if replace and index in replace:
                hidden = replace[index](hidden)
            if clamps and index in clamps:
                hidden = apply_clamp(hidden, clamps[index])
            if additions and index in additions:
                hidden = hidden + additions[index]
            if index in wanted:
                captured[index] = hidden
        return captured

    def layer_inputs(
        self, hidden: torch.Tensor, pad: torch.Tensor, attention: Attention
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """Return what every decoder layer takes besides its input: the input in the layers' dtype, the
        attention mask, position ids (B, S) and the rotary (cos, sin), each (B, S, head_dim)."""
        self.lm_config._attn_implementation = attention
        mask = attention_mask(pad, attention)
        position_ids = torch.cumsum(pad, dim=1) - 1  # (B, S): valid tokens numbered 0, 1, ...; pads repeat
        hidden = hidden.to(self.layers[0].self_attn.q_proj.weight.dtype)
        return hidden, mask, position_ids, self.rotary_emb(hidden, position_ids)

    def residuals(
        self,
        images: Sequence[torch.Tensor],
        image_masks: Sequence[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
        layers: Iterable[int],
        *,
        skip_masked_images: bool = True,
        trim_padding: bool = True,
        attention: Attention = "sdpa",
    ) -> dict[int, torch.Tensor]:
        """Return {layer: resid_post (B, n_images*tokens_per_image + T, width) float32} on the model's device.

        resid_post[L] is the output of decoder layer L (0-based; TransformerLens `blocks.L.hook_resid_post`),
        images first (camera order of `images`) then language. Rows of invalid positions are unspecified
        (zeros where skipped); callers read valid ones only.

        Args:
            images: per camera (B, 3, image_size, image_size) float in [-1, 1] (base, left wrist, right wrist).
            image_masks: per camera (B,) bool.
            tokens: (B, T) integer token ids; token_mask: (B, T) bool.
            layers: decoder layers to capture, all in one pass.
            skip_masked_images, trim_padding, attention: exact speed savings, on by default; turning them
                off reproduces openpi's full computation (used by the tests).
        """
        wanted = self.check_layers(layers)
        self.check_inputs(images, image_masks, tokens, token_mask)
        images, image_masks, tokens, token_mask = self.on_device(images, image_masks, tokens, token_mask)
        batch, n_tokens = tokens.shape
        total = self.arch.prefix_length(len(images), n_tokens)
        with torch.no_grad():
            hidden, pad, columns = self.embed_prefix(
                images,
                image_masks,
                tokens,
                token_mask,
                skip_masked_images=skip_masked_images,
                trim_padding=trim_padding,
            )
            # an empty prefix (every camera and token masked) has nothing to run through the layers
            captured = self.decode(hidden, pad, wanted, attention) if hidden.shape[1] else dict.fromkeys(wanted, hidden)
            if len(columns) == total:
                return {layer: captured[layer].float() for layer in wanted}
            out = {}
            for layer in wanted:
                full = hidden.new_zeros((batch, total, self.arch.width), dtype=torch.float32)
                full[:, columns] = captured[layer].float()
                out[layer] = full
            return out

    def check_layers(self, layers: Iterable[int]) -> list[int]:
        """Return the requested layers sorted, or raise naming the ones this model cannot produce."""
        wanted = sorted(set(layers))
        bad = [layer for layer in wanted if isinstance(layer, bool) or not isinstance(layer, int)]
        bad += [layer for layer in wanted if layer not in bad and not 0 <= layer <= self.max_layer]
        if not wanted or bad:
            raise ValueError(
                f"layers {wanted} invalid: need at least one decoder layer in 0..{self.max_layer} "
                f"(loaded with max_layer={self.max_layer}; the model has {self.arch.depth}); bad: {bad}; "
                f"reload with a larger max_layer for deeper layers"
            )
        return wanted

    def check_inputs(
        self,
        images: Sequence[torch.Tensor],
        image_masks: Sequence[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
    ) -> None:
        """Raise one ValueError listing every input whose shape, dtype or range is wrong."""
        problems = []
        if tokens.ndim != 2 or tokens.dtype.is_floating_point or tokens.dtype == torch.bool:
            problems.append(f"tokens: found {tuple(tokens.shape)} {tokens.dtype}, expected (B, T) int64")
        elif tokens.numel() and (int(tokens.min()) < 0 or int(tokens.max()) >= self.arch.vocab_size):
            problems.append(
                f"tokens: ids span {int(tokens.min())}..{int(tokens.max())}, expected 0..{self.arch.vocab_size - 1}"
            )
        batch = tokens.shape[0] if tokens.ndim else -1
        if token_mask.dtype != torch.bool or token_mask.shape != tokens.shape:
            problems.append(
                f"token_mask: found {tuple(token_mask.shape)} {token_mask.dtype}, expected {tuple(tokens.shape)} bool"
            )
        if len(images) != len(image_masks):
            problems.append(f"images: {len(images)} cameras but {len(image_masks)} image_masks")
        side = self.arch.image_size
        for slot, (image, mask) in enumerate(zip(images, image_masks)):
            if image.shape != (batch, 3, side, side) or not image.dtype.is_floating_point:
                problems.append(
                    f"images[{slot}]: found {tuple(image.shape)} {image.dtype}, expected ({batch}, 3, {side}, {side}) "
                    "float in [-1, 1] (see steering_core.pi05.preprocess)"
                )
            if mask.shape != (batch,) or mask.dtype != torch.bool:
                problems.append(
                    f"image_masks[{slot}]: found {tuple(mask.shape)} {mask.dtype}, expected ({batch},) bool"
                )
        if problems:
            raise ValueError("Pi05Prefix.residuals: " + "; ".join(problems))


class KeyValueRecorder:
    """Stands in for a transformers Cache in the prefix forward: keeps each layer's post-RoPE keys and
    values (B, kv_heads, S, head_dim) and returns them unchanged, so attention sees exactly the prefix."""

    def __init__(self) -> None:
        self.layers: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def update(self, keys: torch.Tensor, values: torch.Tensor, layer_idx: int, cache_kwargs: Any = None):
        self.layers[layer_idx] = (keys, values)
        return keys, values


def attention_mask(pad: torch.Tensor, attention: Attention) -> torch.Tensor:
    """Return the attention mask for pad mask (B, S) bool.

    "eager": openpi's (B, 1, S, S) float32 additive mask, 0 where pad[q] and pad[k], else -2.38e38.
    "sdpa": (B, 1, 1, S) bool key mask. Valid queries see exactly the same keys; padded queries (whose
    rows nobody reads) see the valid keys instead of nothing, which keeps them finite. A row with no
    valid token at all sees every key for the same reason.
    """
    if attention == "eager":
        allowed = pad[:, None, :, None] & pad[:, None, None, :]  # (B, 1, S, S)
        return torch.where(allowed, 0.0, MASKED_LOGIT).to(torch.float32)
    if attention == "sdpa":
        keys = pad | ~pad.any(dim=1, keepdim=True)  # (B, S)
        return keys[:, None, None, :]  # (B, 1, 1, S)
    raise ValueError(f"attention {attention!r} unknown; expected 'sdpa' or 'eager'")
