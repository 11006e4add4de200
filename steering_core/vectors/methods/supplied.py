"""`file`: a direction the user supplies, so that a vector from another tool is evaluated on equal terms.

`steering.direction_file` names it, with `{pair}` and `{layer}` filled in per (pair, layer): a safetensors file
holding one floating-point tensor of the layer's width, finite and not zero. Its path and sha256 are recorded.
"""

from __future__ import annotations

from pathlib import Path

import torch

from steering_core.storage.digests import file_digest
from steering_core.tensor_files import load_safetensors
from steering_core.vectors.methods.direction_file import unit_direction
from steering_core.vectors.methods.registry import MethodResult, PairData, register_method


def supplied_path(template: str | None, pair: str, layer: int) -> Path:
    """Return the file of (pair, layer) named by the `direction_file` template; ValueError without a template."""
    if not template:
        raise ValueError(f"pair {pair!r}, layer {layer}: method `file` needs steering.direction_file (a safetensors "
                         "path, {pair} and {layer} filled in per pair and layer)")
    try:
        return Path(template.format(pair=pair, layer=layer)).expanduser()
    except (KeyError, IndexError, ValueError) as err:
        raise ValueError(f"steering.direction_file {template!r}: only {{pair}} and {{layer}} may be filled in "
                         f"({type(err).__name__}: {err})") from None


def read_supplied(template: str | None, pair: str, layer: int, width: int) -> torch.Tensor:
    """Return the supplied (width,) float32 direction of (pair, layer); ValueError naming the pair, layer, setting
    and file when it is missing, unreadable, not one float tensor of `width` values, non-finite or zero."""
    path = supplied_path(template, pair, layer)
    where = f"pair {pair!r}, layer {layer}, steering.direction_file {path}"
    if not path.is_file():
        raise ValueError(f"{where}: file not found")
    try:
        tensors = load_safetensors(path)
    except (OSError, ValueError) as err:
        raise ValueError(f"{where}: not a readable safetensors file ({str(err).removeprefix(f'{path}: ')})") from None
    if len(tensors) != 1:
        raise ValueError(f"{where}: holds {len(tensors)} tensors {sorted(tensors)}, expected one direction")
    (name, tensor), = tensors.items()
    if not tensor.is_floating_point() or tuple(tensor.shape) != (width,):
        raise ValueError(f"{where}: `{name}` is {tuple(tensor.shape)} {str(tensor.dtype).removeprefix('torch.')}, "
                         f"expected ({width},) float (the layer's residual width)")
    unit_direction(tensor, where)  # finite, not zero
    return tensor.float()


@register_method("file", "a direction supplied as a safetensors file (steering.direction_file)", needs_file=True)
def supplied_direction(data: PairData) -> MethodResult:
    """Return the supplied direction as it is (its sign is the user's: positive − negative)."""
    width = data.stats["positive"].residual_mean.numel()
    tensor = read_supplied(data.settings.direction_file, data.pair, data.layer, width)
    path = supplied_path(data.settings.direction_file, data.pair, data.layer)
    return MethodResult(tensor, {"source": str(path.resolve()), "sha256": file_digest(path)})
