"""A naive float64 numpy SAE written straight from the spec (docs/PI05_SPEC.md section 6.3).

Deliberately independent of `steering_core.sae.model`: numpy instead of torch, explicit per-row loops for
TopK, and the "expected_average_only_in" factor applied to the input (x -> s*x, output / s) instead of
being folded into the weights. Tests compare the library against it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file


@dataclass
class ReferenceSae:
    W_enc: np.ndarray  # (d_in, d_sae)
    b_enc: np.ndarray  # (d_sae,)
    W_dec: np.ndarray  # (d_sae, d_in)
    b_dec: np.ndarray  # (d_in,)
    architecture: str = "standard"
    normalize: str = "none"
    apply_b_dec_to_input: bool = True
    threshold: np.ndarray | None = None
    k: int | None = None
    rescale_by_decoder_norm: bool = False
    input_scale: float = 1.0  # the registry's norm_scaling_factor, applied to inputs

    @classmethod
    def from_weights_file(cls, path: Path, **settings) -> ReferenceSae:
        tensors = {name: value.astype(np.float64) for name, value in load_file(str(path)).items()}
        if "scaling_factor" in tensors:
            # SAELens <= 5 decoded (f * scaling_factor) @ W_dec
            tensors["W_dec"] = tensors["W_dec"] * tensors.pop("scaling_factor")[:, None]
        return cls(**tensors, **settings)

    def _normalise(self, x: np.ndarray) -> tuple[np.ndarray, dict]:
        x = x * self.input_scale
        d_in = x.shape[-1]
        if self.normalize == "constant_norm_rescale":
            c = np.sqrt(d_in) / np.sqrt((x**2).sum(axis=-1, keepdims=True))
            return x * c, {"c": c}
        if self.normalize == "layer_norm":
            mean = x.sum(axis=-1, keepdims=True) / d_in
            std = np.sqrt(((x - mean) ** 2).sum(axis=-1, keepdims=True) / (d_in - 1))
            return (x - mean) / (std + 1e-5), {"mean": mean, "std": std}
        return x, {}

    def encode(self, x: np.ndarray) -> tuple[np.ndarray, dict]:
        xn, stats = self._normalise(np.asarray(x, dtype=np.float64))
        if self.apply_b_dec_to_input:
            xn = xn - self.b_dec
        z = xn @ self.W_enc + self.b_enc
        if self.architecture == "standard":
            return np.maximum(z, 0.0), stats
        if self.architecture == "jumprelu":
            return np.where(z > self.threshold, np.maximum(z, 0.0), 0.0), stats
        if self.rescale_by_decoder_norm:
            z = z * np.linalg.norm(self.W_dec, axis=1)
        f = np.zeros_like(z)
        for row in range(z.shape[0]):
            keep = np.argsort(-z[row])[: self.k]
            f[row, keep] = np.maximum(z[row, keep], 0.0)
        return f, stats

    def direction(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, dtype=np.float64)
        if self.architecture == "topk" and self.rescale_by_decoder_norm:
            d = d / np.linalg.norm(self.W_dec, axis=1)
        return d @ self.W_dec

    def decode(self, f: np.ndarray, stats: dict) -> np.ndarray:
        out = self.direction(f) + self.b_dec
        if "c" in stats:
            out = out / stats["c"]
        if "std" in stats:
            out = out * stats["std"] + stats["mean"]
        return out / self.input_scale
