"""Dose-response metrics over frames, with episode-bootstrap 95% intervals, cross-fitted best α and the nulls.

Shapes: `steered` (dirs, alphas, frames, seeds, horizon, 7) robot actions, each frame steered toward the other
task; `swap` (frames, seeds, horizon, 7) = actions with the other task's instruction minus with the frame's
own, same frame and noise. Δa = steered − steered at α = 0 (the same frame and noise, unsteered). Every action
dimension is divided by its std (the checkpoint's norm stats) unless a name ends in `_raw`.

- efficacy = Σ_f ⟨Δa_f, Δswap_f⟩ / Σ_f ‖Δswap_f‖² (pooled over frames, so a frame whose instructions
  barely differ does not dominate), per side (`positive`/`negative`: the frames of that task) and pooled;
  1 = steering reproduces the instruction swap;
- cosine = mean over frames of cos(Δa_f, Δswap_f);
- shift = mean over frames and seeds of ‖Δa‖ over the horizon, per action group (x, y, z, rotation, gripper);
- contrast shift = the rate of the manifest's contrast state axis the actions ask for (`state_axis_weights`),
  summed over the horizon, signed so that positive means toward the other task (action units);
- cross-fitted efficacy: the α ≠ 0 closest to 1 is chosen on one half of the frames' episodes and its efficacy
  read on the other half, both ways, averaged (no winner's curse from choosing and scoring on the same frames).

Intervals resample episodes with replacement within each side (frames nested in their episode).
"""

from __future__ import annotations

import math

import torch

ACTION_GROUPS = {"x": (0,), "y": (1,), "z": (2,), "rotation": (3, 4, 5), "gripper": (6,)}
ROBOT_DIM = 7
# LIBERO's end-effector rests about π around x (pointing down): the orientation the rotation axes are read at
LIBERO_ORIENTATION = (math.pi, 0.0, 0.0)
QUANTILES = (0.025, 0.975)


def left_jacobian_inverse(r: torch.Tensor) -> torch.Tensor:
    """Return J_l⁻¹(r) (3, 3): how an axis-angle r changes under a small world-frame rotation ω (dr = J_l⁻¹ ω).

    J_l⁻¹ = I − K/2 + (1/θ² − cot(θ/2)/(2θ)) K², K = [r]×, θ = ‖r‖ (finite at θ = π, I − K/2 near 0).
    """
    r = r.double()
    k = torch.tensor([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]], dtype=torch.float64)
    theta = float(r.norm())
    coefficient = 1 / 12 if theta < 1e-6 else 1 / theta**2 - 1 / (2 * theta * math.tan(theta / 2))
    return torch.eye(3, dtype=torch.float64) - k / 2 + coefficient * k @ k


def state_axis_weights(axis: int, orientation: tuple[float, float, float] = LIBERO_ORIENTATION) -> torch.Tensor:
    """Return (7,) float64 w: a LIBERO state axis moves by ⟨w, Δa⟩ per delta action (in action units).

    State: eef position (0-2), eef axis-angle (3-5), gripper qpos (6: left finger, 7: right finger, mirrored).
    Position axes follow action 0-2; the axis-angle follows the rotation action through J_l⁻¹ at `orientation`
    (at LIBERO's π about x, axis 5 moves under action 4 with the sign flipped); the gripper action closes
    (+1) what qpos 6 opens, so qpos 6 has the opposite sign and the mirrored qpos 7 the same sign.
    """
    w = torch.zeros(ROBOT_DIM, dtype=torch.float64)
    if 0 <= axis < 3:
        w[axis] = 1.0
    elif 3 <= axis < 6:
        w[3:6] = left_jacobian_inverse(torch.tensor(orientation, dtype=torch.float64))[axis - 3]
    elif axis in (6, 7):
        w[6] = -1.0 if axis == 6 else 1.0
    else:
        raise ValueError(f"contrast axis {axis} is not a LIBERO state dimension (0..7)")
    return w


def episode_weights(episodes: list[int], sides: list[str], samples: int, seed: int) -> torch.Tensor:
    """Return (samples, frames) float64 bootstrap weights: per side, its episodes drawn with replacement, each
    frame weighted by how often its episode was drawn."""
    generator = torch.Generator().manual_seed(seed)
    weights = torch.zeros(samples, len(episodes), dtype=torch.float64)
    for side in sorted(set(sides)):
        ids = sorted({e for e, s in zip(episodes, sides, strict=True) if s == side})
        draws = torch.randint(len(ids), (samples, len(ids)), generator=generator)
        counts = torch.zeros(samples, len(ids), dtype=torch.float64).scatter_add_(
            1, draws, torch.ones_like(draws, dtype=torch.float64))
        for f, (e, s) in enumerate(zip(episodes, sides, strict=True)):
            if s == side:
                weights[:, f] = counts[:, ids.index(e)]
    return weights


def _ratio(num: torch.Tensor, den: torch.Tensor, mask: torch.Tensor,
           weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (Σ_mask num / Σ_mask den over the last (frame) dim, the same per bootstrap resample (..., samples))."""
    m = mask.double()
    value = (num * m).sum(-1) / (den * m).sum(-1)
    boot = ((num * m) @ weights.T) / ((den * m) @ weights.T)
    return value, boot


def _interval(boot: torch.Tensor) -> torch.Tensor:
    """Return the 95% percentile interval (..., 2) of bootstrap values (..., samples), NaN resamples left out."""
    return torch.nanquantile(boot, torch.tensor(QUANTILES, dtype=boot.dtype), dim=-1).movedim(0, -1)


def closest_to_one(efficacy: torch.Tensor, zero_index: int) -> torch.Tensor:
    """Return the α index (dim 1 of (D, A, ...)) whose efficacy is closest to 1 (the instruction swap), α = 0
    and NaN excluded; ties keep the first."""
    distance = (efficacy - 1.0).abs().nan_to_num(math.inf)
    distance[:, zero_index] = math.inf
    return distance.argmin(1)


def dose_response_metrics(
    steered: torch.Tensor, swap: torch.Tensor, *, scale: torch.Tensor, contrast: torch.Tensor, toward: torch.Tensor,
    halves: torch.Tensor, episodes: list[int], zero_index: int, samples: int, seed: int,
) -> dict[str, torch.Tensor]:
    """Return every metric and its interval (..., 2), the swap's own shifts and the cross-fitted best α.

    `scale` (7,): each action dimension's std; `contrast` (7,): the contrast state axis's `state_axis_weights`,
    signed so that positive is the positive task; `toward` (F,): +1 for a negative-task frame, −1 for a
    positive-task one; `halves` (F,) int: each frame's half (0 or 1) for the cross-fitting.
    """
    steered, swap = steered.double(), swap.double()
    sides = ["negative" if t > 0 else "positive" for t in toward.tolist()]
    weights = episode_weights(episodes, sides, samples, seed)
    masks = {"pooled": torch.ones(len(sides), dtype=torch.bool), "positive": toward < 0, "negative": toward > 0}
    delta = steered - steered[:, zero_index : zero_index + 1]           # (D, A, F, S, H, 7)
    out: dict[str, torch.Tensor] = {}
    for suffix, unit in (("", scale.double()), ("_raw", torch.ones(ROBOT_DIM, dtype=torch.float64))):
        d, s = (delta / unit).flatten(3), (swap / unit).flatten(1)     # (D, A, F, S*H*7), (F, S*H*7)
        inner, swap_sq = (d * s).sum(-1), (s**2).sum(-1).expand(delta.shape[:3])
        for side, mask in masks.items():
            key = "efficacy" + ("" if side == "pooled" else f"_{side}") + suffix
            value, boot = _ratio(inner, swap_sq, mask, weights)
            out[key], out[f"{key}_ci"] = value, _interval(boot)
        groups = [(delta / unit)[..., list(g)].flatten(-2).norm(dim=-1).mean(-1) for g in ACTION_GROUPS.values()]
        value, boot = _ratio(torch.stack(groups, -2), torch.ones_like(groups[0])[..., None, :], masks["pooled"], weights)
        out["shift" + suffix], out[f"shift{suffix}_ci"] = value, _interval(boot)            # (D, A, G)
        out["swap_shift" + suffix] = torch.stack(
            [(swap / unit)[..., list(g)].flatten(-2).norm(dim=-1).mean(-1).mean() for g in ACTION_GROUPS.values()])
        if suffix == "":
            norms = d.norm(dim=-1) * s.norm(dim=-1)
            cosine = torch.where(norms > 0, inner / norms.clamp_min(1e-300), torch.zeros_like(inner))
            value, boot = _ratio(cosine, torch.ones_like(cosine), masks["pooled"], weights)
            out["cosine"], out["cosine_ci"] = value, _interval(boot)
            out |= _crossfit(inner, swap_sq, masks, halves, weights, zero_index)
            out["best_alpha_index"] = closest_to_one(out["efficacy"], zero_index)  # the recommended α, all frames
    along = toward * (delta @ contrast.double()).sum(-1).mean(-1)        # (D, A, F): over horizon, mean over seeds
    value, boot = _ratio(along, torch.ones_like(along), masks["pooled"], weights)
    out["contrast_shift"], out["contrast_shift_ci"] = value, _interval(boot)
    out["swap_contrast_shift"] = (toward * (swap @ contrast.double()).sum(-1).mean(-1)).mean()
    return out


def _crossfit(inner: torch.Tensor, swap_sq: torch.Tensor, masks: dict[str, torch.Tensor], halves: torch.Tensor,
              weights: torch.Tensor, zero_index: int) -> dict[str, torch.Tensor]:
    """Return the per-half efficacy (2, D, A), the α index chosen on each half (2, D) and the cross-fitted
    efficacy (pooled and per side) with its interval: choose on half h, read on half 1 − h, average both ways.

    The choice is redone in every bootstrap resample, so the interval includes the selection's own noise.
    """
    half_masks = [halves == h for h in (0, 1)]
    pooled = [_ratio(inner, swap_sq, m, weights) for m in half_masks]           # per half: (D, A), (D, A, B)
    chosen = torch.stack([closest_to_one(value, zero_index) for value, _ in pooled])               # (2, D)
    chosen_boot = torch.stack([closest_to_one(boot, zero_index) for _, boot in pooled])           # (2, D, B)
    out = {"efficacy_half": torch.stack([value for value, _ in pooled]), "crossfit_alpha_index": chosen}
    for side, mask in masks.items():
        reads = [_ratio(inner, swap_sq, mask & half_masks[h], weights) for h in (0, 1)]
        value = sum(reads[1 - h][0].gather(1, chosen[h][:, None])[:, 0] for h in (0, 1)) / 2
        boot = sum(reads[1 - h][1].gather(1, chosen_boot[h][:, None])[:, 0] for h in (0, 1)) / 2
        key = "crossfit" + ("" if side == "pooled" else f"_{side}")
        out[key], out[f"{key}_ci"] = value, _interval(boot)
        if side == "pooled":
            out["crossfit_boot"] = boot  # (D, B): the same resamples for every direction, so differences pair
    return out


def paired_difference(values: torch.Tensor, boot: torch.Tensor, row: int, reference: int) -> tuple[float, list[float]]:
    """Return values[row] − values[reference] and the 95% interval of that difference over the shared bootstrap
    resamples `boot` (D, B) (paired: each resample draws the same episodes for both)."""
    return float(values[row] - values[reference]), _interval(boot[row] - boot[reference]).tolist()


def holm(p: torch.Tensor) -> torch.Tensor:
    """Return Holm's step-down adjusted p-values of a 1-D family (same order), each capped at 1."""
    order = torch.argsort(p, stable=True)
    m = len(p)
    steps = (m - torch.arange(m, dtype=p.dtype)) * p[order]
    adjusted = torch.cummax(steps, 0).values.clamp(max=1.0)
    out = torch.empty_like(p)
    out[order] = adjusted
    return out


def null_comparison(values: torch.Tensor, null_rows: list[int]) -> dict[str, torch.Tensor]:
    """Return z = (value − null mean) / null std and the empirical p = (1 + #null ≥ value) / (1 + N) of every
    direction's `values` (D, ...) against the rows `null_rows`; z is 0 where the null has no spread."""
    null = values[null_rows]
    mean, std = null.mean(0), null.std(0, unbiased=True)
    safe = torch.where(std > 0, std, torch.ones_like(std))
    z = torch.where(std > 0, (values - mean) / safe, torch.zeros_like(values))
    p = (1 + (null[None] >= values[:, None]).sum(1)) / (1 + len(null_rows))
    return {"z": z, "p": p.double()}


def null_band(efficacy: torch.Tensor, null_rows: list[int]) -> dict[str, torch.Tensor]:
    """Return the null's mean, std and 2.5-97.5% range per α of efficacy (D, A) over `null_rows`."""
    null = efficacy[null_rows]
    low, high = torch.quantile(null, torch.tensor(QUANTILES, dtype=null.dtype), dim=0)
    return {"mean": null.mean(0), "std": null.std(0, unbiased=True), "low": low, "high": high}
