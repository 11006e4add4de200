"""Demo frames as the dataset stores them: oriented, then resized (LIBERO stores 128x128 renders).

Orientation: raw LIBERO renders are upside down (OpenGL convention). The frames of
physical-intelligence/libero were flipped along both H and W by OpenVLA's regeneration,
and openpi's eval client flips live frames the same way, so `rotate180` (default) is what
the checkpoint saw in training. `as_stored` keeps the raw orientation, for datasets meant
for models trained on raw renders.

Resizing: LIBERO stores 128x128 frames; they are resized to `image_size` with bilinear
interpolation, antialiased, half-pixel centres (torch `interpolate(antialias=True)`, which
matches openpi's JAX resize), rounded and clipped to uint8. `bicubic` (PIL's) reproduces the
seed's converter; so does `demo_order="lexicographic"` (the seed iterated `sorted(keys)`, which
puts demo_10 before demo_2) with `orientation="as_stored"` (the seed did not flip).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

Orientation = Literal["rotate180", "as_stored"]
ResizeFilter = Literal["antialiased_bilinear", "bicubic"]
_RESIZE_CHUNK = 64  # frames resized per call: bounds float32 scratch memory for long demos


def prepare_frames(
    frames: np.ndarray, orientation: Orientation, image_size: int, resize_filter: ResizeFilter = "antialiased_bilinear"
) -> np.ndarray:
    """Return (T, image_size, image_size, 3) uint8 frames, oriented then resized (see module docstring).

    `frames` is (T, H, W, 3) uint8 as stored in LIBERO files.
    """
    if orientation == "rotate180":
        frames = frames[:, ::-1, ::-1]
    if frames.shape[1:3] == (image_size, image_size):
        return np.ascontiguousarray(frames)
    if resize_filter == "bicubic":
        from PIL import Image

        size = (image_size, image_size)
        return np.stack([np.asarray(Image.fromarray(np.ascontiguousarray(f)).resize(size, Image.BICUBIC)) for f in frames])
    import torch  # deferred: torch is heavy and only conversion needs it
    import torch.nn.functional as F

    out = np.empty((frames.shape[0], image_size, image_size, 3), dtype=np.uint8)
    for start in range(0, frames.shape[0], _RESIZE_CHUNK):
        chunk = torch.from_numpy(np.ascontiguousarray(frames[start : start + _RESIZE_CHUNK]))
        x = chunk.permute(0, 3, 1, 2).to(torch.float32)  # (t, 3, H, W)
        x = F.interpolate(x, size=(image_size, image_size), mode="bilinear", align_corners=False, antialias=True)
        out[start : start + len(chunk)] = x.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()
    return out
