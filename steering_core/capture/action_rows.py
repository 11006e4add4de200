"""Rows of the action token types: the expert's decision residual and its adaRMS conditioning per denoising step.

`decision`: the output (resid_post) of action-expert layer `l` at the last action token, in every Euler step
of the full sampler (spec 10.9). `adarms`: the time conditioning (B, W) every expert adaRMS norm receives in
that step; it depends on the flow time only, so every frame and every requested layer has the same rows.
Rows are frame-major, step-minor: row f * num_steps + s is frame f at step s.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:  # the model modules load with the model, not with the capture loop
    from steering_core.pi05.policy import Pi05Policy

DECISION_TOKEN = -1  # the last action token of the chunk


def frame_noise(indices: Sequence[int], horizon: int, action_dim: int, noise_seed: int) -> torch.Tensor:
    """Return (B, horizon, action_dim) float32 N(0, 1) noise, each frame from its own CPU generator.

    Frame i draws from `manual_seed(noise_seed * 2**32 + i)`, so its noise does not depend on its batch.
    """
    draws = []
    for index in indices:
        generator = torch.Generator().manual_seed(int(noise_seed) * 2**32 + int(index))
        draws.append(torch.randn(horizon, action_dim, generator=generator, dtype=torch.float32))
    return torch.stack(draws)


@contextlib.contextmanager
def _record_layer_outputs(policy: Pi05Policy, layers: Sequence[int]) -> Iterator[dict[int, list[torch.Tensor]]]:
    """Yield layer -> per-call outputs (B, W) at the last action token while the expert runs."""
    recorded: dict[int, list[torch.Tensor]] = {layer: [] for layer in layers}
    handles = [
        policy.expert.layers[layer].register_forward_hook(
            lambda module, args, output, layer=layer: recorded[layer].append(output[:, DECISION_TOKEN].float())
        )
        for layer in layers
    ]
    try:
        yield recorded
    finally:
        for handle in handles:
            handle.remove()


def decision_rows(
    policy: Pi05Policy,
    images: Sequence[torch.Tensor],
    image_masks: Sequence[torch.Tensor],
    tokens: torch.Tensor,
    token_mask: torch.Tensor,
    noise: torch.Tensor,
    layers: Sequence[int],
    num_steps: int,
) -> dict[int, torch.Tensor]:
    """Return layer -> (B * num_steps, W) float32: expert layer outputs at the last action token, per step.

    Runs `policy.sample_actions` from `noise` (B, H, A) without steering, recording the layers' outputs.
    """
    with _record_layer_outputs(policy, layers) as recorded:
        policy.sample_actions(images, image_masks, tokens, token_mask, noise=noise, num_steps=num_steps)
    batch = tokens.shape[0]
    return {layer: torch.stack(steps, dim=1).reshape(batch * num_steps, -1) for layer, steps in recorded.items()}


@torch.no_grad()
def adarms_rows(policy: Pi05Policy, batch: int, layers: Sequence[int], num_steps: int) -> dict[int, torch.Tensor]:
    """Return layer -> (B * num_steps, W) float32: the expert's adaRMS conditioning at each step's flow time."""
    from steering_core.pi05.expert import euler_times

    _, times = euler_times(num_steps, policy.device, policy.accumulated_time)
    cond = policy.expert.condition(torch.stack(times)).float()  # (num_steps, W)
    rows = cond.repeat(batch, 1)
    return {layer: rows for layer in layers}
