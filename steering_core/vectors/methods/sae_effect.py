"""`sae_effect`: the SAE latents with the largest effect size between the concepts, each vetted first.

Dr.VLA (arXiv 2603.19183) finds most of pi0.5's SAE features memorised: they fire in a single episode. So the
training rows of both concepts stream through the SAE once, keeping per side and latent the row count, mean and
sum of squared deviations (float64, batches merged by Chan's formula: a latent constant on a side has exactly zero
spread), the rows it fires in (> 0) and the training episodes it fires in. A latent is vetted when it fires in at
least `effect_min_episodes` distinct episodes of the two sides. Its effect is Cohen's d,
(μ₊ − μ₋) / s_pooled; a latent whose pooled spread is zero has no finite d and is excluded (`zero_variance`), as are
those with μ₊ = μ₋ (`zero_effect`). The `top_k` vetted latents with the largest |d| give the direction
Σᵢ (μ₊ᵢ − μ₋ᵢ)·W_dec[i] (no b_dec).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from steering_core.pairs import SIDES
from steering_core.sae.model import Sae
from steering_core.vectors.methods.registry import MethodResult, PairData, register_method


@dataclass(frozen=True)
class LatentMoments:
    """One side's per-latent statistics over its training rows, (d_sae,) float64 each, on the CPU."""

    count: int
    mean: torch.Tensor
    m2: torch.Tensor      # sum of squared deviations from the mean
    fired: torch.Tensor   # rows where the latent is > 0


@register_method("sae_effect", "the top_k latents by Cohen's d that fire in at least effect_min_episodes training "
                 "episodes, decoded without b_dec", needs_sae=True, reads_rows=True)
def sae_effect_direction(data: PairData) -> MethodResult:
    """Return Σ Δμᵢ·W_dec[i] over the chosen latents; ValueError naming the pair and layer for slices without
    episodes or when no latent survives the vetting."""
    sae, settings = data.sae, data.settings
    min_episodes, top_k = int(settings.effect_min_episodes), int(settings.top_k)
    rows = {side: data.rows(side) for side in SIDES}
    for side, path in zip(SIDES, data.slices, strict=True):
        if rows[side].episodes is None:
            raise ValueError(f"{data.where}: method sae_effect vets latents by the training episodes they fire in, "
                             f"but the {side} slice {path} has no `episode_index` column; re-slice it with "
                             "`latent-steering slice`")
        if len(rows[side].episodes) != len(rows[side].rows) or not len(rows[side].rows):
            raise ValueError(f"{data.where}: the {side} slice {path} has {len(rows[side].rows)} rows and "
                             f"{len(rows[side].episodes)} episode indices, expected as many and at least one")
    episodes = torch.unique(torch.cat([rows[side].episodes for side in SIDES]))  # sorted: an episode's row index
    seen = torch.zeros(len(episodes), sae.cfg.d_sae, dtype=torch.bool, device=sae.device)
    moments = {side: latent_moments(sae, rows[side].rows, torch.searchsorted(episodes, rows[side].episodes), seen,
                                    int(settings.batch_size)) for side in SIDES}
    positive, negative = moments["positive"], moments["negative"]
    difference = positive.mean - negative.mean
    spread = (positive.m2 + negative.m2) / max(positive.count + negative.count - 2, 1)
    effect = torch.where(spread > 0, difference / spread.sqrt(), torch.zeros_like(difference))
    fired_rows = positive.fired + negative.fired
    fired_episodes = seen.sum(dim=0).cpu()
    never = fired_rows == 0
    memorised = ~never & (fired_episodes < min_episodes)
    zero_effect = ~never & ~memorised & (difference == 0)
    zero_variance = ~never & ~memorised & ~zero_effect & (spread == 0)
    vetted = ~(never | memorised | zero_effect | zero_variance)
    excluded = {name: int(mask.sum()) for name, mask in (("never_fire", never), ("memorised", memorised),
                                                         ("zero_effect", zero_effect), ("zero_variance", zero_variance))}
    if not vetted.any():
        raise ValueError(
            f"{data.where}: sae_effect: no latent fires in at least {min_episodes} training episodes (of "
            f"{len(episodes)}) with a non-zero effect ({excluded['memorised']} memorised, {excluded['never_fire']} "
            f"never fire, {excluded['zero_effect']} zero effect, {excluded['zero_variance']} zero variance); lower "
            "steering.effect_min_episodes or add training episodes")
    score = torch.where(vetted, effect.abs(), torch.full_like(effect, -1.0))
    chosen = torch.sort(score, descending=True, stable=True).indices[:min(top_k, int(vetted.sum()))]
    sparse = torch.zeros_like(difference)
    sparse[chosen] = difference[chosen]
    direction = sae.decode_direction(sparse).detach().to("cpu", torch.float32)
    total = positive.count + negative.count
    latents = [{"latent": int(i), "cohen_d": float(effect[i]), "mean_difference": float(difference[i]),
                "episodes": int(fired_episodes[i]), "frequency": float(fired_rows[i]) / total,
                "frequency_positive": float(positive.fired[i]) / positive.count,
                "frequency_negative": float(negative.fired[i]) / negative.count} for i in chosen.tolist()]
    record: dict[str, Any] = {
        "latents": latents,
        "excluded": excluded,
        "min_episodes": min_episodes,
        "training_episodes": {side: len(torch.unique(rows[side].episodes)) for side in SIDES},
        "rows": {side: moments[side].count for side in SIDES},
    }
    return MethodResult(direction, record)


def latent_moments(sae: Sae, rows: torch.Tensor, episode_rows: torch.Tensor, seen: torch.Tensor,
                   batch_size: int) -> LatentMoments:
    """Return one side's latent moments, streaming `rows` (n, d_in) through the SAE in batches; mark in `seen`
    (episodes, d_sae) the latents each episode fires (`episode_rows`: each row's row of `seen`)."""
    count, mean, m2, fired = 0, 0.0, 0.0, 0.0
    episode_rows = episode_rows.to(sae.device)
    for start in range(0, len(rows), batch_size):
        latents = sae.encode(rows[start:start + batch_size].to(sae.device)).double()
        n = len(latents)
        batch_mean = latents.mean(dim=0)
        batch_m2 = (latents - batch_mean).square_().sum(dim=0)
        delta = batch_mean - mean
        mean = mean + delta * (n / (count + n))
        m2 = m2 + batch_m2 + delta.square() * (count * n / (count + n))
        count += n
        firing = latents > 0
        fired = fired + firing.sum(dim=0, dtype=torch.float64)
        batch_episodes, local = torch.unique(episode_rows[start:start + n], return_inverse=True)
        per_episode = torch.zeros(len(batch_episodes), firing.shape[1], dtype=torch.int32, device=sae.device)
        per_episode.index_add_(0, local, firing.to(torch.int32))
        seen[batch_episodes] |= per_episode > 0
    return LatentMoments(count, mean.cpu(), m2.cpu(), fired.cpu())
