"""Plain reads of safetensors files (steering_core.tensor_files): safetensors' values, any dtype, chunked, or refused."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file, save_file

from steering_core import tensor_files
from steering_core.tensor_files import read_rows_into, read_tensor, safetensors_layout, tensor_locations


@pytest.fixture
def stored(tmp_path):
    generator = torch.Generator().manual_seed(0)
    tensors = {
        "matrix": torch.randn(37, 5, generator=generator).to(torch.bfloat16),
        "wide": torch.randn(4, 3, 2, generator=generator),
        "vector": torch.arange(11, dtype=torch.int64),
        "scalar": torch.tensor(2.5, dtype=torch.float16),
        "empty": torch.zeros(0, 4),
    }
    path = tmp_path / "t.safetensors"
    save_file(tensors, path, metadata={"note": "x"})
    return path


def test_whole_tensors_equal_safetensors_load_in_any_dtype(stored):
    expected = load_file(stored)
    locations = tensor_locations(stored)
    assert set(locations) == set(expected)
    with open(stored, "rb", buffering=0) as handle:
        for name, tensor in expected.items():
            assert locations[name].shape == tuple(tensor.shape) and locations[name].dtype == tensor.dtype
            same = read_tensor(handle, locations[name], torch.device("cpu"), tensor.dtype)
            assert same.dtype == tensor.dtype and torch.equal(same, tensor)
            if tensor.is_floating_point():
                wide = read_tensor(handle, locations[name], torch.device("cpu"), torch.float64)
                assert torch.equal(wide, tensor.double())


def test_row_ranges_and_chunked_conversion(stored, monkeypatch):
    monkeypatch.setattr(tensor_files, "CHUNK_BYTES", 3 * 5 * 2)  # three bf16 rows per staging chunk
    matrix = load_file(stored)["matrix"]
    location = tensor_locations(stored)["matrix"]
    with open(stored, "rb", buffering=0) as handle:
        out = torch.full((20, 5), -1.0)
        read_rows_into(handle, location, 9, out)
        assert torch.equal(out, matrix[9:29].float())
        raw = read_rows_into(handle, location, 30, torch.empty(7, 5, dtype=torch.bfloat16))
        assert torch.equal(raw, matrix[30:])
        staging = torch.empty(2, dtype=torch.uint8)  # smaller than a row: the read uses a row-sized one instead
        assert torch.equal(read_rows_into(handle, location, 0, torch.empty(37, 5), staging), matrix.float())


def test_truncated_and_foreign_files_are_refused(stored, tmp_path):
    location = max(tensor_locations(stored).values(), key=lambda where: where.offset)  # the last in the data
    data = stored.read_bytes()
    short = tmp_path / "short.safetensors"
    short.write_bytes(data[:-40])
    with pytest.raises(ValueError, match="short.safetensors: tensor .* outside the .* data section"):
        tensor_locations(short)
    stored.write_bytes(data[:-40])  # truncated after its header was read
    with open(stored, "rb", buffering=0) as handle, pytest.raises(ValueError, match="ends inside tensor"):
        read_tensor(handle, location, torch.device("cpu"), torch.float32)
    other = tmp_path / "notes.safetensors"
    other.write_bytes(b"\xff" * 8 + b"hello")
    with pytest.raises(ValueError, match="notes.safetensors: not a safetensors file"):
        tensor_locations(other)


def test_layout_is_the_one_save_file_writes(stored, tmp_path):
    tensors = load_file(stored) | {"b_first": torch.ones(3, dtype=torch.float64), "a_half": torch.ones(2, 2, dtype=torch.float16)}
    save_file(tensors, tmp_path / "reference.safetensors", metadata={"format": "pt"})
    header, offsets = safetensors_layout({name: (t.dtype, tuple(t.shape)) for name, t in tensors.items()},
                                         {"format": "pt"})
    path = tmp_path / "streamed.safetensors"
    with open(path, "wb") as handle:
        handle.write(header)
        for name in sorted(tensors, reverse=True):  # any order: each tensor goes to its own offset
            handle.seek(offsets[name])
            handle.write(tensors[name].contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    assert path.read_bytes() == (tmp_path / "reference.safetensors").read_bytes()
