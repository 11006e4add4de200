"""pi0.5's denoising loop (spec 10.4): `num_steps` Euler steps of the action expert, eager or compiled.

On a GPU at batch 1 the loop is bound by Python and kernel launches (10 steps x 18 expert layers), not by
its arithmetic. `Denoiser` with `compiled=True` runs each step as one `torch.compile`d function of fixed
shapes (`dynamic=False`): on CUDA with mode "reduce-overhead", whose inductor kernels are replayed as one
CUDA graph per step; on a CPU plain inductor. The Python loop over the steps stays: ten graph replays
cost little.

The step's shapes would vary with the computed prefix length (a camera masked for the whole batch is
skipped, language padding after the longest prompt is trimmed) and with which expert layers are steered.
The compiled step therefore sees the cache and mask padded to the untrimmed prefix length with masked zero
columns (their softmax weight is exactly 0, so the valid outputs are unchanged), the expert additions as
one dense (depth, rows, 1, width) tensor, zero at unsteered layers (x + 0 = x), and the expert clamps as dense
unit vectors (depth, rows, 1, width) and targets (depth, rows, 1, 1), zero units at unclamped layers and rows
(h + (t - 0) * 0 = h): one compiled graph serves every steering, clamped or not. A policy compiles one
variant per (row bucket, untrimmed prefix length): rows are padded with zero rows up to 1, 2, 4, 8 or 16
(`ROW_BUCKETS`), so a server batching up to 16 requests compiles five variants, all at its warm-up. At most
`max_variants` are compiled, each of at most `max_rows` rows (larger batches are bound by arithmetic, not
launches); other shapes run eagerly, so a process's compiled code and graph memory cannot grow without bound. While a forward
hook watches the expert (capture records its layer outputs so) the loop runs eagerly: dynamo does not guard
on hooks added after it traced a module, so a compiled step would skip them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence

import torch
import torch.nn.functional as F

from steering_core.pi05.expert import ActionExpert, KeyValues
from steering_core.pi05.model import MASKED_LOGIT
from steering_core.pi05.steering import Clamp

logger = logging.getLogger(__name__)

# "reduce-overhead" = inductor + CUDA graphs; openpi's "max-autotune" adds minutes of kernel autotuning at
# start-up for the same launch savings at batch 1
CUDA_COMPILE_MODE = "reduce-overhead"
MAX_COMPILED_VARIANTS = 8  # distinct (rows, prefix length) compiled per policy; dynamo's own recompile_limit is 8
# more rows are bound by arithmetic, not launches; and CUDA graphs copy the padded KV cache into static
# buffers of their own, 18 MB per row at real size (an evaluation sweep of 320 rows: 5.7 GB per variant)
MAX_COMPILED_ROWS = 16
# rows are padded up to one of these sizes (zero rows, dropped after): a server batching 1..16 requests compiles
# five variants, all at its warm-up, instead of one per batch size as they arrive
ROW_BUCKETS = (1, 2, 4, 8, 16)

Step = Callable[..., torch.Tensor]


def pad_prefix(keys_values: KeyValues, mask: torch.Tensor, length: int) -> tuple[KeyValues, torch.Tensor]:
    """Return the cache padded to `length` prefix columns and the mask with those columns masked.

    keys_values: per layer (B, kv_heads, P, head_dim) keys and values; mask: (B, 1, 1, P + H) float32
    additive over [prefix keys | action keys]. The padding columns (zero keys and values) go between the
    prefix and the action keys, where the expert's attention concatenates them.
    """
    cached = keys_values[0][0].shape[2]
    extra = length - cached
    if extra < 0:
        raise ValueError(f"pad_prefix: the cache has {cached} columns, more than the {length} to pad to")
    if extra == 0:
        return keys_values, mask
    padded = [tuple(F.pad(tensor, (0, 0, 0, extra)) for tensor in layer) for layer in keys_values]
    masked = mask.new_full((*mask.shape[:-1], extra), MASKED_LOGIT)
    return padded, torch.cat([mask[..., :cached], masked, mask[..., cached:]], dim=-1)


def row_bucket(rows: int, max_rows: int = MAX_COMPILED_ROWS) -> int | None:
    """Return the compiled row count a batch of `rows` runs at (the smallest bucket holding it), or None past
    `max_rows` (run eagerly)."""
    return next((bucket for bucket in ROW_BUCKETS if rows <= bucket <= max_rows), None)


def pad_rows(tensor: torch.Tensor, rows: int) -> torch.Tensor:
    """Return `tensor` with zero rows appended along dim 0 up to `rows` (rows of a batch never mix: the added
    ones only cost their arithmetic)."""
    extra = rows - tensor.shape[0]
    return tensor if extra == 0 else torch.cat([tensor, tensor.new_zeros((extra, *tensor.shape[1:]))])


def dense_additions(
    additions: Mapping[int, torch.Tensor], depth: int, rows: int, width: int, dtype: torch.dtype,
    device: torch.device,
) -> torch.Tensor:
    """Return (depth, rows, 1, width): each steered layer's addition (or a clamp's unit vectors or targets,
    width 1) broadcast from (1 or rows, 1, width), zeros at the others."""
    dense = torch.zeros(depth, rows, 1, width, dtype=dtype, device=device)
    for layer, addition in additions.items():
        dense[layer] = addition
    return dense


def has_hooks(module: torch.nn.Module) -> bool:
    """Return whether a forward hook (global, or on `module` or a submodule) would see `module` run."""
    hooks = torch.nn.modules.module
    if hooks._global_forward_hooks or hooks._global_forward_pre_hooks:
        return True
    return any(m._forward_hooks or m._forward_pre_hooks for m in module.modules())


def compile_step(expert: ActionExpert, mode: str | None) -> Step:
    """Return `expert.euler_step` compiled for fixed shapes, taking the additions, the clamps' unit vectors and
    their targets as dense tensors (`dense_additions`)."""

    def step(actions, time, dt, rotary, keys_values, mask, additions, units, targets):
        clamps = dict(enumerate(map(Clamp, units.unbind(0), targets.unbind(0))))
        return expert.euler_step(actions, time, dt, rotary, keys_values, mask, dict(enumerate(additions.unbind(0))),
                                 clamps)

    return torch.compile(step, mode=mode, dynamic=False, fullgraph=True)


class Denoiser:
    """The Euler loop of one expert; `compiled` runs the compiled step (built on first use) for up to
    `max_variants` shapes of at most `max_rows` rows (module docstring)."""

    def __init__(self, expert: ActionExpert, compiled: bool, max_variants: int = MAX_COMPILED_VARIANTS,
                 max_rows: int = MAX_COMPILED_ROWS):
        self.expert = expert
        self.compiled = compiled
        self.max_variants, self.max_rows = max_variants, max_rows
        self.variants: set[tuple[int, int]] = set()  # (rows, prefix length) the compiled step has run
        self.refused: set[tuple[int, int]] = set()  # shapes past the bound, run eagerly
        self._step: Step | None = None

    def run(
        self,
        actions: torch.Tensor,
        times: Sequence[torch.Tensor],
        dt: torch.Tensor,
        rotary: tuple[torch.Tensor, torch.Tensor],
        keys_values: KeyValues,
        mask: torch.Tensor,
        additions: Mapping[int, torch.Tensor],
        clamps: Mapping[int, Clamp],
        prefix_length: int,
    ) -> torch.Tensor:
        """Return the actions (rows, H, action_dim) float32 after one Euler step per flow time in `times`.

        actions: the noise (rows, H, action_dim) float32; rotary, keys_values, mask: as `ActionExpert.velocity`;
        additions: {expert layer: (rows, 1, width)} steering; clamps: {expert layer: `Clamp` of (rows, 1, width)
        units and (rows, 1, 1) targets}; prefix_length: the untrimmed prefix length the compiled step pads the
        cache to.
        """
        bucket = row_bucket(actions.shape[0], self.max_rows)
        variant = (bucket, prefix_length)
        # a compiled graph would not run hooks added after it was traced (capture's recorders)
        compiled = self.compiled and bucket is not None and not has_hooks(self.expert)
        if compiled and variant not in self.variants and len(self.variants) >= self.max_variants:
            if variant not in self.refused:
                self.refused.add(variant)
                logger.warning("denoising %s eagerly: %d shapes (rows, prefix length) compiled already, the "
                               "most per policy", variant, self.max_variants)
        elif compiled:
            self.variants.add(variant)
            return self._run_compiled(actions, times, dt, rotary, keys_values, mask, additions, clamps, prefix_length,
                                      bucket)
        for time in times:
            actions = self.expert.euler_step(actions, time, dt, rotary, keys_values, mask, additions, clamps)
        return actions

    def _run_compiled(self, actions, times, dt, rotary, keys_values, mask, additions, clamps, prefix_length, bucket):
        if self._step is None:
            self._step = compile_step(self.expert, CUDA_COMPILE_MODE if actions.device.type == "cuda" else None)
        rows = actions.shape[0]
        keys_values, mask = pad_prefix(keys_values, mask, prefix_length)
        keys_values = [tuple(pad_rows(tensor, bucket) for tensor in layer) for layer in keys_values]
        mask, rotary = pad_rows(mask, bucket), tuple(pad_rows(tensor, bucket) for tensor in rotary)
        arch = self.expert.expert_arch
        dense = [dense_additions(layers, arch.depth, rows, width, dtype, actions.device) for layers, width, dtype in (
            (additions, arch.width, self.expert.compute_dtype),
            ({layer: clamp.unit for layer, clamp in clamps.items()}, arch.width, torch.float32),
            ({layer: clamp.target for layer, clamp in clamps.items()}, 1, torch.float32))]
        # each (depth, bucket, 1, width or 1)
        dense = [pad_rows(tensor.transpose(0, 1), bucket).transpose(0, 1).contiguous() for tensor in dense]
        actions = pad_rows(actions, bucket)
        for time in times:
            # a CUDA graph's outputs are overwritten by its next replay: start a new step, keep a copy
            torch.compiler.cudagraph_mark_step_begin()
            actions = self._step(actions, time, dt, rotary, keys_values, mask, *dense).clone()
        return actions[:rows]
