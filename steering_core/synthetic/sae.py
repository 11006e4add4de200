"""Tiny SAEs in real on-disk formats: SAELens folders (current or pre-6.0 cfg.json) and seed state dicts.

Real dimensions stay the defaults (Gemma-2B width 2048, 16384 latents); tests pass tiny ones.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import torch
from safetensors.torch import save_file

from steering_core.sae.formats import CFG_FILE, DTYPES, HOOK_NAME, SPARSITY_FILE, WEIGHTS_FILE, NormalizeActivations
from steering_core.sae.registry import HUB_REPO_DIR, RELEASES, get_entry
from steering_core.storage.fileio import atomic_dir, atomic_path, write_json

CURRENT_VERSION = "6.18.0"  # SAELens version written into current-layout configs
SNAPSHOT_REVISION = "0" * 40  # fake commit hash of a hub-cache snapshot


def make_sae_weights(
    d_in: int = 2048,
    d_sae: int = 16384,
    *,
    architecture: str = "standard",
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> dict[str, torch.Tensor]:
    """Return random SAE tensors whose latents fire on a fraction of unit-variance inputs.

    Decoder rows have unit norm; the encoder is their transpose plus noise, and a negative
    b_enc makes about a third of the latents fire on standard-normal inputs.
    """
    gen = torch.Generator().manual_seed(seed)  # float32 draws: real sizes stay at 2 x 128 MiB
    W_dec = torch.randn(d_sae, d_in, generator=gen)
    W_dec = W_dec / W_dec.norm(dim=-1, keepdim=True) * (0.5 + torch.rand(d_sae, 1, generator=gen))
    weights = {
        "W_enc": W_dec.T / W_dec.norm(dim=-1) + 0.1 * torch.randn(d_in, d_sae, generator=gen),
        "b_enc": -0.5 * torch.rand(d_sae, generator=gen),
        "W_dec": W_dec,
        "b_dec": 0.1 * torch.randn(d_in, generator=gen),
    }
    if architecture == "jumprelu":
        weights["threshold"] = 0.3 * torch.rand(d_sae, generator=gen)
    return {name: tensor.to(dtype).contiguous() for name, tensor in weights.items()}


def write_sae_folder(
    folder: str | os.PathLike,
    *,
    d_in: int = 2048,
    d_sae: int = 16384,
    architecture: Literal["standard", "jumprelu", "topk"] = "standard",
    normalize_activations: NormalizeActivations = "none",
    apply_b_dec_to_input: bool = True,
    layout: Literal["current", "legacy"] = "current",
    k: int = 100,
    rescale_acts_by_decoder_norm: bool = False,
    hook_layer: int = 12,
    neuronpedia_id: str | None = None,
    dtype: Literal["float32", "float64", "float16", "bfloat16"] = "float32",
    scaling_factor: torch.Tensor | None = None,
    finetuning_scaling_factor: bool = False,
    with_sparsity: bool = True,
    seed: int = 0,
) -> Path:
    """Write a SAELens SAE folder (cfg.json, sae_weights.safetensors, sparsity.safetensors); return it."""
    weights = make_sae_weights(d_in, d_sae, architecture=architecture, seed=seed, dtype=DTYPES[dtype])
    if scaling_factor is not None:
        weights["scaling_factor"] = scaling_factor.to(DTYPES[dtype])
    settings = {
        "d_in": d_in,
        "d_sae": d_sae,
        "dtype": dtype,
        "device": "cpu",
        "apply_b_dec_to_input": apply_b_dec_to_input,
    }
    hook_name = HOOK_NAME.format(layer=hook_layer)
    if layout == "current":
        cfg = _current_cfg(settings, architecture, normalize_activations, k, rescale_acts_by_decoder_norm)
        cfg["metadata"] = {
            "model_name": "gemma-2b-it",
            "hook_name": hook_name,
            "neuronpedia_id": neuronpedia_id,
            "prepend_bos": True,
            "context_size": 1024,
            "sae_lens_version": CURRENT_VERSION,
        }
    else:
        cfg = _legacy_cfg(settings, architecture, normalize_activations, k)
        cfg["finetuning_scaling_factor"] = finetuning_scaling_factor
        cfg |= {"hook_point": hook_name, "hook_point_layer": hook_layer, "hook_point_head_index": None}
        cfg |= {"model_name": "gemma-2b-it", "context_size": 1024, "neuronpedia_id": neuronpedia_id}
    with atomic_dir(folder, overwrite=True) as tmp:
        tmp.mkdir()
        write_json(tmp / CFG_FILE, cfg)
        save_file(weights, tmp / WEIGHTS_FILE)
        if with_sparsity:
            gen = torch.Generator().manual_seed(seed + 1)
            save_file({"sparsity": -4 + 3 * torch.rand(d_sae, generator=gen)}, tmp / SPARSITY_FILE)
    return Path(folder)


def write_sae_state_dict(
    path: str | os.PathLike,
    *,
    d_in: int = 2048,
    d_sae: int = 16384,
    architecture: Literal["standard", "jumprelu"] = "standard",
    nested: bool = False,
    seed: int = 0,
) -> Path:
    """Write a seed-style SAE state dict (`.pt`, optionally under `state_dict`, or `.safetensors`); return it."""
    path = Path(path)
    weights = make_sae_weights(d_in, d_sae, architecture=architecture, seed=seed)
    with atomic_path(path) as tmp:
        if path.suffix == ".safetensors":
            save_file(weights, tmp)
        else:
            torch.save({"state_dict": weights, "step": 1000} if nested else weights, tmp)
    return path


def write_release_to_hub_cache(
    cache_dir: str | os.PathLike, release: str, sae_id: str | None = None, **folder_kwargs
) -> Path:
    """Write one release SAE where huggingface_hub caches it (`models--org--name/snapshots/<rev>/<folder>`)."""
    sae_id, entry = get_entry(release, sae_id)
    org, name = RELEASES[release].repo_id.split("/")
    repo_dir = Path(cache_dir) / HUB_REPO_DIR.format(org=org, name=name)
    (repo_dir / "refs").mkdir(parents=True, exist_ok=True)
    (repo_dir / "refs" / "main").write_text(SNAPSHOT_REVISION)
    folder_kwargs.setdefault("hook_layer", int(sae_id.split(".")[1]))
    return write_sae_folder(repo_dir / "snapshots" / SNAPSHOT_REVISION / entry.folder, **folder_kwargs)


def _current_cfg(settings: dict, architecture: str, normalize: str, k: int, rescale: bool) -> dict:
    """Return a SAELens >= 6 cfg.json body (hook and model details go under `metadata`)."""
    cfg = {**settings, "normalize_activations": normalize, "reshape_activations": "none", "architecture": architecture}
    if architecture == "topk":
        cfg |= {"k": k, "rescale_acts_by_decoder_norm": rescale}
    return cfg


def _legacy_cfg(settings: dict, architecture: str, normalize: str, k: int) -> dict:
    """Return a pre-6.0 cfg.json body: boolean normalisation where it fits, topk as an activation_fn."""
    legacy_normalize = {"none": False, "expected_average_only_in": True}.get(normalize, normalize)
    cfg = {**settings, "normalize_activations": legacy_normalize, "sae_lens_training_version": "3.5.0", "lr": 4e-5}
    if architecture == "topk":
        cfg |= {"activation_fn_str": "topk", "activation_fn_kwargs": {"k": k}}
    else:
        cfg["activation_fn_str"] = "relu"
    if architecture == "jumprelu":
        cfg["architecture"] = "jumprelu"
    return cfg
