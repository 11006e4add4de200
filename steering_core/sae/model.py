"""Sparse autoencoders with SAELens's encode/decode semantics, and `load_sae` for every source.

Input processing follows SAELens: cast to the SAE dtype, normalise (`constant_norm_rescale`
multiplies by sqrt(d_in)/||x||, `layer_norm` standardises with the unbiased std + 1e-5), then
subtract b_dec only if `apply_b_dec_to_input`. Decoding adds b_dec and undoes the normalisation,
which needs the per-row statistics of the matching encode (`InputNorm`); SAELens keeps them as
hidden state on the module, here `encode_with_norm` returns them.
"""

from __future__ import annotations

import functools
import logging
import os
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch

from steering_core.sae.formats import (
    CFG_FILE,
    DTYPES,
    STATE_DICT_SUFFIXES,
    WEIGHTS_FILE,
    SaeConfig,
    apply_scaling_factor,
    check_sparsity,
    parse_cfg,
    read_cfg,
    read_sae_folder,
    read_state_dict_file,
    state_dict_cfg,
)
from steering_core.sae.registry import RELEASES, SaeEntry, find_by_folder, get_entry, resolve_release
from steering_core.storage.fileio import sha256_file, sha256_json
from steering_core.tensor_files import MIN_NORMAL, require_finite

logger = logging.getLogger(__name__)

LAYER_NORM_EPS = 1e-5  # SAELens's run-time layer_norm epsilon
INPUT_DEPENDENT_NORMS = ("constant_norm_rescale", "layer_norm")
ARCHITECTURES: dict[str, type[Sae]] = {}


@dataclass(frozen=True)
class InputNorm:
    """Per-row statistics of an input normalisation, `(..., 1)` each; all None when there is none."""

    scale: torch.Tensor | None = None  # constant_norm_rescale: sqrt(d_in) / ||x||
    mean: torch.Tensor | None = None  # layer_norm
    std: torch.Tensor | None = None  # layer_norm (unbiased)


class Sae(ABC):
    """An inference SAE: `encode` (..., d_in) -> (..., d_sae), `decode` back, `decode_direction`."""

    architecture: ClassVar[str]
    extra_weights: ClassVar[tuple[str, ...]] = ()  # tensors beyond W_enc, b_enc, W_dec, b_dec

    def __init__(
        self,
        cfg: SaeConfig,
        weights: dict[str, torch.Tensor],
        *,
        device: str | torch.device | None = None,
        log_sparsity: torch.Tensor | None = None,
        weights_path: Path | None = None,
    ) -> None:
        _check_weights(cfg, weights, self.extra_weights)
        self.cfg = cfg
        self.device = torch.device(device or "cpu")
        self.dtype = DTYPES[cfg.dtype]
        cast = {
            name: weights[name].to(device=self.device, dtype=self.dtype)
            for name in weight_shapes(cfg, self.extra_weights)
        }
        for name, tensor in cast.items():  # after the cast: a value beyond a narrow dtype's range is refused too
            require_finite(tensor, cfg.source, name, "the SAE is damaged; re-download or re-train it")
        self.W_enc, self.b_enc, self.W_dec, self.b_dec = (cast[n] for n in ("W_enc", "b_enc", "W_dec", "b_dec"))
        for name in self.extra_weights:
            setattr(self, name, cast[name])
        self.log_sparsity = log_sparsity  # (d_sae,) log10 firing frequency during SAE training
        self.weights_path = weights_path

    @property
    def name(self) -> str:
        """Return `release/sae_id` when known, else the source path."""
        if self.cfg.release:
            return f"{self.cfg.release}/{self.cfg.sae_id}"
        return self.cfg.source

    @abstractmethod
    def activate(self, hidden_pre: torch.Tensor) -> torch.Tensor:
        """Return latent activations (..., d_sae) from pre-activations x~ @ W_enc + b_enc.

        `hidden_pre` is a fresh tensor owned by the caller: implementations may overwrite it.
        """

    def decoder_input(self, feature_acts: torch.Tensor) -> torch.Tensor:
        """Return what multiplies W_dec for these activations (identity except for rescaled TopK)."""
        return feature_acts

    @torch.no_grad()
    def encode_with_norm(self, x: torch.Tensor, out: torch.Tensor | None = None) -> tuple[torch.Tensor, InputNorm]:
        """Return latents (..., d_sae) in the SAE dtype, and the input statistics that `decode` needs.

        `out`: a (rows, d_sae) buffer for the pre-activations (activations may overwrite it in place).
        """
        if x.shape[-1] != self.cfg.d_in:
            raise ValueError(
                f"input is {tuple(x.shape)}, SAE {self.name} expects (..., {self.cfg.d_in}); "
                "use the SAE trained on this model width and layer"
            )
        x = x.to(device=self.device, dtype=self.dtype)
        norm = InputNorm()
        if self.cfg.normalize_activations == "constant_norm_rescale":
            norm = InputNorm(scale=self.cfg.d_in**0.5 / x.norm(dim=-1, keepdim=True))
            x = x * norm.scale
        elif self.cfg.normalize_activations == "layer_norm":
            mean = x.mean(dim=-1, keepdim=True)
            std = (x - mean).std(dim=-1, keepdim=True)
            norm = InputNorm(mean=mean, std=std)
            x = (x - mean) / (std + LAYER_NORM_EPS)
        if self.cfg.apply_b_dec_to_input:
            x = x - self.b_dec
        return self.activate(_affine(x, self.W_enc, self.b_enc, out)), norm

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Return latent activations (..., d_sae) of residuals (..., d_in), as SAELens's `encode`."""
        return self.encode_with_norm(x)[0]

    @torch.no_grad()
    def decode(
        self, feature_acts: torch.Tensor, norm: InputNorm | None = None, out: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Return reconstructions (..., d_in): f @ W_dec + b_dec, mapped back through `norm`.

        `out`: a (rows, d_in) buffer for the product.
        """
        if self.cfg.normalize_activations in INPUT_DEPENDENT_NORMS and norm is None:
            raise ValueError(
                f"SAE {self.name} normalises inputs ({self.cfg.normalize_activations}); decoding needs the "
                "InputNorm returned by encode_with_norm(x) for the same rows"
            )
        feature_acts = feature_acts.to(device=self.device, dtype=self.dtype)
        out = _affine(self.decoder_input(feature_acts), self.W_dec, self.b_dec, out)
        if norm is not None and norm.scale is not None:
            out = out / norm.scale
        if norm is not None and norm.std is not None:
            out = out * norm.std + norm.mean
        return out

    @torch.no_grad()
    def decode_direction(self, direction: torch.Tensor) -> torch.Tensor:
        """Return the decoder's linear map of a latent direction (..., d_sae) -> (..., d_in): no b_dec, no norm."""
        direction = direction.to(device=self.device, dtype=self.dtype)
        return self.decoder_input(direction) @ self.W_dec

    def reconstruct(
        self, x: torch.Tensor, out: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Return (reconstruction (..., d_in), latents (..., d_sae)) of residuals x.

        `out`: (rows, d_in) and (rows, d_sae) buffers to compute into, in the SAE's dtype and device. A
        stream of batches that reuses them skips allocating (and, on CPU, page-faulting in) fresh
        latents for every batch: 32 MiB per 512 rows of a 16k-latent SAE.
        """
        decoded, latents = out if out is not None else (None, None)
        feature_acts, norm = self.encode_with_norm(x, latents)
        return self.decode(feature_acts, norm, decoded), feature_acts

    def to(self, device: str | torch.device) -> Sae:
        """Return this SAE with its tensors moved to `device`."""
        self.device = torch.device(device)
        for name in ("W_enc", "b_enc", "W_dec", "b_dec", *self.extra_weights):
            setattr(self, name, getattr(self, name).to(self.device))
        return self

    @functools.cached_property
    def weights_sha256(self) -> str | None:
        """Return the sha256 of the weights file this SAE was read from (None if built in memory)."""
        return sha256_file(self.weights_path) if self.weights_path is not None else None

    def describe(self) -> dict[str, Any]:
        """Return the config plus the weights file and its sha256, as JSON-ready values."""
        return {
            **self.cfg.model_dump(mode="json"),
            "weights_path": str(self.weights_path) if self.weights_path else None,
            "weights_sha256": self.weights_sha256,
        }

    def fingerprint(self) -> str:
        """Return the sha256 of `describe()`: changes with the config or the weights."""
        return sha256_json(self.describe())


def register_architecture(cls: type[Sae]) -> type[Sae]:
    """Register an SAE class under its `architecture` name (as written in cfg.json); refuse duplicates."""
    if cls.architecture in ARCHITECTURES:
        raise ValueError(
            f"SAE architecture {cls.architecture!r} is already registered to {ARCHITECTURES[cls.architecture].__name__}"
        )
    ARCHITECTURES[cls.architecture] = cls
    return cls


def sae_class(architecture: str) -> type[Sae]:
    """Return the SAE class registered for an architecture name."""
    if architecture not in ARCHITECTURES:
        raise ValueError(f"unknown SAE architecture {architecture!r}; allowed values: {sorted(ARCHITECTURES)}")
    return ARCHITECTURES[architecture]


@register_architecture
class StandardSae(Sae):
    """f = ReLU(x~ @ W_enc + b_enc)."""

    architecture = "standard"

    def activate(self, hidden_pre: torch.Tensor) -> torch.Tensor:
        """Return ReLU of the pre-activations."""
        return hidden_pre.relu_()


@register_architecture
class JumpReluSae(Sae):
    """f = ReLU(z) where z > threshold, else 0 (z = x~ @ W_enc + b_enc)."""

    architecture = "jumprelu"
    extra_weights = ("threshold",)
    threshold: torch.Tensor

    def activate(self, hidden_pre: torch.Tensor) -> torch.Tensor:
        """Return ReLU of the pre-activations, zeroed at or below each latent's threshold."""
        return hidden_pre.masked_fill_(hidden_pre <= self.threshold, 0).relu_()


@register_architecture
class TopKSae(Sae):
    """f keeps the k largest pre-activations (optionally scaled by ||W_dec row||), ReLU'd; the rest are 0."""

    architecture = "topk"

    def __init__(self, cfg: SaeConfig, weights: dict[str, torch.Tensor], **kwargs: Any) -> None:
        if cfg.k is None or not 0 < cfg.k <= cfg.d_sae:
            raise ValueError(f"{cfg.source}: topk SAE has k = {cfg.k}, expected 1 <= k <= d_sae ({cfg.d_sae})")
        super().__init__(cfg, weights, **kwargs)

    def activate(self, hidden_pre: torch.Tensor) -> torch.Tensor:
        """Return the top-k ReLU'd pre-activations per row, zeros elsewhere."""
        if self.cfg.rescale_acts_by_decoder_norm:
            hidden_pre = hidden_pre * self.W_dec.norm(dim=-1)
        top = hidden_pre.topk(self.cfg.k, dim=-1)
        return torch.zeros_like(hidden_pre).scatter(-1, top.indices, top.values.relu())

    def decoder_input(self, feature_acts: torch.Tensor) -> torch.Tensor:
        """Return activations divided by ||W_dec row|| when encode multiplied by it."""
        if self.cfg.rescale_acts_by_decoder_norm:
            return feature_acts / self.W_dec.norm(dim=-1)
        return feature_acts


def _affine(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """Return x @ weight + bias for x of shape (..., n), in one fused product (addmm) over the flattened rows.

    `out`, when given, is a (rows, m) buffer the product is written into.
    """
    rows = x.reshape(-1, x.shape[-1])
    return torch.addmm(bias, rows, weight, out=out).reshape(*x.shape[:-1], weight.shape[-1])


def weight_shapes(cfg: SaeConfig, extra_weights: tuple[str, ...] = ()) -> dict[str, tuple[int, ...]]:
    """Return the expected shape of every SAE tensor under `cfg`; extra ones are per latent."""
    shapes = {
        "W_enc": (cfg.d_in, cfg.d_sae),
        "b_enc": (cfg.d_sae,),
        "W_dec": (cfg.d_sae, cfg.d_in),
        "b_dec": (cfg.d_in,),
    }
    return shapes | {name: (cfg.d_sae,) for name in extra_weights}


def _check_weights(cfg: SaeConfig, weights: dict[str, torch.Tensor], extra_weights: tuple[str, ...]) -> None:
    """Raise one ValueError listing missing, unexpected and misshapen tensors."""
    expected = weight_shapes(cfg, extra_weights)
    problems = [f"missing `{name}` {shape}" for name, shape in expected.items() if name not in weights]
    problems += [f"unexpected `{name}`" for name in sorted(set(weights) - set(expected))]
    problems += [
        f"`{name}` is {tuple(weights[name].shape)}, expected {shape}"
        for name, shape in expected.items()
        if name in weights and tuple(weights[name].shape) != shape
    ]
    if problems:
        raise ValueError(
            f"{cfg.source}: {cfg.architecture} SAE weights do not match its config "
            f"(d_in {cfg.d_in}, d_sae {cfg.d_sae}): " + "; ".join(problems)
        )


def check_trained(cfg: SaeConfig, weights: dict[str, torch.Tensor]) -> None:
    """Raise naming the SAE file and tensor when a weight is not floating point (integers would be cast silently),
    or the encoder or decoder holds no normal float32 value: all zeros or subnormal, it encodes or decodes every
    direction to zero or rounding noise."""
    for name, tensor in weights.items():
        if not tensor.is_floating_point():
            raise ValueError(f"{cfg.source}: `{name}` is {tensor.dtype}, expected floating point weights; the SAE is "
                             "damaged: re-download or re-train it")
    for name in ("W_enc", "W_dec"):  # NaN counts as a value here: the finiteness check names it
        if name in weights and not ((weights[name].abs() >= MIN_NORMAL) | weights[name].isnan()).any():
            raise ValueError(f"{cfg.source}: `{name}` is all zeros or subnormal (no |value| of at least "
                             f"{MIN_NORMAL:.3g}), expected trained weights (every direction would be zero); the SAE "
                             "is untrained or damaged: re-download or re-train it")


def fold_norm_scaling_factor(weights: dict[str, torch.Tensor], factor: float) -> dict[str, torch.Tensor]:
    """Return weights with an input scale folded in as SAELens does: W_enc * s, W_dec / s, b_dec / s."""
    return weights | {
        "W_enc": weights["W_enc"] * factor,
        "W_dec": weights["W_dec"] / factor,
        "b_dec": weights["b_dec"] / factor,
    }


def load_sae(
    source: str | os.PathLike,
    sae_id: str | None = None,
    device: str | torch.device | None = None,
    *,
    local_dir: str | os.PathLike | None = None,
    cfg_from: str | os.PathLike | None = None,
) -> Sae:
    """Return the SAE of a SAELens folder, a release name, or a `.pt`/`.safetensors` state dict.

    Args:
        source: a folder with cfg.json + sae_weights.safetensors; a release of `RELEASES`, resolved
            offline with `sae_id` (a folder `local_dir/<repo folder>/`, then the hub cache); or a state dict.
        sae_id: SAE within a release (`blocks.12.hook_resid_post`); for a state dict, its hook name.
        device: where the weights live (default cpu).
        local_dir: a folder holding release folders, searched before the hub cache.
        cfg_from: for a state dict, a folder or release whose cfg.json supplies the settings
            (the seed loaded `gemma-2b-it-res-jb` and then overwrote its weights); default SAELens's.
    """
    path = Path(source).expanduser().absolute()
    log_sparsity = None
    if path.is_file():
        if path.suffix not in STATE_DICT_SUFFIXES:
            raise ValueError(f"{path}: an SAE file must be a state dict ending in {' or '.join(STATE_DICT_SUFFIXES)}")
        weights, weights_path = read_state_dict_file(path), path
        if cfg_from is None:
            raw, known, cfg_file = state_dict_cfg(weights, sae_id=sae_id), None, path
        else:
            cfg_folder, known = _locate(cfg_from, sae_id, local_dir)
            raw, cfg_file = read_cfg(cfg_folder), cfg_folder / CFG_FILE
    else:
        if cfg_from is not None:
            raise ValueError(f"cfg_from applies to state-dict files only; {source} already has a cfg.json")
        folder, known = _locate(source, sae_id, local_dir)
        raw, weights, log_sparsity = read_sae_folder(folder)
        weights_path, cfg_file = folder / WEIGHTS_FILE, folder / CFG_FILE
    overrides: dict[str, Any] = {}
    if known is not None:
        release, known_id, entry = known
        overrides = {"release": release, "sae_id": known_id}
        if entry.neuronpedia_id:
            overrides["neuronpedia_id"] = entry.neuronpedia_id
    cfg = parse_cfg(raw, source=str(weights_path), overrides=overrides, where=str(cfg_file))
    check_trained(cfg, weights)
    weights = apply_scaling_factor(cfg, weights)
    if cfg.normalize_activations == "expected_average_only_in":
        factor = known[2].norm_scaling_factor if known is not None else None
        if factor is None:
            logger.warning(
                "%s: normalize_activations is expected_average_only_in but no norm_scaling_factor is known; "
                "inputs are used unscaled, as SAELens does",
                cfg.source,
            )
        else:
            weights = fold_norm_scaling_factor(weights, factor)
            cfg = cfg.model_copy(update={"normalize_activations": "none", "norm_scaling_factor": factor})
    check_sparsity(log_sparsity, cfg)
    sae = sae_class(cfg.architecture)(cfg, weights, device=device, log_sparsity=log_sparsity, weights_path=weights_path)
    logger.info(
        "loaded %s SAE %s (d_in %d, d_sae %d) on %s", cfg.architecture, sae.name, cfg.d_in, cfg.d_sae, sae.device
    )
    return sae


def _locate(
    source: str | os.PathLike, sae_id: str | None, local_dir: str | os.PathLike | None
) -> tuple[Path, tuple[str, str, SaeEntry] | None]:
    """Return (folder, registry match or None) of an SAE folder path or a release name.

    A folder named like a registry folder counts as that release SAE (Neuronpedia id, norm factor).
    """
    path = Path(source).expanduser()
    if path.is_dir():
        known = find_by_folder(path.name)
        if known is not None:
            logger.info("%s: recognised as %s / %s", path, known[0], known[1])
        return path, known
    if str(source) in RELEASES:
        sae_id, entry = get_entry(str(source), sae_id)
        return resolve_release(str(source), sae_id, local_dir=local_dir), (str(source), sae_id, entry)
    if path.suffix or os.sep in str(source):
        raise FileNotFoundError(f"{path}: no such SAE folder or state-dict file")
    raise ValueError(
        f"{source!r} is neither an SAE folder or file nor a known release; known releases: {sorted(RELEASES)}"
    )
