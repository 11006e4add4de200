"""openpi-client's wire format: msgpack with numpy arrays and scalars as tagged maps (spec "Serving protocol").

An ndarray travels as `{b"__ndarray__": True, b"data": C-order bytes, b"dtype": dtype.str, b"shape": [...]}`
and a numpy scalar as `{b"__npgeneric__": True, b"data": item(), b"dtype": dtype.str}`, with msgpack >= 1.0
defaults (bin type for bytes, str keys decoded to str, map keys limited to str/bytes). Object, void and complex
dtypes are refused both ways. Decoding walks the message itself, rather than through an object hook, so a
malformed array names its key (`observation/image: ...`), and refuses nesting deeper than MAX_DEPTH and a map
that holds one key twice (msgpack would keep the last value silently).
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

NDARRAY_TAG = b"__ndarray__"
NPGENERIC_TAG = b"__npgeneric__"
REFUSED_KINDS = "VOc"  # structured/void, object, complex: openpi's pack_array refuses them too
# maps and lists inside one another: an observation with a steering list of entries is 3 deep, a tagged array
# one more; anything far deeper is an attack on the decoder's recursion (msgpack itself allows 1024)
MAX_DEPTH = 32


class WireError(ValueError):
    """A message that is not a valid openpi-client message; `key` names where (None: the whole message)."""

    def __init__(self, key: str | None, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


def pack(obj: Any) -> bytes:
    """Return the msgpack bytes of `obj` exactly as `openpi_client.msgpack_numpy.packb` writes them."""
    return msgpack.packb(obj, default=_encode_numpy)


def unpack(data: bytes) -> Any:
    """Return the object in `data`, numpy maps turned into arrays (read-only views) and scalars.

    Raises WireError for bytes that are not one msgpack object or hold a malformed array.
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise WireError(None, f"expected a binary msgpack message, got {type(data).__name__}")
    try:
        obj = msgpack.unpackb(data, object_pairs_hook=_Pairs)
    except (ValueError, msgpack.UnpackException) as err:
        raise WireError(None, f"message is not msgpack ({type(err).__name__}: {err})") from None
    return _decode(obj, None, 0)


def _encode_numpy(obj: Any) -> dict[bytes, Any]:
    if isinstance(obj, np.ndarray | np.generic):
        if obj.dtype.kind in REFUSED_KINDS:
            raise ValueError(f"Unsupported dtype: {obj.dtype}")
        if isinstance(obj, np.ndarray):
            return {NDARRAY_TAG: True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
        return {NPGENERIC_TAG: True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot serialize {type(obj).__name__} object")


class _Pairs(list):
    """A msgpack map as its (key, value) pairs in order, so that a key given twice is seen."""


def _unique(pairs: _Pairs, key: str | None) -> dict:
    """Return the map of `pairs`; WireError naming the first key it holds twice."""
    found: dict = {}
    for name, value in pairs:
        if name in found:
            raise WireError(_child(key, name), "this key appears twice in one map; send each key once")
        found[name] = value
    return found


def _decode(obj: Any, key: str | None, depth: int) -> Any:
    if isinstance(obj, list) and depth >= MAX_DEPTH:  # a map too: _Pairs
        raise WireError(key, f"nested deeper than {MAX_DEPTH} maps and lists; an observation is at most a few deep")
    if isinstance(obj, _Pairs):
        obj = _unique(obj, key)
        if NDARRAY_TAG in obj:
            return _decode_array(obj, key)
        if NPGENERIC_TAG in obj:
            return _decode_scalar(obj, key)
        return {k: _decode(v, _child(key, k), depth + 1) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_decode(v, f"{key or ''}[{i}]", depth + 1) for i, v in enumerate(obj)]
    return obj


def _child(key: str | None, name: Any) -> str:
    name = name.decode(errors="replace") if isinstance(name, bytes) else str(name)
    return f"{key}.{name}" if key else name


def _dtype(obj: dict, key: str | None) -> np.dtype:
    spec = obj.get(b"dtype")
    try:
        dtype = np.dtype(spec) if isinstance(spec, str) else None
    except (TypeError, ValueError, SyntaxError):
        dtype = None
    if dtype is None:
        raise WireError(key, f"array dtype {spec!r:.60} is not a numpy dtype string like '<f4' or '|u1'")
    if dtype.kind in REFUSED_KINDS:
        raise WireError(key, f"array dtype {dtype} is not supported (object, void and complex dtypes are refused)")
    return dtype


def _decode_array(obj: dict, key: str | None) -> np.ndarray:
    dtype, data, shape = _dtype(obj, key), obj.get(b"data"), obj.get(b"shape")
    if not isinstance(data, bytes):
        raise WireError(key, f"array data must be bytes, got {type(data).__name__}")
    if not isinstance(shape, list) or not all(isinstance(n, int) and n >= 0 for n in shape):
        raise WireError(key, f"array shape must be a list of non-negative integers, got {shape!r}")
    if len(data) != math.prod(shape) * dtype.itemsize:
        raise WireError(key, f"array of shape {tuple(shape)} and dtype {dtype} needs "
                             f"{math.prod(shape) * dtype.itemsize} bytes, got {len(data)}")
    try:
        return np.ndarray(buffer=data, dtype=dtype, shape=tuple(shape))
    except ValueError as err:  # numpy's own limits: more than 64 dimensions, a zero-size dtype
        raise WireError(key, f"array of shape {tuple(shape)} and dtype {dtype}: {err}") from None


def _decode_scalar(obj: dict, key: str | None) -> np.generic:
    dtype = _dtype(obj, key)
    data = obj.get(b"data")
    try:
        value = dtype.type(data)
    except (TypeError, ValueError, OverflowError) as err:
        raise WireError(key, f"numpy scalar of dtype {dtype}: {err}") from None
    if not isinstance(value, np.generic):
        raise WireError(key, f"numpy scalar of dtype {dtype}: data must be one value, got {type(data).__name__}")
    return value
