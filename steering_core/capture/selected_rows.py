"""Capture's forward: the residuals of the selected rows only, never a (batch, prefix, width) tensor per layer.

The deepest captured layer runs its queries, attention output and MLP for the selected rows alone (keys and
values still from every valid token), which is most of a capture's saving at instruction tokens (spec 14).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:  # transformers costs seconds: imported when a capture runs, not when the CLI starts
    from transformers.models.gemma.modeling_gemma import GemmaDecoderLayer

    from steering_core.pi05.arch import Pi05Arch
    from steering_core.pi05.model import Attention, Pi05Prefix


def selected_residuals(
    model: Pi05Prefix,
    images: Sequence[torch.Tensor],
    image_masks: Sequence[torch.Tensor],
    tokens: torch.Tensor,
    token_mask: torch.Tensor,
    layers: Iterable[int],
    frame_of_row: torch.Tensor,
    positions: torch.Tensor,
    *,
    attention: Attention = "sdpa",
) -> dict[int, torch.Tensor]:
    """Return {layer: (n, width) float32} resid_post of the n rows (frame_of_row[i], positions[i]) only.

    The rows `residuals` would return at [frame_of_row, positions] (positions in the full prefix,
    valid tokens only), without ever holding a (B, prefix, width) tensor per layer: each layer's rows
    are gathered as it is produced, and the deepest layer computes its queries, attention output and
    MLP for the selected rows alone (keys and values still from every valid token). Rows of layers
    before the deepest are bit-identical to `residuals`'; the deepest layer's agree to rounding.

    Args:
        model: the prefix model.
        images, image_masks, tokens, token_mask, layers, attention: as for `model.residuals` (masked cameras
            skipped and padding trimmed).
        frame_of_row: (n,) int64 batch index of each row; positions: (n,) int64 prefix position.
    """
    wanted = model.check_layers(layers)
    model.check_inputs(images, image_masks, tokens, token_mask)
    images, image_masks, tokens, token_mask = model.on_device(images, image_masks, tokens, token_mask)
    frame_of_row, positions = frame_of_row.to(model.device, torch.long), positions.to(model.device, torch.long)
    with torch.no_grad():
        hidden, pad, columns = model.embed_prefix(images, image_masks, tokens, token_mask)
        query_columns, slot_of_row = _query_columns(model.arch, pad, columns, len(images), tokens.shape[1],
                                                    frame_of_row, positions)
        out, start = {}, 0
        for layer in wanted[:-1]:
            hidden = model.decode(hidden, pad, [layer], attention, start=start)[layer]
            out[layer] = hidden[frame_of_row, query_columns[frame_of_row, slot_of_row]].float()
            start = layer + 1
        deepest = wanted[-1]
        if deepest > start:
            hidden = model.decode(hidden, pad, [deepest - 1], attention, start=start)[deepest - 1]
        hidden, mask, _, position_embeddings = model.layer_inputs(hidden, pad, attention)
        rows = _selected_rows_layer(model.layers[deepest], hidden, mask, position_embeddings, query_columns)
        out[deepest] = rows[frame_of_row, slot_of_row].float()
        return out

def _query_columns(
    arch: Pi05Arch, pad: torch.Tensor, columns: torch.Tensor, n_images: int, n_tokens: int,
    frame_of_row: torch.Tensor, positions: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (B, Lq) computed columns of each frame's selected rows (padded with a repeat of its first
    row, or column 0 for a frame without rows) and the slot (n,) of each row in its frame's list.

    Raises ValueError when a row is not a valid token of its frame (a masked camera or padding).
    """
    batch = pad.shape[0]
    total = arch.prefix_length(n_images, n_tokens)
    bad = (frame_of_row < 0) | (frame_of_row >= batch) | (positions < 0) | (positions >= total)
    lookup = torch.full((total,), -1, dtype=torch.long, device=pad.device)
    lookup[columns] = torch.arange(len(columns), device=pad.device)
    found = lookup[positions.clamp(0, total - 1)]
    bad |= found < 0
    bad |= ~pad[frame_of_row.clamp(0, batch - 1), found.clamp(min=0)]
    if bool(bad.any()):
        at = int(bad.nonzero()[0])
        raise ValueError(
            f"selected_residuals: row {at} (frame {int(frame_of_row[at])}, position "
            f"{int(positions[at])}) is not a valid token of a {batch}-frame batch with {total}-token prefixes "
            f"({int(bad.sum())} such rows); select image tokens of present cameras and unpadded language tokens"
        )
    counts = torch.bincount(frame_of_row, minlength=batch)
    order = torch.sort(frame_of_row, stable=True).indices
    first = torch.cumsum(counts, 0) - counts  # first position of each frame in `order`
    slot_of_row = torch.empty_like(frame_of_row)
    slot_of_row[order] = torch.arange(len(order), device=pad.device) - first[frame_of_row[order]]
    width = max(int(counts.max()) if len(counts) else 0, 1)
    query_columns = torch.zeros(batch, width, dtype=torch.long, device=pad.device)
    query_columns[frame_of_row, slot_of_row] = found
    padding = torch.arange(width, device=pad.device)[None, :] >= counts[:, None]
    query_columns = torch.where(padding, query_columns[:, :1], query_columns)
    return query_columns, slot_of_row


def _selected_rows_layer(
    layer: GemmaDecoderLayer,
    hidden: torch.Tensor,
    mask: torch.Tensor,
    position_embeddings: tuple[torch.Tensor, torch.Tensor],
    query_columns: torch.Tensor,
) -> torch.Tensor:
    """Return a Gemma decoder layer's output (B, Lq, width) at columns `query_columns` (B, Lq) only.

    The same operations as `GemmaDecoderLayer.forward` (and the same attention function), but keys and
    values are projected for every column while the queries, the attention output, the residual adds and
    the MLP run for the selected columns alone. `hidden` (B, S, width), `mask` and `position_embeddings`
    come from `Pi05Prefix.layer_inputs`.
    """
    from transformers.modeling_utils import ALL_ATTENTION_FUNCTIONS
    from transformers.models.gemma.modeling_gemma import eager_attention_forward

    attention = layer.self_attn
    batch, length = query_columns.shape
    head_dim = attention.head_dim

    def take(values: torch.Tensor) -> torch.Tensor:  # (B, S, d) -> (B, Lq, d)
        return values.gather(1, query_columns[..., None].expand(batch, length, values.shape[-1]))

    normed = layer.input_layernorm(hidden)
    queries = attention.q_proj(take(normed)).view(batch, length, -1, head_dim).transpose(1, 2)
    keys = attention.k_proj(normed).view(batch, normed.shape[1], -1, head_dim).transpose(1, 2)
    values = attention.v_proj(normed).view(batch, normed.shape[1], -1, head_dim).transpose(1, 2)
    cos, sin = position_embeddings
    queries, keys = _rotate(queries, take(cos), take(sin)), _rotate(keys, cos, sin)
    if mask.shape[2] > 1:  # eager: (B, 1, S, S) additive mask, one row per query
        mask = mask.gather(2, query_columns[:, None, :, None].expand(batch, 1, length, mask.shape[3]))
    implementation = attention.config._attn_implementation
    interface = eager_attention_forward if implementation == "eager" else ALL_ATTENTION_FUNCTIONS[implementation]
    mixed, _ = interface(attention, queries, keys, values, mask, dropout=0.0, scaling=attention.scaling)
    after_attention = take(hidden) + attention.o_proj(mixed.reshape(batch, length, -1))
    return after_attention + layer.mlp(layer.post_attention_layernorm(after_attention))


def _rotate(states: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Return rotary-embedded states (B, heads, L, head_dim) for cos, sin (B, L, head_dim): the operations
    of transformers' `apply_rotary_pos_emb`, for one tensor at a time."""
    from transformers.models.gemma.modeling_gemma import rotate_half

    return (states * cos[:, None]) + (rotate_half(states) * sin[:, None])
