"""MP4 videos of episodes: uint8 (H, W, 3) RGB frames encoded with PyAV (installed with lerobot), written atomically.

H.264 (libx264) when the PyAV wheel has it, else MPEG-4 part 2; yuv420p, which every browser and player reads.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path

import numpy as np

from steering_core.storage.fileio import atomic_path

# a recorded episode has a frame per step of LIBERO's 20 Hz control: 20 fps plays it in real time
DEFAULT_FPS = 20
_CODECS = ("libx264", "mpeg4")


def video_codec() -> str:
    """Return the encoder used: libx264 if this PyAV build has it, else mpeg4."""
    import av

    return next(name for name in _CODECS if name in av.codecs_available)


def write_video(path: str | os.PathLike, frames: Sequence[np.ndarray], fps: float = DEFAULT_FPS) -> Path:
    """Write `frames` (each uint8 (H, W, 3) RGB, H and W even, all one size) as an MP4 at `fps`; return the path."""
    import av

    path = Path(path)
    if not len(frames):
        raise ValueError(f"{path}: no frames to write; record frames (record_frames=True) for the episodes to film")
    shape = np.shape(frames[0])
    bad = [i for i, f in enumerate(frames) if np.asarray(f).dtype != np.uint8 or np.shape(f) != shape]
    if bad or len(shape) != 3 or shape[2] != 3 or shape[0] % 2 or shape[1] % 2:
        raise ValueError(f"{path}: frames must be uint8 (H, W, 3) with even H and W, all of one size; frame 0 is "
                         f"{np.asarray(frames[0]).dtype} {shape}" + (f", frames {bad[:5]} differ" if bad else ""))
    with atomic_path(path) as tmp, av.open(str(tmp), mode="w", format="mp4") as container:
        stream = container.add_stream(video_codec(), rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height, stream.pix_fmt = shape[1], shape[0], "yuv420p"
        for frame in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")))
        container.mux(stream.encode())  # flush the encoder's delayed frames
    return path
