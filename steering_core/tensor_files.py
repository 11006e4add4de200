"""Reading tensor files safely: a file that is not what its name says gives one error naming it.

safetensors trusts the first 8 bytes as the header length: a text file or a pickle renamed
`.safetensors` then fails deep inside the reader (or asks for gigabytes of memory). `check_safetensors`
checks the framing first; `load_torch_file` refuses pickled objects other than tensors with a message
that does not advise `weights_only=False`.
"""

from __future__ import annotations

import json
import os
import pickle
import re
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save

_LENGTH_BYTES = 8  # safetensors: u64 little-endian header length, then the JSON header, then the data
_MAX_HEADER = 100 << 20  # the reference reader's own limit (100 MB)
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
    `data_offsets` lie inside the data section.
    """
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as handle:
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
    return header


def load_safetensors(path: str | os.PathLike, device: str = "cpu") -> dict[str, torch.Tensor]:
    """Return every tensor of a safetensors file, after `check_safetensors`."""
    check_safetensors(path)
    return load_file(path, device=device)


def load_torch_file(path: str | os.PathLike) -> Any:
    """Return the content of a `torch.save` file holding only tensors and plain containers (weights_only).

    Pickled objects of other classes are refused with a ValueError naming the file: they would run code.
    """
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
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
