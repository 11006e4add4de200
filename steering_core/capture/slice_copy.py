"""Slicing's second pass over one shard: its selected rows, read once, go straight to the concepts' files.

The shard is read through one bounded buffer. A checked shard is read whole, front to back, and every
byte goes to its digest (`shard_checks`), so checking costs no second read; an unchecked one (a shard read
by ranges from a bucket is never checked whole) is read only in the runs of rows some concept needs, runs
joined across their smallest gaps while the unneeded rows read stay within SLACK of the needed ones: few
reads (one ranged GET each, per buffer), and bytes read at most 1 + SLACK times the rows selected.
Rows are written where they belong in each concept's `.safetensors` (`SliceFile.write`); with
reduce=frame a concept's rows of the shard are gathered and their per-frame means written instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np
import torch

from steering_core.capture.shard_checks import Digest
from steering_core.capture.shards import SHARD_FIX
from steering_core.capture.slice_files import SliceFile
from steering_core.tensor_files import TensorLocation, require_finite

SLACK = 0.1  # unneeded rows an unchecked copy may read to join runs of needed ones, per needed row


@dataclass
class Part:
    """One shard's share of a concept's output: which rows to read and where their units go."""

    rows: np.ndarray  # (n,) ascending row numbers in the shard
    dest: np.ndarray  # output row of each unit: of each row (reduce=token) or of each frame (reduce=frame)
    frame_of_row: np.ndarray | None  # reduce=frame: (n,) the shard-local frame of each row


def copy_shard(
    handle: BinaryIO,
    location: TensorLocation,
    parts: Sequence[tuple[Part, SliceFile]],
    buffer: torch.Tensor,
    device: str,
    digest: Digest | None = None,
) -> None:
    """Copy each part's rows of the shard open in `handle` (unbuffered) to its file, through `buffer`.

    `location` is the shard's residual matrix, `buffer` a uint8 CPU tensor of at least one row; `device`
    is where frame means are computed. With a `digest`, every byte of the file is fed to it.
    Rows holding NaN or Inf are refused, naming the shard.
    """
    count, row_bytes = location.shape[0], location.row_bytes
    if digest is not None:
        _feed(handle, 0, location.offset, buffer, digest)  # header and row columns
        spans = [(0, count)]
    else:
        spans = _spans(np.unique(np.concatenate([part.rows for part, _ in parts] or [np.empty(0, np.int64)])))
    gathered = {id(part): torch.empty(len(part.rows), location.shape[1]) for part, _ in parts
                if part.frame_of_row is not None}
    per_chunk = buffer.numel() // row_bytes
    for start, size in ((start, min(per_chunk, stop - start)) for first, stop in spans
                        for start in range(first, stop, per_chunk)):
        raw = _read(handle, location.offset + start * row_bytes, buffer[: size * row_bytes], location)
        if digest is not None:
            digest.update(raw.numpy())
        rows = raw.view(location.dtype).view(-1, *location.shape[1:]).to(torch.float32)  # no copy when float32
        require_finite(rows, location.path, location.name, SHARD_FIX, start)
        for part, file in parts:
            low, high = np.searchsorted(part.rows, [start, start + len(rows)])
            if low == high:
                continue
            if part.frame_of_row is not None:
                gathered[id(part)][low:high] = rows[torch.from_numpy(part.rows[low:high] - start)]
                continue
            for a, b in _runs(part.rows[low:high], part.dest[low:high]):
                at = int(part.rows[low + a]) - start
                file.write(int(part.dest[low + a]), rows[at : at + b - a])
    if digest is not None:
        _feed(handle, location.offset + count * row_bytes, None, buffer, digest)  # whatever follows (nothing, as written)
    for part, file in parts:
        if part.frame_of_row is not None:
            means = _frame_means(gathered[id(part)], part.frame_of_row, len(part.dest), device)
            for a, b in _runs(part.dest):
                file.write(int(part.dest[a]), means[a:b])


def _read(handle: BinaryIO, offset: int, out: torch.Tensor, location: TensorLocation) -> torch.Tensor:
    """Fill uint8 `out` with the file's bytes from `offset`; raise naming the file when it ends first."""
    handle.seek(offset)
    if handle.readinto(out.numpy()) != out.numel():
        raise ValueError(f"{location.path}: the file ends inside tensor `{location.name}`; it is truncated")
    return out


def _feed(handle: BinaryIO, start: int, stop: int | None, buffer: torch.Tensor, digest: Digest) -> None:
    """Feed the file's bytes [start, stop) (stop None: to its end) to `digest`, through `buffer`."""
    view = buffer.numpy()
    handle.seek(start)
    while stop is None or start < stop:
        size = handle.readinto(view[: len(view) if stop is None else min(len(view), stop - start)])
        if not size:
            break
        digest.update(view[:size])
        start += size


def _spans(rows: np.ndarray) -> list[tuple[int, int]]:
    """Return [start, stop) spans covering the ascending unique `rows`: their runs, joined across the smallest
    gaps while the rows of the gaps joined total at most SLACK times the rows."""
    if not len(rows):
        return []
    gaps = np.diff(rows) - 1
    breaks = np.flatnonzero(gaps)  # rows[i + 1] starts a new run
    by_size = breaks[np.argsort(gaps[breaks], kind="stable")]
    kept = np.sort(by_size[np.cumsum(gaps[by_size]) > SLACK * len(rows)])
    return list(zip(rows[np.concatenate([[0], kept + 1])].tolist(), (rows[np.append(kept, -1)] + 1).tolist()))


def _runs(*sequences: np.ndarray) -> list[tuple[int, int]]:
    """Return [start, stop) spans over which every sequence counts up by one (one read or write each)."""
    steps = np.zeros(max(len(sequences[0]) - 1, 0), dtype=bool)
    for values in sequences:
        steps |= np.diff(values) != 1
    breaks = (np.flatnonzero(steps) + 1).tolist()
    return list(zip([0, *breaks], [*breaks, len(sequences[0])]))


def _frame_means(residuals: torch.Tensor, frame_of_row: np.ndarray, frames: int, device: str) -> torch.Tensor:
    """Return (frames, width) float32 means of the rows of each frame, summed in float64 on `device`."""
    inverse_t = torch.from_numpy(frame_of_row).to(device)
    sums = torch.zeros(frames, residuals.shape[1], dtype=torch.float64, device=device)
    sums.index_add_(0, inverse_t, residuals.to(device, torch.float64))
    counts = torch.bincount(inverse_t, minlength=frames).to(torch.float64)
    return (sums / counts[:, None]).to("cpu", torch.float32)
