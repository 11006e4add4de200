"""Every parquet read of a dataset, with pyarrow's errors naming the file: a truncated file, a CSV renamed
`.parquet` or a damaged column raise ValueError `<file>: not a readable parquet file (<pyarrow's reason>); ...`."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq


@contextlib.contextmanager
def parquet_errors(path: str | os.PathLike) -> Iterator[None]:
    """Re-raise a pyarrow error met while reading `path` (lazily too: a batch iterator) as one line naming it."""
    try:
        yield
    except pa.ArrowException as err:
        reason = " ".join(str(err).split()) or type(err).__name__
        raise ValueError(f"{path}: not a readable parquet file ({reason}); expected a parquet table as LeRobot "
                         "writes it: re-create or re-download the dataset") from None


def read_table(path: str | os.PathLike, **options: Any) -> pa.Table:
    """`pyarrow.parquet.read_table` of `path` (`options`: columns, filters), its errors naming the file."""
    with parquet_errors(path):
        return pq.read_table(path, **options)


def read_schema(path: str | os.PathLike) -> pa.Schema:
    """`pyarrow.parquet.read_schema` of `path`, its errors naming the file."""
    with parquet_errors(path):
        return pq.read_schema(path)


def read_metadata(path: str | os.PathLike) -> pq.FileMetaData:
    """`pyarrow.parquet.read_metadata` of `path`, its errors naming the file."""
    with parquet_errors(path):
        return pq.read_metadata(path)


def parquet_file(path: str | os.PathLike) -> pq.ParquetFile:
    """`pyarrow.parquet.ParquetFile` of `path`, its errors naming the file (iterate it inside `parquet_errors`)."""
    with parquet_errors(path):
        return pq.ParquetFile(path)
