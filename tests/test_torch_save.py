"""save_torch: torch.save's records with zlib's CRC-32s, checked by Python's zipfile and read back by torch.load."""

from __future__ import annotations

import threading
import zipfile
import zlib

import pytest
import torch
from helpers_zip import assert_same_torch_records

from steering_core.tensor_files import fill_zip_crcs, save_torch, save_torch_without_crcs


@pytest.mark.parametrize("payload", [
    torch.randn(37, 5, generator=torch.Generator().manual_seed(0)),
    {"direction": torch.arange(6, dtype=torch.float64), "layer": 12, "label": "open the drawer", "rows": [1, 2]},
    torch.tensor([], dtype=torch.bfloat16),
], ids=["tensor", "dict", "empty-bf16"])
def test_records_equal_torch_save_and_load_back(tmp_path, payload):
    ours = save_torch(payload, tmp_path / "ours.pt")
    torch.save(payload, tmp_path / "torch.pt")
    assert_same_torch_records(ours, tmp_path / "torch.pt")  # zipfile checks every CRC-32 on the way
    loaded = torch.load(ours, weights_only=True)
    if isinstance(payload, dict):
        assert loaded.keys() == payload.keys() and torch.equal(loaded["direction"], payload["direction"])
        assert {k: v for k, v in loaded.items() if k != "direction"} == {k: v for k, v in payload.items() if k != "direction"}
    else:
        assert torch.equal(loaded, payload) and loaded.dtype == payload.dtype


def test_without_crcs_until_filled(tmp_path):
    path = save_torch_without_crcs(torch.ones(4, 4), tmp_path / "t.pt")
    with zipfile.ZipFile(path) as archive:
        assert {info.CRC for info in archive.infolist()} == {0}
    assert torch.equal(torch.load(path, weights_only=True), torch.ones(4, 4))  # torch.load does not check them
    fill_zip_crcs(path)
    with zipfile.ZipFile(path) as archive:
        assert archive.testzip() is None and 0 not in {info.CRC for info in archive.infolist()}


def test_torch_checksum_switch_is_restored(tmp_path):
    assert torch.serialization.get_crc32_options() is True
    with pytest.raises(Exception):  # noqa: B017  torch.save refuses a lambda, whatever its error type
        save_torch({"f": lambda: 0}, tmp_path / "bad.pt")
    assert torch.serialization.get_crc32_options() is True
    torch.save(torch.ones(2), tmp_path / "plain.pt")  # a later plain torch.save checksums as usual
    with zipfile.ZipFile(tmp_path / "plain.pt") as archive:
        assert archive.testzip() is None and 0 not in {info.CRC for info in archive.infolist()}


def test_concurrent_saves_each_get_their_checksums(tmp_path):
    tensors = [torch.full((64, 64), float(i)) for i in range(8)]
    threads = [threading.Thread(target=save_torch, args=(t, tmp_path / f"{i}.pt")) for i, t in enumerate(tensors)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for i, tensor in enumerate(tensors):
        torch.save(tensor, tmp_path / f"ref{i}.pt")
        assert_same_torch_records(tmp_path / f"{i}.pt", tmp_path / f"ref{i}.pt")


def test_a_known_checksum_is_used_only_for_a_record_of_its_size(tmp_path):
    tensor = torch.arange(12, dtype=torch.float32)
    data = (tensor.numel() * 4, zlib.crc32(tensor.numpy().tobytes()))
    torch.save(tensor, tmp_path / "torch.pt")
    for known in ({"data/0": data}, {"data/0": (data[0] + 4, 12345)}):  # the right size and checksum; a wrong size
        path = save_torch_without_crcs(tensor, tmp_path / "ours.pt")
        fill_zip_crcs(path, known)
        assert_same_torch_records(path, tmp_path / "torch.pt")
