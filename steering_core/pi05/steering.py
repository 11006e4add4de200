"""Residual-stream steering of pi0.5: one layer's output at chosen positions moved along a vector.

Two modes: "add" adds `alpha * vector`; "clamp" sets the output's projection on the unit vector v̂ to the
target t = start + alpha * (end - start) of `levels = (start, end)`, h' = h + (t - <h, v̂>) v̂ (alpha 0
puts every steered token at `start`, 1 at `end`, wherever it was). At one layer clamps apply first, then
additions.

Two streams (spec 10.7): "lm", PaliGemma's language model, whose layer outputs exist only in the prefix
forward and reach the actions through deeper layers' keys and values; "expert", the action expert, whose
layer outputs are steered at every action token in every denoising step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Literal, NamedTuple

import torch

from steering_core.pi05.arch import ExpertArch, Pi05Arch

Stream = Literal["lm", "expert"]
Mode = Literal["add", "clamp"]
LAST_LM_LAYER = ("the last language-model layer's output only feeds the final norm, which no action reads, "
                 "so steering it cannot change the actions")
STREAMS: tuple[Stream, ...] = ("lm", "expert")
MODES: tuple[Mode, ...] = ("add", "clamp")
# |α| in residual_norm units (add) or level fractions (clamp): a shift 100 times the typical residual norm swamps
# the residual stream (the evaluation's grid stays within a few units); larger values only reach float overflow.
# The evaluation's and the rollouts' grids stay within it; it is the server's default --max-alpha.
MAX_ALPHA = 100.0


def check_alpha_grid(alphas: Sequence[float]) -> None:
    """Raise unless every α of a grid is finite and |α| <= `MAX_ALPHA`."""
    if not all(math.isfinite(alpha) for alpha in alphas):
        raise ValueError(f"alphas {list(alphas)} must be finite numbers")
    if (largest := max((abs(alpha) for alpha in alphas), default=0.0)) > MAX_ALPHA:
        raise ValueError(f"alphas hold |α| = {largest:g}, above {MAX_ALPHA:g} (units of the mean residual norm, or "
                         f"level fractions for clamp): a larger shift swamps the residual stream; give values within "
                         f"±{MAX_ALPHA:g}")


@dataclass(frozen=True, eq=False)
class Steering:
    """Steer the output (resid_post) of decoder layer `layer` of `stream` along `vector`.

    mode "add": add `alpha * vector`. mode "clamp": set the projection on vector/|vector| to
    `start + alpha * (end - start)` of `levels = (start, end)` (module docstring).
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
    mode: Mode = "add"
    levels: tuple[float, float] | None = None

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
        if self.mode not in MODES:
            problems.append(f"mode {self.mode!r} unknown; expected one of {MODES}")
        elif self.mode == "add" and self.levels is not None:
            problems.append(f"levels apply to mode 'clamp' only; mode 'add' takes none, found {self.levels!r}")
        elif self.mode == "clamp":
            problems += self._clamp_problems()
        if problems:
            raise ValueError("Steering: " + "; ".join(problems))

    def _clamp_problems(self) -> list[str]:
        """Return what keeps this steering from clamping: its levels or a vector without a direction."""
        problems = []
        levels = self.levels
        numbers = isinstance(levels, (tuple, list)) and len(levels) == 2 and all(
            isinstance(level, (int, float)) and not isinstance(level, bool) and math.isfinite(level) for level in levels)
        if not numbers:
            problems.append(f"clamp needs levels (m₋, m₊), two finite numbers; found {levels!r}")
        elif levels[0] == levels[1]:
            problems.append(f"clamp needs two different levels (m₋, m₊); found equal levels {levels[0]!r}: the "
                            "concepts do not differ along this direction")
        if isinstance(self.vector, torch.Tensor) and self.vector.ndim == 1 and self.vector.is_floating_point():
            norm = float(self.vector.float().norm())
            if not (math.isfinite(norm) and norm > 0):
                problems.append(f"clamp needs a vector with a direction; found norm {norm}")
        return problems

    def to(self, device: torch.device) -> Steering:
        """Return this steering with its vector and masks on `device` (the model's entry points call it)."""
        moved = {name: getattr(self, name).to(device) for name in ("vector", "token_mask", "prefix_mask")
                 if getattr(self, name) is not None}
        return replace(self, **moved)

    def delta(self, dtype: torch.dtype) -> torch.Tensor:
        """Return alpha * vector (W,) computed in float32, then cast to the stream's dtype."""
        return (self.alpha * self.vector.float()).to(dtype)

    def clamp(self, where: torch.Tensor | None = None) -> Clamp:
        """Return this clamp as a `Clamp`: unit vector (1, 1, W) and target (1, 1, 1) float32, acting where
        `where` is 1 (None = everywhere)."""
        vector = self.vector.float()
        unit = vector / vector.norm()
        return Clamp(unit[None, None], unit.new_full((1, 1, 1), self.target), where)

    @property
    def target(self) -> float:
        """Return the projection a clamp sets: start + alpha * (end - start)."""
        start, end = self.levels
        return start + self.alpha * (end - start)


class Clamp(NamedTuple):
    """Per layer, each row's projection on its unit vector set to its target where `where` is 1:
    h' = h + where * (target - <h, unit>) * unit, in float32, cast back. A zero unit leaves its row unchanged.

    unit (rows, 1, W) float32; target (rows, 1, 1) float32; where (rows, S, 1) float32, None = every position.
    """

    unit: torch.Tensor
    target: torch.Tensor
    where: torch.Tensor | None = None


def apply_clamp(hidden: torch.Tensor, clamp: Clamp) -> torch.Tensor:
    """Return `hidden` (rows, S, W) with `clamp` applied (its docstring), in hidden's dtype."""
    wide = hidden.float()
    shift = clamp.target - (wide * clamp.unit).sum(dim=-1, keepdim=True)
    if clamp.where is not None:
        shift = shift * clamp.where
    return (wide + shift * clamp.unit).to(hidden.dtype)


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
    entries: Sequence[Sequence[Steering]], arch: Pi05Arch, expert: ExpertArch, batch: int, n_tokens: int,
    n_images: int,
) -> None:
    """Raise one ValueError naming every steering whose layer, vector width or mask shape does not fit, that
    steers the last language-model layer (it cannot change the actions), or that is an entry's second clamp
    of one layer. Steerings are numbered across the entries in order."""
    widths = {"lm": arch.width, "expert": expert.width}
    depths = {"lm": arch.depth, "expert": expert.depth}
    prefix_len = arch.prefix_length(n_images, n_tokens)
    problems = []
    clamped: dict[tuple[int, Stream, int], int] = {}  # (entry, stream, layer) -> the index of its clamp
    numbered = [(entry, item) for entry, items in enumerate(entries) for item in items]
    for index, (entry, item) in enumerate(numbered):
        if item.mode == "clamp":
            first = clamped.setdefault((entry, item.stream, item.layer), index)
            if first != index:
                problems.append(f"steering[{first}] and steering[{index}] ({item.stream} layer {item.layer}): two "
                                "clamps of one layer in one entry; give at most one")
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


def lm_positions(
    item: Steering, token_mask: torch.Tensor, columns: torch.Tensor, n_image_columns: int
) -> torch.Tensor:
    """Return (B, S, 1) float32: 1 at the computed prefix columns an lm steering acts on.

    columns: (S,) index of each computed column in the full prefix (`Pi05Prefix.embed_prefix`); positions
    that were not computed (a skipped camera, trimmed padding) are invalid and need no steering. Every
    tensor is on the model's device (`Steering.to`).
    """
    if item.prefix_mask is not None:
        where = item.prefix_mask
    else:
        prompt = token_mask if item.token_mask is None else item.token_mask
        where = torch.cat([prompt.new_zeros(prompt.shape[0], n_image_columns), prompt], dim=1)
    return where[:, columns, None].float()


def lm_additions(
    steerings: Sequence[Steering],
    token_mask: torch.Tensor,
    columns: torch.Tensor,
    n_image_columns: int,
    dtype: torch.dtype,
) -> dict[int, torch.Tensor]:
    """Return {lm layer: (B, S, width) tensor to add to that layer's output} over the computed prefix columns
    (`lm_positions`), summed over the entry's "add" steerings."""
    additions: dict[int, torch.Tensor] = {}
    for item in steerings:
        if item.stream == "lm" and item.mode == "add":
            delta = lm_positions(item, token_mask, columns, n_image_columns).to(dtype) * item.delta(dtype)
            additions[item.layer] = additions[item.layer] + delta if item.layer in additions else delta
    return additions


def expert_additions(steerings: Sequence[Steering], dtype: torch.dtype) -> dict[int, torch.Tensor]:
    """Return {expert layer: (1, 1, width) tensor added to that layer's output at every action token}."""
    additions: dict[int, torch.Tensor] = {}
    for item in steerings:
        if item.stream == "expert" and item.mode == "add":
            delta = item.delta(dtype)[None, None]
            additions[item.layer] = additions[item.layer] + delta if item.layer in additions else delta
    return additions


def lm_clamps(
    steerings: Sequence[Steering], token_mask: torch.Tensor, columns: torch.Tensor, n_image_columns: int
) -> dict[int, Clamp]:
    """Return {lm layer: Clamp (unit (1, 1, W), target (1, 1, 1), where (B, S, 1))} of an entry's clamps."""
    return {item.layer: item.clamp(lm_positions(item, token_mask, columns, n_image_columns))
            for item in steerings if item.stream == "lm" and item.mode == "clamp"}


def expert_clamps(steerings: Sequence[Steering]) -> dict[int, Clamp]:
    """Return {expert layer: Clamp (unit (1, 1, W), target (1, 1, 1)) at every action token} of an entry's
    clamps."""
    return {item.layer: item.clamp() for item in steerings if item.stream == "expert" and item.mode == "clamp"}


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


def stack_clamps(entries: Sequence[Mapping[int, Clamp]], batch: int) -> dict[int, Clamp]:
    """Return per-layer clamps for entries stacked along the batch as `stack_entries` stacks additions: an
    entry without a clamp at a layer gets a zero unit there (its rows unchanged)."""
    fields = [stack_entries([{layer: clamp[field] for layer, clamp in entry.items() if clamp[field] is not None}
                             for entry in entries], batch) for field in range(len(Clamp._fields))]
    return {layer: Clamp(*(stacked.get(layer) for stacked in fields)) for layer in fields[0]}
