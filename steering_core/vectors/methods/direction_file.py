"""A method's direction file: `<pair folder>/<method>_direction.safetensors`, one unit vector and what it means.

Tensor `direction` (width,) float32, unit length, pointing from the negative concept to the positive one.
Metadata (JSON strings): `method`, `pair`, `layer`, `norm` (the method's vector before normalising),
`positive_level` and `negative_level` (m₊, m₋: the mean projection of each concept's training rows on the unit
direction, the clamp mode's levels), `mean_residual_norm` (R, the add mode's α unit) and `record` (how the method
chose it). The same entry, without the tensor, is listed under `methods` in the pair's directions.json.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from steering_core.pairs import SIDES
from steering_core.tensor_files import MIN_NORMAL, load_safetensors, require_finite, save_safetensors
from steering_core.vectors.concept_stats import ConceptStats

METHOD_FILE = "{method}_direction.safetensors"
TENSOR_KEY = "direction"


@dataclass(frozen=True)
class MethodDirection:
    """One method's unit direction of a (pair, layer) with its clamp levels and record."""

    method: str
    pair: str
    layer: int
    direction: torch.Tensor      # (width,) float32, unit length
    norm: float                  # the method's vector's length before normalising
    levels: tuple[float, float]  # (m₋, m₊): the negative and positive concepts' mean projections on `direction`
    mean_residual_norm: float | None
    record: dict[str, Any]

    def entry(self, file_name: str) -> dict[str, Any]:
        """Return the directions.json entry of this direction (everything but the tensor)."""
        return {"file": file_name, "norm": self.norm, "negative_level": self.levels[0],
                "positive_level": self.levels[1], "record": self.record}


def unit_direction(vector: torch.Tensor, where: str) -> tuple[torch.Tensor, float]:
    """Return (vector / ‖vector‖ as float32, ‖vector‖), computed in float64; ValueError naming `where` for a
    vector holding NaN or Inf, or whose length is zero or a float32 subnormal."""
    vector = vector.detach().to("cpu", torch.float64).flatten()
    require_finite(vector, where, TENSOR_KEY)
    norm = float(vector.norm())
    if not norm >= MIN_NORMAL:  # normalising a subnormal length amplifies rounding, not a direction
        raise ValueError(f"{where}: the direction's length is {norm:.3g}, below float32's smallest normal number "
                         f"({MIN_NORMAL:.3g}): it points nowhere, nothing to steer along")
    return (vector / norm).float(), norm


def method_direction(method: str, pair: str, layer: int, vector: torch.Tensor, stats: dict[str, ConceptStats],
                     mean_residual_norm: float | None, record: dict[str, Any]) -> MethodDirection:
    """Return a method's unit direction with its levels, the concepts' residual means projected on it."""
    unit, norm = unit_direction(vector, f"pair {pair!r}, layer {layer}, method {method!r}")
    means = {side: stats[side].residual_mean.double() for side in SIDES}
    if means["positive"].numel() != unit.numel():
        raise ValueError(f"pair {pair!r}, layer {layer}, method {method!r}: the direction has {unit.numel()} values, "
                         f"the layer's residuals {means['positive'].numel()}")
    levels = tuple(float(means[side] @ unit.double()) for side in ("negative", "positive"))
    return MethodDirection(method, pair, layer, unit, norm, levels, mean_residual_norm, record)


def write_method_direction(folder: Path, direction: MethodDirection) -> str:
    """Write `<method>_direction.safetensors` into `folder`; return its file name."""
    name = METHOD_FILE.format(method=direction.method)
    metadata = {"method": direction.method, "pair": direction.pair, "layer": direction.layer, "norm": direction.norm,
                "negative_level": direction.levels[0], "positive_level": direction.levels[1],
                "mean_residual_norm": direction.mean_residual_norm, "record": direction.record}
    save_safetensors({TENSOR_KEY: direction.direction.contiguous()}, folder / name,
                     metadata={key: json.dumps(value) for key, value in metadata.items()})
    return name


def read_method_direction(path: Path) -> MethodDirection:
    """Return the direction stored at `path`; ValueError naming the file for a damaged one."""
    from safetensors import safe_open

    tensors = load_safetensors(path)
    with safe_open(str(path), "pt") as handle:
        raw = handle.metadata() or {}
    try:
        meta = {key: json.loads(value) for key, value in raw.items()}
        levels = (float(meta["negative_level"]), float(meta["positive_level"]))
        direction = tensors[TENSOR_KEY]
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: not a method direction file ({type(err).__name__}: {err}); re-run steer") from None
    require_finite(direction, path, TENSOR_KEY, "re-run steer to rewrite it")
    if direction.ndim != 1 or not direction.is_floating_point():
        raise ValueError(f"{path}: `{TENSOR_KEY}` is {tuple(direction.shape)} {direction.dtype}, expected (width,) "
                         "float32; re-run steer")
    return MethodDirection(meta["method"], meta["pair"], int(meta["layer"]), direction.float(), float(meta["norm"]),
                           levels, meta.get("mean_residual_norm"), meta.get("record") or {})
