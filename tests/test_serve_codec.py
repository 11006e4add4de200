"""The wire codec against hand-assembled msgpack bytes (openpi-client's format) and its refusals."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from steering_core.serve.codec import WireError, pack, unpack


def test_array_bytes_match_the_hand_assembled_message():
    # map of 4; bin "__ndarray__" -> true; bin "data" -> bin8 (1.0f, 2.0f LE); bin "dtype" -> str "<f4";
    # bin "shape" -> [2]  (byte layout checked against openpi_client.msgpack_numpy, spec "Serving protocol")
    expected = bytes.fromhex(
        "84" "c40b" + b"__ndarray__".hex() + "c3" "c404" + b"data".hex() + "c408" "0000803f00000040"
        "c405" + b"dtype".hex() + "a3" + b"<f4".hex() + "c405" + b"shape".hex() + "9102"
    )
    assert len(expected) == 51
    assert pack(np.array([1.0, 2.0], dtype=np.float32)) == expected


def test_scalar_travels_as_its_python_item():
    expected = bytes.fromhex(
        "83" "c40d" + b"__npgeneric__".hex() + "c3" "c404" + b"data".hex() + "cb3ff8000000000000"
        "c405" + b"dtype".hex() + "a3" + b"<f4".hex()
    )
    assert pack(np.float32(1.5)) == expected
    value = unpack(expected)
    assert type(value) is np.float32 and value == 1.5


def test_nested_round_trip_keeps_dtype_shape_and_bits():
    rng = np.random.default_rng(0)
    message = {
        "observation/image": rng.integers(0, 256, (5, 4, 3), dtype=np.uint8),
        "observation/state": rng.normal(size=8),
        "prompt": "open the drawer",
        "steering": [{"pair": "p", "layer": 3, "alpha": np.float32(0.5)}],
        "flags": np.array([True, False]),
        "strided": np.arange(12, dtype=np.int16).reshape(3, 4)[:, ::2],  # not C-contiguous
        "big_endian": np.arange(3, dtype=">f8"),
    }
    back = unpack(pack(message))
    assert back.keys() == message.keys() and back["prompt"] == message["prompt"]
    for key in ("observation/image", "observation/state", "flags", "strided", "big_endian"):
        assert back[key].dtype == message[key].dtype and back[key].shape == message[key].shape
        assert np.array_equal(back[key], message[key])
    assert not back["observation/image"].flags.writeable  # a view on the message, as openpi's unpack gives
    assert back["steering"][0]["alpha"].dtype == np.float32


@pytest.mark.parametrize("value", [np.array([1 + 2j]), np.array([object()], dtype=object), np.zeros(2, "V4"),
                                   np.complex64(1j)])
def test_refused_dtypes_are_not_packed(value):
    with pytest.raises(ValueError, match="Unsupported dtype"):
        pack({"x": value})


def _array_map(data: bytes, dtype: str, shape: list) -> dict:
    return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}


@pytest.mark.parametrize("array, problem", [
    (_array_map(b"\0" * 5, "<f4", [2]), "needs 8 bytes, got 5"),
    (_array_map(b"\0" * 8, "|O", [1]), "not supported"),
    (_array_map(b"\0" * 8, "<c8", [1]), "not supported"),
    (_array_map(b"\0" * 8, "nonsense", [2]), "not a numpy dtype"),
    (_array_map(b"\0" * 8, "<f4", [-2]), "non-negative integers"),
])
def test_malformed_arrays_name_their_key(array, problem):
    message = msgpack.packb({"observation": {"image": array}})
    with pytest.raises(WireError, match=problem) as err:
        unpack(message)
    assert err.value.key == "observation.image"


@pytest.mark.parametrize("data", [b"\xc1", b"\x92\x01", b"\x80\x80", "text"])
def test_bytes_that_are_not_one_msgpack_object(data):
    with pytest.raises(WireError, match="msgpack"):
        unpack(data)
