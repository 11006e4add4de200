"""Reading tensor files safely: a file that is not what its name says gives one error naming it.

safetensors trusts the first 8 bytes as the header length: a text file or a pickle renamed
`.safetensors` then fails deep inside the reader (or asks for gigabytes of memory). `check_safetensors`
checks the framing first (each tensor's shape must fill its data_offsets exactly); `load_torch_file`
refuses pickled objects other than tensors with a message that does not advise `weights_only=False`.
`require_finite` is the one NaN/Inf check every step calls at its boundaries (one reduction per tensor),
`require_finite_file` applies it to a safetensors file chunk by chunk. `tensor_locations` / `read_rows_into` read tensors with plain
file reads straight into caller-owned memory, from a local file or, through `open_read`, by ranged reads of the object
a mounted URL root publishes for it, `safetensors_layout` lets a file be written tensor by
tensor, and `save_torch` writes torch.save files with a fast CRC-32 in place of torch's slower one.
"""

from __future__ import annotations

import contextlib
import json
import math
import mmap
import os
import pickle
import re
import struct
import threading
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch
from safetensors.torch import load_file, save

from steering_core.devices import SAFETENSORS_DTYPES
from steering_core.remote.reads import RemoteFile, remote_file
from steering_core.storage.fileio import crc32
from steering_core.storage.finite import non_finite

# float32's smallest normal number: a length or weight below it is 0 or subnormal, rounding noise rather than a value
MIN_NORMAL = float(torch.finfo(torch.float32).tiny)
_LENGTH_BYTES = 8  # safetensors: u64 little-endian header length, then the JSON header, then the data
_MAX_HEADER = 100 << 20  # the reference reader's own limit (100 MB)
# bytes per element of every safetensors dtype code
_ITEM_BYTES = {"BOOL": 1, "U8": 1, "I8": 1, "F8_E5M2": 1, "F8_E4M3": 1, "I16": 2, "U16": 2, "F16": 2, "BF16": 2,
               "I32": 4, "U32": 4, "F32": 4, "I64": 8, "U64": 8, "F64": 8}
SAFETENSORS_EXPECTED = "expected a safetensors file (8-byte header length, JSON header, tensor data)"


def _looks_like(head: bytes) -> str:
    """Return what a file's first bytes suggest it is, for the error message."""
    if head[:1] == b"\x80":
        return "; it looks like a pickle (torch.save of an old format)"
    if head[:2] == b"PK":
        return "; it looks like a zip archive (a torch.save .pt file)"
    if head and all(32 <= b < 127 or b in b"\t\r\n" for b in head):
        return "; it looks like text"
    return ""


def check_safetensors(path: str | os.PathLike) -> dict[str, Any]:
    """Return the JSON header of a safetensors file after checking its framing; ValueError naming the file otherwise.

    Checked: the header length fits the file, the header is a JSON object, and every tensor's
    `data_offsets` lie inside the data section and hold exactly its shape and dtype.
    """
    path = Path(path)
    with open_read(path) as (handle, size):
        return _checked_header(path, handle, size)[0]


def readable(path: str | os.PathLike) -> Path | RemoteFile:
    """Return what `open_read` reads for `path`: the published object standing for it when it is absent here
    under a mounted URL root (`publish.remote_file`: its size and ETag checked against its publication record
    now, the identity check of a file never downloaded whole), else the local path."""
    return remote_file(path) or Path(path)


@contextlib.contextmanager
def open_read(source: str | os.PathLike | RemoteFile, missing: str | None = None) -> Iterator[tuple[BinaryIO, int]]:
    """Yield (unbuffered binary handle, size) of a file to read with seek / read / readinto.

    `source` is a path (resolved by `readable`) or what `readable` returned for one, to open it again without
    checking it again. A published object is read by ranges: one ranged GET per read, never the whole object.
    `missing`: the text of the FileNotFoundError naming a local file that is not there.
    """
    remote = source if isinstance(source, RemoteFile) else readable(source)
    if isinstance(remote, RemoteFile):
        with remote.open() as handle:
            yield handle, remote.size
        return
    try:
        handle = open(remote, "rb", buffering=0)
    except (FileNotFoundError, IsADirectoryError):
        if missing is None:
            raise
        raise FileNotFoundError(f"{remote}: {missing}") from None
    with handle:
        yield handle, os.fstat(handle.fileno()).st_size


def _checked_header(path: Path, handle: BinaryIO, size: int) -> tuple[dict[str, Any], int]:
    """Return (`check_safetensors` header, byte offset where the data section starts) of the file open in `handle`."""
    handle.seek(0)
    head = handle.read(_LENGTH_BYTES)
    length = int.from_bytes(head, "little") if len(head) == _LENGTH_BYTES else -1
    if not 2 <= length <= min(size - _LENGTH_BYTES, _MAX_HEADER):
        found = f"{size} bytes" if length < 0 else f"a header length of {length} in a {size}-byte file"
        raise ValueError(f"{path}: not a safetensors file ({found}{_looks_like(head)}); {SAFETENSORS_EXPECTED}")
    raw = handle.read(length)
    try:
        header = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ValueError(f"{path}: not a safetensors file (its header is not JSON); {SAFETENSORS_EXPECTED}") from None
    data = size - _LENGTH_BYTES - length
    if not isinstance(header, dict):
        raise ValueError(f"{path}: not a safetensors file (its header is not a JSON object); {SAFETENSORS_EXPECTED}")
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        offsets = entry.get("data_offsets") if isinstance(entry, dict) else None
        if not (isinstance(offsets, list) and len(offsets) == 2 and all(isinstance(o, int) for o in offsets)
                and 0 <= offsets[0] <= offsets[1] <= data):
            raise ValueError(f"{path}: tensor {name!r} has data_offsets {offsets!r} outside the {data}-byte data "
                             "section; the file is truncated or damaged, re-download or re-write it")
        _check_extent(path, name, entry)
    return header, _LENGTH_BYTES + length


def _check_extent(path: Path, name: str, entry: dict[str, Any]) -> None:
    """Raise naming the file and tensor unless its dtype is known and its shape fills its data_offsets exactly."""
    if entry.get("dtype") not in _ITEM_BYTES:
        raise ValueError(f"{path}: tensor `{name}` has dtype {entry.get('dtype')!r}, expected one of "
                         f"{sorted(_ITEM_BYTES)}")
    shape, (first, last) = entry.get("shape"), entry["data_offsets"]
    if not (isinstance(shape, list) and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
            and math.prod(shape) * _ITEM_BYTES[entry["dtype"]] == last - first):
        raise ValueError(f"{path}: tensor `{name}` has shape {shape!r} {entry['dtype']}, which disagrees with its "
                         f"data_offsets ({last - first} bytes); the file is damaged, re-download or re-write it")


def require_finite(
    values: torch.Tensor | np.ndarray, where: str | os.PathLike, name: str, fix: str = "", first_row: int = 0
) -> None:
    """Raise a ValueError naming `where` (the file) and tensor `name` if `values` holds NaN or Inf.

    `first_row`: the row number of `values[0]` in the whole tensor, when `values` is a chunk of it;
    `fix` says what to do about it.
    """
    problem = non_finite(values, name, first_row)
    if problem is not None:
        raise ValueError(f"{where}: {problem}" + (f"; {fix}" if fix else ""))


def load_safetensors(path: str | os.PathLike, device: str = "cpu") -> dict[str, torch.Tensor]:
    """Return every tensor of a safetensors file, after `check_safetensors`."""
    check_safetensors(path)
    return load_file(path, device=device)


def load_torch_file(path: str | os.PathLike, *, mmap: bool = False) -> Any:
    """Return the content of a `torch.save` file holding only tensors and plain containers (weights_only).

    Pickled objects of other classes are refused with a ValueError naming the file: they would run code.
    `mmap`: tensors stay in the file, read on use (a large slice is not loaded whole).
    """
    try:
        return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as err:
        # torch's message goes on to advise weights_only=False, i.e. running the file's code: keep only its reason
        found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", str(err))
        reason = f"it names {found.group(1)}" if found else "not plain tensors"
        raise ValueError(f"{path}: holds pickled objects other than tensors, which are never unpickled here "
                         f"({reason}); expected tensors saved with torch.save or safetensors") from None
    except Exception as err:  # noqa: BLE001  torch's reader fails in many ways on a file that is no torch.save
        reason = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ValueError(f"{path}: not a readable torch.save file ({reason[:200]}); "
                         "expected tensors saved with torch.save or safetensors") from None


def save_safetensors(tensors: dict[str, torch.Tensor], path: str | os.PathLike, metadata: dict[str, str] | None = None) -> Path:
    """Write a safetensors file whose header keys (and metadata keys) are sorted: equal inputs, equal bytes.

    safetensors keeps metadata in a hash map, so its key order (and the file's bytes) changes between
    processes; the header is re-serialised here, the data section is written as the library laid it out.
    """
    data = save(tensors, metadata=metadata)
    length = int.from_bytes(data[:_LENGTH_BYTES], "little")
    header = json.loads(data[_LENGTH_BYTES:_LENGTH_BYTES + length])
    if "__metadata__" in header:
        header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
    text = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the format pads the header to 8 bytes with spaces
    path = Path(path)
    path.write_bytes(len(text).to_bytes(_LENGTH_BYTES, "little") + text + data[_LENGTH_BYTES + length:])
    return path


# ----------------------------------------------------------------------------- plain reads and streamed writes
# safetensors' `safe_open` reads through a memory map: the file pages it touches stay mapped, and count in
# the process's resident memory, for as long as the file is open. Reading with plain file reads instead puts
# each byte once into its destination (or into one bounded staging buffer when the dtype or device differs),
# so loading a checkpoint costs the converted tensors and nothing more, and slicing a shard copies each
# selected row once. The data are little-endian, as torch stores tensors on x86 and ARM.

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
    """Return name -> location of every tensor of a safetensors file, from its header (`check_safetensors`)."""
    return read_layout(path)[1]


def read_layout(path: str | os.PathLike) -> tuple[dict[str, Any], dict[str, TensorLocation]]:
    """Return a safetensors file's checked header and name -> location of each tensor (`open_read`, `layout_of`)."""
    path = Path(path)
    with open_read(path) as (handle, size):
        return layout_of(path, handle, size)


def layout_of(path: Path, handle: BinaryIO, size: int) -> tuple[dict[str, Any], dict[str, TensorLocation]]:
    """Return `read_layout` of the file `path` open in `handle` (`open_read`): two reads, its length and header."""
    header, start = _checked_header(path, handle, size)
    locations = {}
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        if entry["dtype"] not in _DTYPES:
            raise ValueError(f"{path}: tensor `{name}` has dtype {entry['dtype']!r}, expected one of {sorted(_DTYPES)}")
        locations[name] = TensorLocation(path, name, _DTYPES[entry["dtype"]], tuple(entry["shape"]),
                                         start + entry["data_offsets"][0])
    return header, locations


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


def require_finite_file(path: str | os.PathLike, names: Iterable[str] | None = None, fix: str = "") -> None:
    """Raise `require_finite`'s error for the first floating-point tensor of a safetensors file (of `names`,
    default all) that holds NaN or Inf; read chunk by chunk through one staging buffer."""
    path = Path(path)
    staging = staging_buffer()
    with open_read(path) as (handle, size):
        locations = layout_of(path, handle, size)[1]
        for name in locations if names is None else names:
            location = locations[name]
            if not location.dtype.is_floating_point or not location.row_bytes:
                continue
            if staging.numel() < location.row_bytes:
                staging = torch.empty(location.row_bytes, dtype=torch.uint8)
            rows, per_chunk = (location.shape or (1,))[0], staging.numel() // location.row_bytes
            for first in range(0, rows, per_chunk):
                count = min(per_chunk, rows - first)
                chunk = staging[: count * location.row_bytes].view(location.dtype).view(count, *location.shape[1:])
                require_finite(_read_exact(handle, location, first, chunk), location.path, name, fix, first)


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


# ----------------------------------------------------------------------------- torch.save with fast checksums
# torch.save checksums every record with its own CRC-32, about a third of zlib's speed and far below ISA-L's
# (`fileio.crc32`): for a slice of residuals that costs more than writing the bytes. torch can skip the checksum
# (`set_crc32_options`, a process-wide switch; torch.load never checks it); `save_torch` skips it and then writes
# the CRC-32 of every record where the zip format keeps it (the record's data descriptor and its central directory
# entry), so zip tools accept the file.

_TORCH_SAVE = threading.Lock()  # the switch is process-wide: one save at a time turns it off and back on
_LOCAL_HEADER, _CENTRAL_HEADER, _DESCRIPTOR = b"PK\x03\x04", b"PK\x01\x02", b"PK\x07\x08"
_HAS_DESCRIPTOR = 0x08  # general purpose flag bit 3: sizes and CRC follow the data


def save_torch(obj: Any, path: str | os.PathLike) -> Path:
    """torch.save `obj` to `path` (archive name `archive`, whatever the file is called), CRC-32s by `fileio.crc32`."""
    fill_zip_crcs(save_torch_without_crcs(obj, path))
    return Path(path)


def save_torch_without_crcs(obj: Any, path: str | os.PathLike) -> Path:
    """torch.save `obj` to `path` with zero CRC-32s; `fill_zip_crcs` completes it.

    Only torch.save calls made through this module are serialised with each other: a torch.save in
    another thread during one of them writes its file without CRC-32s (torch.load still reads it).
    """
    with open(path, "wb") as handle, _TORCH_SAVE:
        previous = torch.serialization.get_crc32_options()
        torch.serialization.set_crc32_options(False)
        try:
            torch.save(obj, handle)  # to a handle: the archive is named `archive`, not after a temporary path
        finally:
            torch.serialization.set_crc32_options(previous)
    return Path(path)


def fill_zip_crcs(path: str | os.PathLike, known: dict[str, tuple[int, int]] | None = None) -> None:
    """Write each record's CRC-32 into its data descriptor (or local header) and central directory entry.

    `known`: record name inside the archive folder (e.g. `data/0`) -> (its size, its CRC-32) computed
    elsewhere from the same bytes; used when the record has that size, computed here otherwise.
    """
    path, known = Path(path), known or {}
    with zipfile.ZipFile(path) as archive:  # reads the central directory only
        records, central = archive.infolist(), archive.start_dir
    patches: list[tuple[int, int]] = []  # (byte offset, CRC-32)
    # not populated: with a known checksum only the small records' pages are ever read
    with open(path, "r+b") as handle, mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as mapped, \
            memoryview(mapped) as data:
        for record in records:
            at = record.header_offset
            if data[at : at + 4] != _LOCAL_HEADER:
                raise ValueError(f"{path}: no zip local header at byte {at}; torch.save wrote an unexpected layout")
            name_length, extra_length = struct.unpack("<HH", data[at + 26 : at + 30])
            start = at + 30 + name_length + extra_length
            end = start + record.compress_size
            size, crc = known.get(record.filename.partition("/")[2], (-1, 0))
            if size != record.compress_size:
                crc = crc32(data[start:end])  # a view of the mapped file: no copy
            if record.flag_bits & _HAS_DESCRIPTOR:
                if data[end : end + 4] != _DESCRIPTOR:
                    raise ValueError(f"{path}: record {record.filename} has no data descriptor after its data")
                patches.append((end + 4, crc))
            else:
                patches.append((at + 14, crc))
            if data[central : central + 4] != _CENTRAL_HEADER:  # central entries come in the records' order
                raise ValueError(f"{path}: no zip central directory entry at byte {central}")
            patches.append((central + 16, crc))
            central += 46 + sum(struct.unpack("<HHH", data[central + 28 : central + 34]))
        for offset, crc in patches:
            handle.seek(offset)
            handle.write(struct.pack("<I", crc))
