"""A tensor that stands for one on another device, so a CPU-only suite can see device-placement bugs.

`elsewhere(t)` returns `t` as a `Foreign` tensor: its values are on the CPU, but any operation that mixes it with
an ordinary (non-scalar) tensor raises the error CUDA raises for a CPU tensor meeting a CUDA one. Operations on
foreign tensors alone stay foreign (as CUDA ops stay on CUDA); `.to(device)`, `.to(tensor)`, `.cpu()` and
`.cuda()` return an ordinary tensor: moving it to the model's device is the only way in.
"""

from __future__ import annotations

import torch
from torch.utils._pytree import tree_flatten

MOVES = {torch.Tensor.to, torch.Tensor.cpu, torch.Tensor.cuda}
MIXED = "Expected all tensors to be on the same device (a Foreign tensor met one on the model's device)"


class Foreign(torch.Tensor):
    """A CPU tensor playing one on another device; see the module docstring."""

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in MOVES and _moves_device(func, args, kwargs):
            with torch._C.DisableTorchFunctionSubclass():
                return func(*args, **kwargs).as_subclass(torch.Tensor)
        with torch._C.DisableTorchFunctionSubclass():  # reading .ndim here must not come back to this function
            tensors = [(isinstance(item, Foreign), item.ndim) for item in tree_flatten((args, kwargs))[0]
                       if isinstance(item, torch.Tensor)]
        if any(is_foreign and ndim for is_foreign, ndim in tensors) and any(
                not is_foreign and ndim for is_foreign, ndim in tensors):
            raise RuntimeError(f"{MIXED}: {getattr(func, '__name__', func)}")
        return super().__torch_function__(func, types, args, kwargs)


def _moves_device(func, args, kwargs) -> bool:
    """Return True when this `.to`/`.cpu`/`.cuda` call names a device (or a tensor to follow)."""
    if func is not torch.Tensor.to:
        return True
    named = [*args[1:], kwargs.get("device"), kwargs.get("other")]
    return any(isinstance(item, (str, torch.device, torch.Tensor)) for item in named)


def elsewhere(tensor: torch.Tensor) -> Foreign:
    """Return `tensor` as a Foreign tensor (same values)."""
    return tensor.as_subclass(Foreign)
