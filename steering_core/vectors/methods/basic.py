"""The methods read from the concepts' streaming statistics alone: `sae` (the seed's direction), `mean_difference`
(DiffMean) and `sae_top_k` (the largest latent differences only)."""

from __future__ import annotations

import torch

from steering_core.vectors.methods.registry import MethodResult, PairData, register_method


def latent_difference(data: PairData) -> torch.Tensor:
    """Return the (d_sae,) float32 difference of the concepts' mean latent activations."""
    return (data.stats["positive"].latent_mean - data.stats["negative"].latent_mean).float()


@register_method("sae", "the concepts' mean latent difference decoded through W_dec (the seed's residual_direction)",
                 needs_sae=True)
def sae_direction(data: PairData) -> MethodResult:
    """Return Δf @ W_dec (+ b_dec with `include_decoder_bias`, the seed's decode(Δf))."""
    latent = latent_difference(data)
    residual = data.sae.decode_direction(latent).detach().to("cpu", torch.float32)
    bias = bool(data.settings.include_decoder_bias)
    if bias:
        residual = residual + data.sae.b_dec.detach().to("cpu", torch.float32)
    return MethodResult(residual, {"latent_norm": float(latent.norm()), "include_decoder_bias": bias})


@register_method("mean_difference", "the difference of the concepts' residual means (DiffMean)")
def mean_difference(data: PairData) -> MethodResult:
    """Return mean(positive rows) − mean(negative rows), from the statistics (float64 sums)."""
    return MethodResult((data.stats["positive"].residual_mean - data.stats["negative"].residual_mean).float())


@register_method("sae_top_k", "only the top_k latents with the largest |mean difference|, decoded without b_dec",
                 needs_sae=True)
def top_k_direction(data: PairData) -> MethodResult:
    """Return the decoder image of the k largest-|value| entries of the latent difference (k = `top_k`)."""
    latent = latent_difference(data)
    k = min(int(data.settings.top_k), latent.numel())
    top = latent.abs().topk(k).indices
    kept = torch.zeros_like(latent)
    kept[top] = latent[top]
    residual = data.sae.decode_direction(kept).detach().to("cpu", torch.float32)
    return MethodResult(residual, {"k": k, "latents": top.tolist(), "differences": latent[top].tolist()})
