"""SAE files on disk: SAELens folders (current and pre-6.0 `cfg.json`) and bare state-dict files.

A SAELens folder holds `cfg.json`, `sae_weights.safetensors` and optionally
`sparsity.safetensors`. Configs written before SAELens 6.0 use other key names
(`hook_point`, `activation_fn_str`, a boolean `normalize_activations`, no
`architecture`); `upgrade_legacy_cfg` applies SAELens's upgrade rules so both
layouts parse into one `SaeConfig`. The seed's fine-tuned SAE is a state dict
(`W_enc, W_dec, b_enc, b_dec`, optionally under `state_dict`) without any config.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Literal

import torch
from pydantic import Field
from safetensors import safe_open

from steering_core.devices import DTYPES
from steering_core.storage.fileio import read_json
from steering_core.storage.schema import StrictModel
from steering_core.tensor_files import check_safetensors, load_safetensors, load_torch_file

logger = logging.getLogger(__name__)

CFG_FILE = "cfg.json"
WEIGHTS_FILE = "sae_weights.safetensors"
SPARSITY_FILE = "sparsity.safetensors"  # tensor `sparsity`: log10 firing frequency per latent
FOLDER_FILES = (CFG_FILE, WEIGHTS_FILE)
STATE_DICT_SUFFIXES = (".pt", ".safetensors")
STATE_DICT_KEYS = ("W_enc", "W_dec", "b_enc", "b_dec")
HOOK_NAME = "blocks.{layer}.hook_resid_post"  # TransformerLens name of resid_post[layer]

NormalizeActivations = Literal["none", "expected_average_only_in", "constant_norm_rescale", "layer_norm"]
NORMALIZATIONS: tuple[str, ...] = NormalizeActivations.__args__

# SAELens 6.0 changed the cfg.json layout; configs of older versions (or without a version) get upgraded.
_FIRST_CURRENT_MAJOR = 6
_LEGACY_RENAMES = {
    "hook_point": "hook_name",
    "hook_point_head_index": "hook_head_index",
    "activation_fn_str": "activation_fn",
    "hook_point_layer": "hook_layer",  # dropped by SAELens; kept here as the layer it names
}
_LEGACY_DEFAULTS = {
    "apply_b_dec_to_input": True,
    "prepend_bos": True,
    "activation_fn": "relu",
    "architecture": "standard",
    "finetuning_scaling_factor": False,
}
_LEGACY_NORMALIZE = {False: "none", True: "expected_average_only_in"}
_LAYER_IN_HOOK = re.compile(r"^blocks\.(\d+)\.")
_FLAGS = ("apply_b_dec_to_input", "rescale_acts_by_decoder_norm", "finetuning_scaling_factor")  # JSON true/false


class SaeConfig(StrictModel):
    """What an SAE is and how it preprocesses inputs; defaults are `gemma-2b-it-res-jb` layer 12."""

    d_in: int = Field(2048, gt=0)  # Gemma-2B residual width
    d_sae: int = Field(16384, gt=0)  # 8x expansion of the seed's SAE
    architecture: str = "standard"
    hook_name: str | None = "blocks.12.hook_resid_post"
    hook_layer: int | None = 12
    dtype: Literal["float32", "float64", "float16", "bfloat16"] = "float32"
    normalize_activations: NormalizeActivations = "none"
    apply_b_dec_to_input: bool = True
    k: int | None = None  # topk only; SAELens's default is 100
    rescale_acts_by_decoder_norm: bool = False  # topk only
    finetuning_scaling_factor: bool = False  # a per-latent `scaling_factor` was folded into W_dec
    norm_scaling_factor: float | None = None  # "expected_average_only_in" factor folded into the weights
    model_name: str | None = None
    neuronpedia_id: str | None = None
    release: str | None = None
    sae_id: str | None = None
    source: str = ""


def is_legacy_cfg(raw: dict[str, Any]) -> bool:
    """Return whether a cfg.json predates SAELens 6.0 (no `sae_lens_version`, or one below 6)."""
    meta = _metadata(raw)
    version = raw.get("sae_lens_version") or meta.get("sae_lens_version")
    if not version:
        return True
    major = re.match(r"\s*v?(\d+)", str(version))
    return major is None or int(major.group(1)) < _FIRST_CURRENT_MAJOR


def upgrade_legacy_cfg(raw: dict[str, Any]) -> dict[str, Any]:
    """Return a pre-6.0 cfg dict with SAELens's renames and defaults applied (flat layout)."""
    cfg = {_LEGACY_RENAMES.get(key, key): value for key, value in raw.items()}
    for key, value in _LEGACY_DEFAULTS.items():
        cfg.setdefault(key, value)
    topk_k = (cfg.get("activation_fn_kwargs") or {}).get("k")
    if cfg["activation_fn"] == "topk" and topk_k is not None:
        cfg["architecture"] = "topk"
        cfg["k"] = topk_k
    normalize = cfg.get("normalize_activations")
    if isinstance(normalize, bool) or normalize is None:
        cfg["normalize_activations"] = _LEGACY_NORMALIZE.get(normalize, "none")
    return cfg


def parse_cfg(
    raw: dict[str, Any], *, source: str, overrides: dict[str, Any] | None = None, where: str | None = None
) -> SaeConfig:
    """Return the `SaeConfig` of a cfg.json dict in either layout; raise one error, naming `where` (the cfg file;
    default `source`), listing every problem.

    Each setting has one spelling: a key given twice (at the top level and in `metadata`, or under its pre-6.0
    and its current name) is refused, as are values of another type (`"16"` for an integer, `1` for a flag) and
    a topk SAE without its `k` (SAELens would take 100).
    """
    problems = _spelling_problems(raw)
    flat = upgrade_legacy_cfg(raw) if is_legacy_cfg(raw) else {**_metadata(raw), **raw}
    flat.update(overrides or {})
    for key in ("d_in", "d_sae"):
        if not _positive_int(flat.get(key)):
            problems.append(f"`{key}` is {flat.get(key)!r}, expected a positive integer")
    for key in _FLAGS:
        if not isinstance(flat.get(key, False), bool | None):
            problems.append(f"`{key}` is {flat[key]!r}, expected true or false")
    if flat.get("architecture") == "topk" and not _positive_int(flat.get("k")):
        found = "missing" if flat.get("k") is None else f"{flat['k']!r}"
        problems.append(f"`k` is {found}, expected a positive integer: a topk SAE keeps its k largest latents per "
                        "row (legacy configs: activation_fn_kwargs.k)")
    if flat.get("architecture") == "topk" and flat.get("activation_fn", "topk") != "topk" and (
            "activation_fn" in raw or "activation_fn_str" in raw):
        problems.append(f"`architecture` is 'topk' but `activation_fn` is {flat['activation_fn']!r}; give one "
                        "activation (remove activation_fn, or set it to 'topk')")
    dtype = str(flat.get("dtype", "float32")).removeprefix("torch.")
    if dtype not in DTYPES:
        problems.append(f"`dtype` is {flat.get('dtype')!r}, expected one of {sorted(DTYPES)}")
    normalize = flat.get("normalize_activations", "none")
    if normalize not in NORMALIZATIONS:
        problems.append(f"`normalize_activations` is {normalize!r}, expected one of {list(NORMALIZATIONS)}")
    activation = flat.get("activation_fn", "relu")
    if activation != "relu" and not (activation == "topk" and flat.get("architecture") == "topk"):
        problems.append(f"`activation_fn` is {activation!r}, expected 'relu' (or 'topk' with activation_fn_kwargs.k)")
    if flat.get("reshape_activations", "none") != "none":
        problems.append(f"`reshape_activations` is {flat['reshape_activations']!r}: only residual-stream SAEs ('none')")
    if problems:
        raise ValueError(f"{where or source}: unusable SAE config: " + "; ".join(problems))
    hook_name = flat.get("hook_name")
    architecture = str(flat.get("architecture", "standard"))
    return SaeConfig(
        d_in=flat["d_in"],
        d_sae=flat["d_sae"],
        architecture=architecture,
        hook_name=hook_name,
        hook_layer=flat["hook_layer"] if flat.get("hook_layer") is not None else hook_layer_of(hook_name),
        dtype=dtype,
        normalize_activations=normalize,
        apply_b_dec_to_input=_flag(flat, "apply_b_dec_to_input", True),
        k=flat["k"] if architecture == "topk" else None,
        rescale_acts_by_decoder_norm=_flag(flat, "rescale_acts_by_decoder_norm", False),
        finetuning_scaling_factor=_flag(flat, "finetuning_scaling_factor", False),
        model_name=flat.get("model_name"),
        neuronpedia_id=flat.get("neuronpedia_id"),
        release=flat.get("release"),
        sae_id=flat.get("sae_id"),
        source=source,
    )


def _spelling_problems(raw: dict[str, Any]) -> list[str]:
    """Return a problem for each setting a cfg.json gives under two keys (SAELens would keep one silently)."""
    problems = []
    if "metadata" in raw and "meta" in raw:
        problems.append("`metadata` and `meta` are both given; keep `metadata`")
    if is_legacy_cfg(raw):
        problems += [f"`{old}` and `{new}` are both given (the pre-6.0 and the current name); keep one"
                     for old, new in _LEGACY_RENAMES.items() if old in raw and new in raw]
        kwargs = raw.get("activation_fn_kwargs")
        if "k" in raw and isinstance(kwargs, dict) and "k" in kwargs:
            problems.append("`k` and `activation_fn_kwargs.k` are both given; keep one")
    else:
        problems += [f"`{key}` is given at the top level and in `metadata`; keep one"
                     for key in sorted(set(_metadata(raw)) & set(raw))]
    return problems


def _positive_int(value: Any) -> bool:
    """Return whether a JSON value is a positive integer (true and 4.0 are not)."""
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def _flag(flat: dict[str, Any], key: str, default: bool) -> bool:
    """Return a cfg flag, its default when absent or null."""
    value = flat.get(key)
    return default if value is None else value


def hook_layer_of(hook_name: str | None) -> int | None:
    """Return the block index named by a TransformerLens hook (`blocks.12.hook_resid_post` -> 12)."""
    match = _LAYER_IN_HOOK.match(hook_name or "")
    return int(match.group(1)) if match else None


def read_cfg(folder: Path) -> dict[str, Any]:
    """Return the raw cfg.json dict of a SAELens folder."""
    raw = read_json(folder / CFG_FILE)
    if not isinstance(raw, dict):
        raise ValueError(f"{folder / CFG_FILE}: expected a JSON object, found {type(raw).__name__}")
    return raw


def read_sae_folder(folder: Path) -> tuple[dict[str, Any], dict[str, torch.Tensor], torch.Tensor | None]:
    """Return (raw cfg dict, weights, log10 sparsity or None) of a SAELens folder."""
    missing = [name for name in FOLDER_FILES if not (folder / name).is_file()]
    if missing:
        raise FileNotFoundError(
            f"{folder}: not a SAELens SAE folder, missing {', '.join(missing)}; "
            f"a folder needs {' and '.join(FOLDER_FILES)} (optional {SPARSITY_FILE})"
        )
    raw = read_cfg(folder)
    weights = load_safetensors(folder / WEIGHTS_FILE)
    log_sparsity = None
    if (folder / SPARSITY_FILE).is_file():
        check_safetensors(folder / SPARSITY_FILE)
        with safe_open(folder / SPARSITY_FILE, framework="pt", device="cpu") as handle:
            if "sparsity" not in handle.keys():
                raise ValueError(f"{folder / SPARSITY_FILE}: no tensor `sparsity`, found {sorted(handle.keys())}")
            log_sparsity = handle.get_tensor("sparsity")
    return raw, weights, log_sparsity


def check_sparsity(log_sparsity: torch.Tensor | None, cfg: SaeConfig) -> None:
    """Raise unless a sparsity tensor (when there is one) holds one float per latent of the SAE `cfg` describes."""
    if log_sparsity is None:
        return
    if tuple(log_sparsity.shape) != (cfg.d_sae,) or not log_sparsity.is_floating_point():
        raise ValueError(f"{Path(cfg.source).parent / SPARSITY_FILE}: `sparsity` is {tuple(log_sparsity.shape)} "
                         f"{log_sparsity.dtype}, expected ({cfg.d_sae},) floats (one log10 firing frequency per "
                         "latent, d_sae of cfg.json); remove the file or use the one saved with these weights")


def read_state_dict_file(path: Path) -> dict[str, torch.Tensor]:
    """Return the SAE tensors of a `.pt`/`.safetensors` state dict (top level or under `state_dict`)."""
    if path.suffix == ".safetensors":
        payload: Any = load_safetensors(path)
    else:
        payload = load_torch_file(path)
    if isinstance(payload, dict) and not set(STATE_DICT_KEYS) <= payload.keys():
        payload = payload.get("state_dict", payload)
    if not isinstance(payload, dict) or not set(STATE_DICT_KEYS) <= payload.keys():
        found = sorted(payload) if isinstance(payload, dict) else type(payload).__name__
        raise ValueError(
            f"{path}: not an SAE state dict; expected tensors {', '.join(STATE_DICT_KEYS)} "
            f"at the top level or under `state_dict`, found {found}"
        )
    tensors = {key: value for key, value in payload.items() if isinstance(value, torch.Tensor)}
    ignored = sorted(set(payload) - set(tensors))
    if ignored:
        logger.warning("%s: ignoring non-tensor entries %s", path, ignored)
    return tensors


def state_dict_cfg(weights: dict[str, torch.Tensor], *, sae_id: str | None) -> dict[str, Any]:
    """Return a current-layout cfg dict for a bare state dict: shapes from W_enc, SAELens defaults."""
    d_in, d_sae = weights["W_enc"].shape
    return {
        "d_in": int(d_in),
        "d_sae": int(d_sae),
        "architecture": "jumprelu" if "threshold" in weights else "standard",
        "dtype": "float32",
        "sae_lens_version": f"{_FIRST_CURRENT_MAJOR}.0.0",
        "metadata": {"hook_name": sae_id if hook_layer_of(sae_id) is not None else None},
    }


def apply_scaling_factor(cfg: SaeConfig, weights: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Return weights with an old `scaling_factor` dropped (all ones) or folded into W_dec rows.

    SAELens drops an all-ones `scaling_factor`; any other requires `finetuning_scaling_factor`,
    under which SAELens 5 decoded `(f * scaling_factor) @ W_dec`, i.e. W_dec rows scaled.
    """
    if "scaling_factor" not in weights:
        return weights
    weights = dict(weights)
    scale = weights.pop("scaling_factor")
    if torch.allclose(scale, torch.ones_like(scale)):
        return weights
    if not cfg.finetuning_scaling_factor:
        raise ValueError(
            f"{cfg.source}: `scaling_factor` is not all ones but `finetuning_scaling_factor` is false; "
            "SAELens refuses this SAE too: set `finetuning_scaling_factor: true` in cfg.json if the factor is meant"
        )
    if cfg.rescale_acts_by_decoder_norm:
        raise ValueError(
            f"{cfg.source}: `scaling_factor` with `rescale_acts_by_decoder_norm` is ambiguous; "
            "fold the factor into W_dec before saving"
        )
    weights["W_dec"] = weights["W_dec"] * scale.to(weights["W_dec"].dtype)[:, None]
    return weights


def _metadata(raw: dict[str, Any]) -> dict[str, Any]:
    """Return the nested metadata of a current cfg (`metadata`, or `meta` in 6.0 release candidates)."""
    meta = raw.get("metadata", raw.get("meta"))
    return meta if isinstance(meta, dict) else {}
