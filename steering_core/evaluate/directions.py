"""The directions compared by the evaluation, all in the residual space of one layer of one stream.

Language model (layer L, from phase 3's files):
- `residual_direction`: the pair's SAE direction (latent difference @ W_dec, as phase 3 wrote it);
- `mean_difference_direction`: the plain difference of the concepts' residual means;
- `top_k_latents`: only the k largest |latent differences|, decoded without b_dec;
Action expert (expert layer K, from the pair's `decision` slices, `evaluate.expert_layers`):
- `decision_mean_difference`: mean(positive decision rows) − mean(negative decision rows);
The null directions (`random_NN`, `permuted_NN`) are added by `steering_core.evaluate.nulls`.

Without an SAE, phase 3's `residual_direction` is the mean difference itself; it is evaluated once.
"""

from __future__ import annotations

from pathlib import Path

import torch
from safetensors import safe_open

from steering_core.sae.model import Sae
from steering_core.tensor_files import check_safetensors, load_torch_file, require_finite
from steering_core.vectors.directions import read_pair_vectors

RESIDUAL = "residual_direction"
DECISION = "decision_mean_difference"
MEAN_DIFFERENCE = "mean_difference_direction"
TOP_K = "top_k_latents"
RANDOM = "random_{index:02d}"
PERMUTED = "permuted_{index:02d}"
NULL_PREFIXES = ("random_", "permuted_")


def is_null(name: str) -> bool:
    """Return True for a null direction's name (random or permuted)."""
    return name.startswith(NULL_PREFIXES)


def top_k_direction(latent_direction: torch.Tensor, sae: Sae, k: int) -> torch.Tensor:
    """Return the residual image of the k largest-|value| latents of a (d_sae,) direction, without b_dec."""
    kept = torch.zeros_like(latent_direction)
    top = latent_direction.abs().topk(min(k, latent_direction.numel())).indices
    kept[top] = latent_direction[top]
    return sae.decode_direction(kept).detach().to("cpu", torch.float32)


def pair_directions(pair_path: Path, sae: Sae | None, *, top_k: int) -> dict[str, torch.Tensor]:
    """Return name -> (width,) float32 direction for one pair folder of phase 3.

    Raises ValueError when a direction is zero (nothing to scale) or when the SAE does not match the
    pair's latent direction.
    """
    vectors = read_pair_vectors(pair_path)
    directions = {RESIDUAL: vectors["residual"].float()}
    if "latent" in vectors:
        directions[MEAN_DIFFERENCE] = vectors["mean"].float()
        if sae is not None:
            if vectors["latent"].numel() != sae.cfg.d_sae:
                raise ValueError(f"{pair_path}: latent_direction has {vectors['latent'].numel()} latents, the SAE "
                                 f"{sae.name} has {sae.cfg.d_sae}; evaluate with the SAE phase 3 used")
            directions[TOP_K] = top_k_direction(vectors["latent"].float(), sae, top_k)
    return nonzero(directions, str(pair_path))


def decision_directions(slices: tuple[Path, Path]) -> dict[str, torch.Tensor]:
    """Return name -> (expert width,) float32 direction of one pair at one expert layer.

    `slices` are the (positive, negative) `decision` slices of the layer (training episodes only); the
    direction is the difference of their row means (computed in float64).
    """
    means = [read_slice_rows(path).double().mean(0) for path in slices]
    directions = {DECISION: (means[0] - means[1]).float()}
    return nonzero(directions, f"decision slices {slices[0].parent}")


def nonzero(directions: dict[str, torch.Tensor], where: str) -> dict[str, torch.Tensor]:
    """Return `directions`; raise ValueError naming `where` when one is zero (nothing to scale)."""
    zero = [name for name, v in directions.items() if not float(v.norm()) > 0]
    if zero:
        raise ValueError(f"{where}: direction(s) {zero} are zero; the two concepts have equal means")
    return directions


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


def check_width(directions: dict[str, torch.Tensor], width: int, where: str, stream: str = "lm") -> None:
    """Raise ValueError naming every direction whose shape is not (width,) (the width of `stream`)."""
    wrong = {name: tuple(v.shape) for name, v in directions.items() if tuple(v.shape) != (width,)}
    if wrong:
        what = "action expert's" if stream == "expert" else "language model's"
        raise ValueError(f"{where}: directions {wrong} do not match the policy's {what} residual width ({width},); "
                         "use vectors of the same model and layer")
