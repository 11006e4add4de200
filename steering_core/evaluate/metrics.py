"""Dose-response metrics over frames, with bootstrap 95% intervals and z-scores against the random band.

Shapes: `steered` (dirs, alphas, frames, seeds, horizon, 7) robot actions; `swap` (frames, seeds, horizon, 7)
= actions with the positive instruction minus with the negative one, same frame and noise (for a
negative-task frame the instruction swap; for a positive-task frame the swap with its sign flipped).
Δa = steered − steered at α = 0 (the same frame and noise, unsteered).

- efficacy = Σ_f ⟨Δa_f, Δswap_f⟩ / Σ_f ‖Δswap_f‖² (pooled over frames, so a frame whose instructions
  barely differ does not dominate); 1 = steering reproduces the instruction swap;
- cosine = mean over frames of cos(Δa_f, Δswap_f);
- shift = mean over frames and seeds of ‖Δa‖ over the horizon, per action group (x, y, z, rotation, gripper);
- contrast shift = Δa along the manifest's contrast axis, summed over the horizon, signed so that
  positive means toward the positive task.
"""

from __future__ import annotations

import torch

ACTION_GROUPS = {"x": (0,), "y": (1,), "z": (2,), "rotation": (3, 4, 5), "gripper": (6,)}
STATE_TO_ACTION = (0, 1, 2, 3, 4, 5, 6, 6)  # LIBERO state (eef xyz, axis-angle, 2 gripper) -> action dim
QUANTILES = (0.025, 0.975)


def action_dim_of_state_axis(axis: int) -> int:
    """Return the delta-action dimension that moves a LIBERO state axis."""
    if not 0 <= axis < len(STATE_TO_ACTION):
        raise ValueError(f"contrast axis {axis} is not a LIBERO state dimension (0..{len(STATE_TO_ACTION) - 1})")
    return STATE_TO_ACTION[axis]


def bootstrap_indices(frames: int, samples: int, seed: int) -> torch.Tensor:
    """Return (samples, frames) int64 frame indices drawn with replacement (the same for every metric)."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(frames, (samples, frames), generator=generator)


def ratio_with_interval(
    numerator: torch.Tensor, denominator: torch.Tensor, resamples: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (Σ_f num / Σ_f den, its 95% percentile interval (..., 2)) over the last (frame) dimension."""
    value = numerator.sum(-1) / denominator.sum(-1)
    boot = numerator[..., resamples].sum(-1) / denominator[..., resamples].sum(-1)  # (..., samples)
    interval = torch.quantile(boot, torch.tensor(QUANTILES, dtype=boot.dtype), dim=-1).movedim(0, -1)
    return value, interval


def mean_with_interval(values: torch.Tensor, resamples: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (mean over the last (frame) dimension, its 95% bootstrap interval (..., 2))."""
    return ratio_with_interval(values, torch.ones_like(values), resamples)


def dose_response_metrics(
    steered: torch.Tensor, swap: torch.Tensor, zero_index: int, contrast_dim: int, contrast_sign: float,
    resamples: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """Return every metric (dirs, alphas[, group]) and its interval (..., 2), plus the swap's own shifts."""
    steered, swap = steered.double(), swap.double()
    delta = steered - steered[:, zero_index : zero_index + 1]           # (D, A, F, S, H, 7)
    flat_delta, flat_swap = delta.flatten(3), swap.flatten(1)            # (D, A, F, S*H*7), (F, S*H*7)
    inner = (flat_delta * flat_swap).sum(-1)                             # (D, A, F)
    swap_sq = (flat_swap**2).sum(-1).expand_as(inner)
    out: dict[str, torch.Tensor] = {}
    out["efficacy"], out["efficacy_ci"] = ratio_with_interval(inner, swap_sq, resamples)
    norms = flat_delta.norm(dim=-1) * flat_swap.norm(dim=-1)
    cosine = torch.where(norms > 0, inner / norms.clamp_min(1e-300), torch.zeros_like(inner))
    out["cosine"], out["cosine_ci"] = mean_with_interval(cosine, resamples)
    group_shift = torch.stack([_group_norm(delta, dims) for dims in ACTION_GROUPS.values()], dim=-1)  # (D, A, F, G)
    value, interval = mean_with_interval(group_shift.movedim(-1, -2), resamples)                      # (D, A, G)
    out["shift"], out["shift_ci"] = value, interval
    along = contrast_sign * delta[..., contrast_dim].sum(-1).mean(-1)   # (D, A, F): over horizon, mean over seeds
    out["contrast_shift"], out["contrast_shift_ci"] = mean_with_interval(along, resamples)
    out["swap_shift"] = torch.stack([_group_norm(swap, dims) for dims in ACTION_GROUPS.values()], -1).mean(0)
    out["swap_contrast_shift"] = (contrast_sign * swap[..., contrast_dim].sum(-1).mean(-1)).mean()
    return out


def _group_norm(actions: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    """Return ‖actions[..., dims]‖ over (horizon, dims), averaged over seeds: (..., seeds, H, 7) -> (...)."""
    return actions[..., list(dims)].flatten(-2).norm(dim=-1).mean(-1)


def random_band_z(efficacy: torch.Tensor, random_rows: list[int]) -> dict[str, torch.Tensor]:
    """Return the random band (mean, std, min, max per α) and every direction's z-score against it.

    z = (efficacy − band mean) / band std (sample std); 0 where the band has no spread (α = 0).
    """
    band = efficacy[random_rows]                                   # (R, A)
    mean, std = band.mean(0), band.std(0, unbiased=True)
    safe = torch.where(std > 0, std, torch.ones_like(std))
    z = torch.where(std > 0, (efficacy - mean) / safe, torch.zeros_like(efficacy))
    return {"random_mean": mean, "random_std": std, "random_min": band.min(0).values, "random_max": band.max(0).values,
            "z": z}
