"""The one NaN/Inf test of the library, for numpy arrays and torch tensors alike (importing neither torch nor
anything heavy, so light commands that read demos stay light)."""

from __future__ import annotations

from typing import Any

import numpy as np


def non_finite(values: Any, name: str, first_row: int = 0) -> str | None:
    """Return what is wrong with `values` (a numpy array or torch tensor) if it holds NaN or Inf, naming tensor
    `name` and the first bad element, else None; one reduction when all is well.

    `first_row`: the row number of `values[0]` in the whole tensor, when `values` is a chunk of it.
    """
    if isinstance(values, np.ndarray):
        if not np.issubdtype(values.dtype, np.floating) or bool(np.isfinite(values).all()):
            return None
        at = [int(i) for i in np.argwhere(~np.isfinite(values))[0]]
    else:  # a torch tensor
        if not values.is_floating_point() or bool(values.isfinite().all()):
            return None
        at = (~values.isfinite()).nonzero()[0].tolist()
    value = values[tuple(at)].item()
    if at:
        at[0] += first_row
    where_in = f" at {tuple(at) if len(at) > 1 else at[0]}" if at else ""
    return f"tensor `{name}` holds NaN or Inf ({value}{where_in}); expected finite values"
