"""Compare torch.save files by their zip records, with every record's CRC-32 checked by Python's zipfile."""

from __future__ import annotations

import zipfile
from pathlib import Path

SERIALIZATION_ID = ".data/serialization_id"  # torch derives it from its own checksums: it differs when they are skipped


def torch_zip_records(path: Path) -> dict[str, bytes]:
    """Return record name (without the archive folder) -> bytes of a torch.save file, after zipfile's CRC check."""
    with zipfile.ZipFile(path) as archive:
        assert archive.testzip() is None, f"{path}: a record's CRC-32 does not match its bytes"
        return {info.filename.split("/", 1)[1]: archive.read(info) for info in archive.infolist()}


def assert_same_torch_records(ours: Path, torch_saved: Path) -> None:
    """Assert `ours` holds the records torch.save wrote to `torch_saved`, byte for byte, but the serialization id."""
    mine, theirs = torch_zip_records(ours), torch_zip_records(torch_saved)
    assert set(mine) == set(theirs)
    mine.pop(SERIALIZATION_ID), theirs.pop(SERIALIZATION_ID)
    assert mine == theirs
