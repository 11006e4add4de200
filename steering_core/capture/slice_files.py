"""One concept's slice files, streamed: rows go to their final place in the file as they are read.

The `.safetensors` copy is laid out first (header and row columns, `safetensors_layout`, the bytes
`save_file` would write), then each residual row is written at its offset with `os.pwrite` as the
shards are read, so no concept is ever held whole in memory. The `.pt` copy is then saved from a
memory map of that finished file, reading the bytes from the page cache, and its CRC-32s filled in
(`tensor_files.fill_zip_crcs`), the large record's as the rows were written (or from the same map).
"""

from __future__ import annotations

import mmap
import os
from pathlib import Path

import numpy as np
import torch

from steering_core.capture.shards import RESIDUALS
from steering_core.storage.fileio import crc32
from steering_core.tensor_files import fill_zip_crcs, safetensors_layout, save_torch_without_crcs

_PT_DATA_RECORD = "data/0"  # torch.save's record of a lone tensor's storage (spec 14); used only if its size matches


class SliceFile:
    """A concept's `.safetensors` slice being filled: (rows, width) float32 `residuals` + int64 row columns."""

    def __init__(self, path: Path, columns: dict[str, np.ndarray], width: int) -> None:
        self.path, self.rows, self.width = path, len(columns["index"]), width
        self.frames = int(np.unique(columns["index"]).size)  # dataset frames the rows come from
        entries = {RESIDUALS: (torch.float32, (self.rows, width))}
        entries |= {name: (torch.int64, (self.rows,)) for name in columns}
        header, self._offsets = safetensors_layout(entries)
        self._crc, self._crc_rows = 0, 0  # CRC-32 of output rows 0 .. _crc_rows - 1, kept while rows come in order
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        os.ftruncate(self._fd, self._offsets[RESIDUALS] + self.rows * width * 4)  # residuals come last (F32)
        _pwrite(self._fd, memoryview(header), 0)
        for name, values in columns.items():
            _pwrite(self._fd, memoryview(np.ascontiguousarray(values, dtype="<i8")).cast("B"), self._offsets[name])

    def write(self, first: int, rows: torch.Tensor) -> None:
        """Write (n, width) contiguous float32 CPU `rows` as output rows first .. first + n - 1."""
        data = memoryview(rows.numpy()).cast("B")
        _pwrite(self._fd, data, self._offsets[RESIDUALS] + first * self.width * 4)
        if first == self._crc_rows:  # in output order, as a slice's rows usually come: the .pt's checksum grows with them
            self._crc, self._crc_rows = crc32(data, self._crc), first + len(rows)

    def close(self) -> None:
        """Close the file (once every row is written)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def save_pt(self, path: Path) -> Path:
        """Write the residuals of the closed file as a torch.save `.pt` (the seed's copy), CRC-32s included,
        read from a memory map of the file."""
        populate = getattr(mmap, "MAP_POPULATE", 0)  # Linux: map every page in one call, not a fault per 64 KiB
        with open(self.path, "r+b") as handle:  # shared (no page copied) and writable (torch wants that); only read
            mapped = mmap.mmap(handle.fileno(), 0, flags=mmap.MAP_SHARED | populate,
                               prot=mmap.PROT_READ | mmap.PROT_WRITE)
        start, size = self._offsets[RESIDUALS], self.rows * self.width * 4
        data_crc = self._crc
        if self._crc_rows != self.rows:  # rows came out of order: checksum them where they now lie
            with memoryview(mapped) as data:
                data_crc = crc32(data[start : start + size])
        residuals = torch.frombuffer(mapped, dtype=torch.float32, offset=start, count=self.rows * self.width)
        save_torch_without_crcs(residuals.view(self.rows, self.width), path)  # the map closes with its last reference
        fill_zip_crcs(path, {_PT_DATA_RECORD: (size, data_crc)})
        return path


def _pwrite(fd: int, data: memoryview, offset: int) -> None:
    """Write all of `data` at `offset` (pwrite may write less than asked)."""
    while data:
        written = os.pwrite(fd, data, offset)
        data, offset = data[written:], offset + written
