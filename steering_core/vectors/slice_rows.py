"""A concept slice's rows and their episodes, read whole: the methods that fit on rows (probe, latent effects) and
the evaluation's nulls read them through here."""

from __future__ import annotations

from pathlib import Path

import torch
from safetensors import safe_open

from steering_core.tensor_files import check_safetensors, load_torch_file, require_finite


def read_slice_rows(path: Path) -> torch.Tensor:
    """Return a concept slice's (rows, width) residuals: its .safetensors `residuals`, or the .pt beside it."""
    tensors = path.with_suffix(".safetensors")
    if tensors.is_file():
        check_safetensors(tensors)
        with safe_open(str(tensors), "pt") as handle:
            rows = handle.get_tensor("residuals")
    else:
        rows, tensors = load_torch_file(path), path
    require_finite(rows, tensors, "residuals", "re-run slice to rewrite it")
    return rows


def read_slice_episodes(path: Path) -> torch.Tensor | None:
    """Return a concept slice's (rows,) int64 `episode_index` column, or None when its .safetensors has none."""
    tensors = path.with_suffix(".safetensors")
    if not tensors.is_file():
        return None
    with safe_open(str(tensors), "pt") as handle:
        return handle.get_tensor("episode_index") if "episode_index" in handle.keys() else None
