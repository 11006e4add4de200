"""Read safetensors tensors straight from the file into memory the caller owns, without a memory map.

safetensors' `safe_open` reads through a memory map: the file pages it touches stay mapped, and count
in the process's resident memory, for as long as the file is open. Reading with plain file reads
instead puts each byte once into its destination (or into one bounded buffer when the dtype or device
differs), so loading a checkpoint costs the converted tensors and nothing more, and slicing a shard
copies each selected row once.

Format (safetensors): an 8-byte little-endian header size N, N bytes of JSON mapping each name to
`dtype`, `shape` and `data_offsets` (begin, end) relative to the end of the header, then the data,
little-endian (as torch stores tensors on x86 and ARM).
"""

from __future__ import annotations

import json
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import torch

from steering_core.devices import SAFETENSORS_DTYPES

CHUNK_BYTES = 16 << 20  # the staging buffer of a converting read

_DTYPES = SAFETENSORS_DTYPES | {"I64": torch.int64, "I32": torch.int32, "U8": torch.uint8, "BOOL": torch.bool}


@dataclass(frozen=True)
class TensorLocation:
    """Where one tensor's bytes lie in a safetensors file."""

    path: Path
    name: str
    dtype: torch.dtype  # as stored
    shape: tuple[int, ...]
    offset: int  # absolute byte offset of element 0

    @property
    def row_bytes(self) -> int:
        """Return the bytes of one row (one element of a 1-D tensor)."""
        return math.prod(self.shape[1:]) * self.dtype.itemsize


def tensor_locations(path: str | os.PathLike) -> dict[str, TensorLocation]:
    """Return name -> location of every tensor of a safetensors file, from its header alone."""
    path = Path(path)
    with open(path, "rb") as handle:
        raw = handle.read(8)
        size = struct.unpack("<Q", raw)[0] if len(raw) == 8 else -1
        header = json.loads(handle.read(size)) if 0 < size <= path.stat().st_size - 8 else None
    if not isinstance(header, dict):
        raise ValueError(f"{path}: not a safetensors file (header size {size}); expected a .safetensors file")
    locations = {}
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        if entry.get("dtype") not in _DTYPES:
            raise ValueError(f"{path}: tensor `{name}` has dtype {entry.get('dtype')!r}, expected one of {sorted(_DTYPES)}")
        locations[name] = TensorLocation(
            path, name, _DTYPES[entry["dtype"]], tuple(entry["shape"]), 8 + size + entry["data_offsets"][0]
        )
    return locations


def staging_buffer() -> torch.Tensor:
    """Return a staging buffer for converting reads: CHUNK_BYTES of CPU memory, reusable across calls."""
    return torch.empty(CHUNK_BYTES, dtype=torch.uint8)


def read_rows_into(
    handle: BinaryIO, location: TensorLocation, start: int, out: torch.Tensor, staging: torch.Tensor | None = None
) -> torch.Tensor:
    """Read rows [start, start + len(out)) of a stored tensor into `out` and return it.

    `handle` is the file opened with `open(path, "rb", buffering=0)`; `out` is contiguous, of the
    tensor's row shape, on any device and in any dtype. Same dtype on CPU: the file is read straight
    into `out`. Otherwise chunk by chunk through `staging` (a uint8 CPU buffer from `staging_buffer`,
    one is allocated if None; pass the same one to many reads so that loading a checkpoint allocates
    it once), converted and moved by `copy_`.
    """
    rows = out.shape[0] if out.ndim else 1
    if out.device.type == "cpu" and out.dtype == location.dtype:
        _read_exact(handle, location, start, out)
        return out
    staging = staging_buffer() if staging is None else staging
    if staging.numel() < location.row_bytes:
        staging = torch.empty(location.row_bytes, dtype=torch.uint8)
    per_chunk = staging.numel() // max(location.row_bytes, 1)
    flat = out.view(rows, *location.shape[1:])
    for first in range(0, rows, per_chunk):
        count = min(per_chunk, rows - first)
        chunk = staging[: count * location.row_bytes].view(location.dtype).view(count, *location.shape[1:])
        flat[first : first + count].copy_(_read_exact(handle, location, start + first, chunk))
    return out


def read_tensor(
    handle: BinaryIO, location: TensorLocation, device: torch.device, dtype: torch.dtype,
    staging: torch.Tensor | None = None,
) -> torch.Tensor:
    """Return the whole stored tensor as a new tensor on `device` in `dtype` (`read_rows_into`)."""
    out = torch.empty(location.shape, dtype=dtype, device=device)
    return read_rows_into(handle, location, 0, out, staging)


def _read_exact(handle: BinaryIO, location: TensorLocation, start: int, out: torch.Tensor) -> torch.Tensor:
    """Fill CPU tensor `out` (stored dtype) with the bytes of rows start.. of the tensor; raise on a short file."""
    if not out.numel():
        return out
    view = out.reshape(-1).view(torch.uint8).numpy()
    handle.seek(location.offset + start * location.row_bytes)
    if handle.readinto(view) != view.size:
        raise ValueError(
            f"{location.path}: the file ends inside tensor `{location.name}` (rows from {start}); it is truncated"
        )
    return out


# safetensors lays tensors out by dtype, widest first in this order, then by name
_LAYOUT_ORDER = ("U64", "I64", "F64", "U32", "I32", "F32", "BF16", "F16", "U16", "I16", "I8", "U8", "BOOL")
_CODES = {dtype: code for code, dtype in _DTYPES.items()}


def safetensors_layout(
    entries: dict[str, tuple[torch.dtype, tuple[int, ...]]], metadata: dict[str, str] | None = None
) -> tuple[bytes, dict[str, int]]:
    """Return the header (size prefix included) of a safetensors file of these tensors, and name -> absolute
    byte offset of each tensor's data: the bytes safetensors' `save_file` writes, so a file can be written
    tensor by tensor (`os.pwrite`) without holding every tensor in memory."""
    order = sorted(entries, key=lambda name: (_LAYOUT_ORDER.index(_CODES[entries[name][0]]), name))
    header: dict[str, object] = {"__metadata__": dict(sorted(metadata.items()))} if metadata else {}
    offsets, position = {}, 0
    for name in order:
        dtype, shape = entries[name]
        size = math.prod(shape) * dtype.itemsize
        header[name] = {"dtype": _CODES[dtype], "shape": list(shape), "data_offsets": [position, position + size]}
        offsets[name], position = position, position + size
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the data starts 8-byte aligned
    start = 8 + len(text)
    return struct.pack("<Q", len(text)) + text, {name: start + offset for name, offset in offsets.items()}
