"""Image cells of a LeRobot data parquet must carry their PNG bytes.

lerobot decodes an image feature with HF datasets' `Image`, which opens the file a cell's `path` names when its
`bytes` are empty: a dataset could make a run read any file on the machine. lerobot itself always embeds the bytes
(`finalize`), so a cell without them is refused before any frame is read. Reads parquet statistics (the null count
of `<key>.bytes` per row group) where the writer kept them, else that column alone.

The first cell of each data file and camera must also be a PNG of the size info.json declares, in RGB: its
header (the first 26 bytes) is read, never the pixels, so a corrupt, grayscale, tiny or huge image is refused
before a run starts (`check_png_headers`); later frames' headers are checked before they are decoded (capture.frames).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path

import pyarrow.compute as pc

from steering_core.data.dataset import INFO_FILE, DatasetMeta
from steering_core.data.parquet_reads import parquet_errors, parquet_file, read_table


def check_image_cells(meta: DatasetMeta, episodes: Sequence[int]) -> None:
    """Raise one ValueError naming the data file and feature whose image cells hold no bytes (for `episodes`)."""
    keys = [key for key, feature in meta.info["features"].items() if feature.get("dtype") == "image"]
    if not keys:
        return
    for path in sorted({meta.root / meta.episode(int(e)).data_file for e in episodes}):
        for key in keys:
            missing = _cells_without_bytes(path, key)
            if missing:
                cells = read_table(path, columns=[key]).column(0).combine_chunks()
                empty = cells.filter(pc.is_null(cells.field("bytes"))).field("path").drop_null()
                named = f", e.g. path {empty[0].as_py()!r}" if len(empty) else ""
                raise ValueError(f"{path}: {missing} cell(s) of image feature {key!r} hold no PNG bytes{named}; "
                                 "a LeRobot dataset embeds its images (lerobot's finalize() does), and files a "
                                 "dataset names are never opened: re-create the dataset")


def _cells_without_bytes(path: Path, key: str) -> int:
    """Return how many cells of image feature `key` in one data file have null bytes."""
    metadata = parquet_file(path).metadata
    leaf = f"{key}.bytes"
    columns = [i for i in range(metadata.num_columns) if metadata.schema.column(i).path == leaf]
    if not columns:
        raise ValueError(f"{path}: image feature {key!r} has no `bytes` field; expected struct<bytes, path> cells")
    counts = []
    for group in range(metadata.num_row_groups):
        stats = metadata.row_group(group).column(columns[0]).statistics
        if stats is None or not stats.has_null_count:
            return int(pc.sum(pc.is_null(read_table(path, columns=[leaf]).column(0))).as_py() or 0)
        counts.append(stats.null_count)
    return int(sum(counts))


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PNG_HEADER_BYTES = 26  # the signature, then the IHDR chunk's length, type, width, height, depth and colour type
_PNG_RGB = 2  # IHDR colour type of 8-bit RGB, what lerobot writes for an (H, W, 3) image feature


def check_png_headers(meta: DatasetMeta, episodes: Sequence[int]) -> None:
    """Raise a ValueError naming the data file and feature whose first image is no RGB PNG of the declared shape."""
    features = {key: f for key, f in meta.info["features"].items() if f.get("dtype") == "image"}
    for path in sorted({meta.root / meta.episode(int(e)).data_file for e in episodes}):
        if not features:
            return
        with parquet_errors(path):
            batch = next(parquet_file(path).iter_batches(batch_size=1, columns=list(features)))
        for key, feature in features.items():
            problem = png_problem(batch.column(key)[0]["bytes"].as_py() or b"", tuple(feature.get("shape") or ()))
            if problem:
                raise ValueError(f"{path}: the first image of feature {key!r} {problem} (`features.{key}.shape` "
                                 f"in {meta.root / INFO_FILE}); re-create the dataset")


def png_problem(data: bytes, shape: tuple[int, ...]) -> str | None:
    """Return what keeps PNG bytes from being an 8-bit RGB image of `shape` (H, W, 3), read from its header."""
    if len(data) < PNG_HEADER_BYTES or not data.startswith(PNG_SIGNATURE) or data[12:16] != b"IHDR":
        return "is not a PNG, expected one"
    width, height, depth, colour = struct.unpack(">IIBB", data[16:PNG_HEADER_BYTES])
    if (height, width, 3) != tuple(shape) or depth != 8 or colour != _PNG_RGB:
        return (f"is a {height}x{width} PNG of colour type {colour}, depth {depth}; expected shape {list(shape)}, "
                f"8-bit RGB (colour type {_PNG_RGB})")
    return None
