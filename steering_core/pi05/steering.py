"""Residual-stream steering of pi0.5: `alpha * vector` added to one layer's output at chosen positions.

Two streams (spec 10.7): "lm", PaliGemma's language model, whose layer outputs exist only in the prefix
forward and reach the actions through deeper layers' keys and values; "expert", the action expert, whose
layer outputs are steered at every action token in every denoising step.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import torch

from steering_core.pi05.arch import ExpertArch, Pi05Arch

Stream = Literal["lm", "expert"]
LAST_LM_LAYER = ("the last language-model layer's output only feeds the final norm, which no action reads, "
                 "so steering it cannot change the actions")
STREAMS: tuple[Stream, ...] = ("lm", "expert")


@dataclass(frozen=True, eq=False)
class Steering:
    """Add `alpha * vector` to the output (resid_post) of decoder layer `layer` of `stream`.

    lm: at the prompt positions where `token_mask` (B, T) is True, or the prefix positions where
    `prefix_mask` (B, n_images * tokens_per_image + T) is True; neither = every valid prompt token.
    expert: at every action token in every denoising step (no masks).
    """

    layer: int
    vector: torch.Tensor  # (width of the stream,)
    alpha: float = 1.0
    token_mask: torch.Tensor | None = None
    prefix_mask: torch.Tensor | None = None
    stream: Stream = "lm"

    def __post_init__(self) -> None:
        problems = []
        if isinstance(self.layer, bool) or not isinstance(self.layer, int) or self.layer < 0:
            problems.append(f"layer {self.layer!r} must be a non-negative integer")
        if not isinstance(self.vector, torch.Tensor) or self.vector.ndim != 1 or not self.vector.is_floating_point():
            found = tuple(self.vector.shape) if isinstance(self.vector, torch.Tensor) else type(self.vector).__name__
            problems.append(f"vector must be a 1-D floating-point tensor, found {found}")
        if isinstance(self.alpha, bool) or not isinstance(self.alpha, (int, float)):
            problems.append(f"alpha {self.alpha!r} must be a number")
        if self.stream not in STREAMS:
            problems.append(f"stream {self.stream!r} unknown; expected one of {STREAMS}")
        for name in ("token_mask", "prefix_mask"):
            mask = getattr(self, name)
            if mask is not None and (not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.ndim != 2):
                found = f"{tuple(mask.shape)} {mask.dtype}" if isinstance(mask, torch.Tensor) else type(mask).__name__
                problems.append(f"{name} must be a 2-D bool tensor, found {found}")
        if self.token_mask is not None and self.prefix_mask is not None:
            problems.append("give token_mask or prefix_mask, not both")
        if self.stream == "expert" and (self.token_mask is not None or self.prefix_mask is not None):
            problems.append("expert steering applies at every action token; it takes no token_mask or prefix_mask")
        if problems:
            raise ValueError("Steering: " + "; ".join(problems))

    def to(self, device: torch.device) -> Steering:
        """Return this steering with its vector and masks on `device` (the model's entry points call it)."""
        moved = {name: getattr(self, name).to(device) for name in ("vector", "token_mask", "prefix_mask")
                 if getattr(self, name) is not None}
        return replace(self, **moved)

    def delta(self, dtype: torch.dtype) -> torch.Tensor:
        """Return alpha * vector (W,) computed in float32, then cast to the stream's dtype."""
        return (self.alpha * self.vector.float()).to(dtype)


@dataclass(frozen=True, eq=False)
class Splice:
    """Replace the output (resid_post) of language-model layer `layer` by `replace` of it at chosen prompt positions.

    `replace` maps the selected rows (n, width) float32 to (n, width) (an SAE's reconstruction, zeros for an
    ablation); the rows are those where `token_mask` (B, T) is True, in row-major (batch, position) order;
    None = every valid prompt token. Unselected positions keep their residuals.
    """

    layer: int
    replace: Callable[[torch.Tensor], torch.Tensor]
    token_mask: torch.Tensor | None = None

    def __post_init__(self) -> None:
        problems = []
        if isinstance(self.layer, bool) or not isinstance(self.layer, int) or self.layer < 0:
            problems.append(f"layer {self.layer!r} must be a non-negative integer")
        if not callable(self.replace):
            problems.append(f"replace must be a function of the rows, found {type(self.replace).__name__}")
        mask = self.token_mask
        if mask is not None and (not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.ndim != 2):
            found = f"{tuple(mask.shape)} {mask.dtype}" if isinstance(mask, torch.Tensor) else type(mask).__name__
            problems.append(f"token_mask must be a 2-D bool tensor, found {found}")
        if problems:
            raise ValueError("Splice: " + "; ".join(problems))

    def to(self, device: torch.device) -> Splice:
        """Return this splice with its mask on `device` (the model's entry points call it)."""
        return self if self.token_mask is None else replace(self, token_mask=self.token_mask.to(device))

    def check(self, arch: Pi05Arch, batch: int, n_tokens: int) -> None:
        """Raise one ValueError if the layer is not a language-model layer below the last, or the mask misfits."""
        problems = []
        if self.layer >= arch.depth:
            problems.append(f"layer out of range, the lm stream has {arch.depth} layers (0..{arch.depth - 1})")
        elif self.layer == arch.depth - 1:
            problems.append(f"{LAST_LM_LAYER}; splice a layer below {self.layer}")
        if self.token_mask is not None and tuple(self.token_mask.shape) != (batch, n_tokens):
            problems.append(f"token_mask is {tuple(self.token_mask.shape)}, expected {(batch, n_tokens)}")
        if problems:
            raise ValueError(f"splice (lm layer {self.layer}): " + "; ".join(problems))

    def layer_function(
        self, token_mask: torch.Tensor, columns: torch.Tensor, n_image_columns: int
    ) -> Callable[[torch.Tensor], torch.Tensor]:
        """Return the map of the layer's output (n * B, S, width) over the computed prefix `columns` (S,): the
        selected rows replaced, the rest unchanged; n copies of the batch (a sweep's entries) are each spliced."""
        prompt = token_mask if self.token_mask is None else self.token_mask
        where = torch.cat([prompt.new_zeros(prompt.shape[0], n_image_columns), prompt], dim=1)[:, columns]  # (B, S)

        def splice(hidden: torch.Tensor) -> torch.Tensor:
            selected = where.repeat(hidden.shape[0] // where.shape[0], 1)  # (n * B, S)
            rows = hidden[selected].float()  # (rows, width)
            new = self.replace(rows)
            if not isinstance(new, torch.Tensor) or tuple(new.shape) != tuple(rows.shape):
                found = tuple(new.shape) if isinstance(new, torch.Tensor) else type(new).__name__
                raise ValueError(f"splice (lm layer {self.layer}): replace returned {found}, expected "
                                 f"{tuple(rows.shape)} (one row per selected position)")
            out = hidden.clone()
            out[selected] = new.to(device=hidden.device, dtype=hidden.dtype)
            return out

        return splice


SteeringArg = Steering | Sequence[Steering] | None


def as_list(steering: SteeringArg) -> list[Steering]:
    """Return `steering` as a list (None -> [])."""
    if steering is None:
        return []
    items = [steering] if isinstance(steering, Steering) else list(steering)
    bad = [type(item).__name__ for item in items if not isinstance(item, Steering)]
    if bad:
        raise ValueError(f"steering must be a Steering, a list of Steering or None; found {', '.join(bad)}")
    return items


def check_steerings(
    steerings: Sequence[Steering], arch: Pi05Arch, expert: ExpertArch, batch: int, n_tokens: int, n_images: int
) -> None:
    """Raise one ValueError naming every steering whose layer, vector width or mask shape does not fit, or that
    steers the last language-model layer (it cannot change the actions)."""
    widths = {"lm": arch.width, "expert": expert.width}
    depths = {"lm": arch.depth, "expert": expert.depth}
    prefix_len = arch.prefix_length(n_images, n_tokens)
    problems = []
    for index, item in enumerate(steerings):
        where = f"steering[{index}] ({item.stream} layer {item.layer})"
        if item.layer >= depths[item.stream]:
            problems.append(
                f"{where}: layer out of range, the {item.stream} stream has {depths[item.stream]} layers "
                f"(0..{depths[item.stream] - 1})"
            )
        elif item.stream == "lm" and item.layer == arch.depth - 1:
            problems.append(f"{where}: {LAST_LM_LAYER}; steer a layer below {item.layer}")
        width = item.vector.shape[0]
        if width != widths[item.stream]:
            fits = [stream for stream, w in widths.items() if w == width]
            hint = f"; a width-{width} vector fits the {fits[0]} stream" if fits else ""
            problems.append(
                f"{where}: vector width {width}, expected {widths[item.stream]} for the {item.stream} stream{hint}"
            )
        for name, shape in (("token_mask", (batch, n_tokens)), ("prefix_mask", (batch, prefix_len))):
            mask = getattr(item, name)
            if mask is not None and tuple(mask.shape) != shape:
                problems.append(f"{where}: {name} is {tuple(mask.shape)}, expected {shape}")
    if problems:
        raise ValueError("; ".join(problems))


def lm_additions(
    steerings: Sequence[Steering],
    token_mask: torch.Tensor,
    columns: torch.Tensor,
    n_image_columns: int,
    dtype: torch.dtype,
) -> dict[int, torch.Tensor]:
    """Return {lm layer: (B, S, width) tensor to add to that layer's output} over the computed prefix columns.

    columns: (S,) index of each computed column in the full prefix (`Pi05Prefix.embed_prefix`); positions
    that were not computed (a skipped camera, trimmed padding) are invalid and need no steering. Every
    tensor is on the model's device (`Steering.to`).
    """
    additions: dict[int, torch.Tensor] = {}
    for item in steerings:
        if item.stream != "lm":
            continue
        if item.prefix_mask is not None:
            where = item.prefix_mask
        else:
            prompt = token_mask if item.token_mask is None else item.token_mask
            where = torch.cat([prompt.new_zeros(prompt.shape[0], n_image_columns), prompt], dim=1)
        delta = where[:, columns, None].to(dtype) * item.delta(dtype)
        additions[item.layer] = additions[item.layer] + delta if item.layer in additions else delta
    return additions


def expert_additions(steerings: Sequence[Steering], dtype: torch.dtype) -> dict[int, torch.Tensor]:
    """Return {expert layer: (1, 1, width) tensor added to that layer's output at every action token}."""
    additions: dict[int, torch.Tensor] = {}
    for item in steerings:
        if item.stream == "expert":
            delta = item.delta(dtype)[None, None]
            additions[item.layer] = additions[item.layer] + delta if item.layer in additions else delta
    return additions


def stack_entries(entries: Sequence[Mapping[int, torch.Tensor]], batch: int) -> dict[int, torch.Tensor]:
    """Return per-layer additions for entries stacked along the batch (entry-major, `batch` rows each).

    Each entry maps layer -> tensor with a leading dim of 1 or `batch`; entries without a layer add zeros.
    """
    layers = sorted({layer for entry in entries for layer in entry})
    stacked = {}
    for layer in layers:
        template = next(entry[layer] for entry in entries if layer in entry)
        shape = (batch, *template.shape[1:])
        blocks = [entry[layer].expand(shape) if layer in entry else template.new_zeros(shape) for entry in entries]
        stacked[layer] = torch.cat(blocks)
    return stacked
