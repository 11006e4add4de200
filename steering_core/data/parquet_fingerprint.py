"""Content fingerprints for the `datasets` metadata in parquet footers, so that a conversion is byte-deterministic.

lerobot 0.4 writes each v3.0 data file with the schema of a `datasets.Dataset` built from the episode's
frames (`Dataset.from_dict` on the PNG file paths it staged under `<root>/images/`, then `embed_images`).
That schema carries `{"huggingface": {"info": ..., "fingerprint": <16 hex>}}`, and the fingerprint is a hash
of the dataset state, which includes those absolute image paths (docs/PI05_SPEC.md §11.1): it changes with
the staging folder (host, pid, random suffix) and the output path, although the rows are the same.

The fingerprint is replaced here by one of the file's content (the sha256 of every byte before the footer,
cut to the same length), in place: a string of the same length keeps every thrift length and offset of the
footer valid, so only the footer is rewritten, never the (possibly 100 MB) row data.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import os
import re
from pathlib import Path

from steering_core.data.parquet_reads import read_metadata

logger = logging.getLogger(__name__)

_MAGIC = b"PAR1"
_TAIL = 8  # footer length (4 bytes, little endian) + magic
_HF_KEY, _SCHEMA_KEY = b"huggingface", b"ARROW:schema"
_FINGERPRINT = re.compile(r"[0-9a-f]{1,64}")
_CHUNK = 1 << 20


def content_fingerprint(path: str | os.PathLike) -> str | None:
    """Give the parquet file at `path` a fingerprint of its own content; return it (None: the file has none).

    Rewrites the footer in place, so call it on a staged file. ValueError naming the file if the footer is not
    laid out as pyarrow writes it (the fingerprint must appear once in the JSON and once in the Arrow schema).
    """
    path = Path(path)
    metadata = read_metadata(path).metadata or {}
    if _HF_KEY not in metadata:
        return None
    old = json.loads(metadata[_HF_KEY]).get("fingerprint")
    if old is None:
        return None
    if not isinstance(old, str) or not _FINGERPRINT.fullmatch(old):
        raise ValueError(f"{path}: `datasets` fingerprint {old!r} in the parquet footer; expected 1-64 hex digits")
    with open(path, "r+b") as handle:
        size = handle.seek(0, os.SEEK_END)
        handle.seek(size - _TAIL)
        tail = handle.read(_TAIL)
        footer_start = size - _TAIL - int.from_bytes(tail[:4], "little")
        if tail[4:] != _MAGIC or footer_start < len(_MAGIC):
            raise ValueError(f"{path}: not a parquet file (no footer); expected one written by pyarrow")
        new = _hash_prefix(handle, footer_start)[: len(old)]
        handle.seek(footer_start)
        footer = handle.read(size - _TAIL - footer_start)
        replaced = _replace_once(path, footer, metadata[_HF_KEY], _swap(path, metadata[_HF_KEY], old, new))
        if _SCHEMA_KEY in metadata:
            schema = metadata[_SCHEMA_KEY]
            swapped = base64.b64encode(_swap(path, base64.b64decode(schema), old, new))
            replaced = _replace_once(path, replaced, schema, swapped)
        handle.seek(footer_start)
        handle.write(replaced)
    found = json.loads(read_metadata(path).metadata[_HF_KEY]).get("fingerprint")
    if found != new:  # a footer we misread would show here, not in a later reader
        raise ValueError(f"{path}: fingerprint reads {found!r} after rewriting the footer; expected {new!r}")
    logger.debug("%s: fingerprint %s -> %s", path, old, new)
    return new


def _hash_prefix(handle, end: int) -> str:
    """Return the hex sha256 of the first `end` bytes of an open file."""
    digest = hashlib.sha256()
    handle.seek(0)
    left = end
    while left > 0:
        chunk = handle.read(min(_CHUNK, left))
        if not chunk:
            raise ValueError(f"{handle.name}: file ends before its parquet footer")
        digest.update(chunk)
        left -= len(chunk)
    return digest.hexdigest()


def _swap(path: Path, blob: bytes, old: str, new: str) -> bytes:
    """Return `blob` with its one occurrence of `old` replaced by `new` (same length)."""
    if blob.count(old.encode()) != 1:
        raise ValueError(f"{path}: fingerprint {old} appears {blob.count(old.encode())} times in a footer entry; "
                         "expected once")
    return blob.replace(old.encode(), new.encode())


def _replace_once(path: Path, footer: bytes, old: bytes, new: bytes) -> bytes:
    """Return `footer` with the one occurrence of `old` replaced by the equally long `new`."""
    if len(old) != len(new) or footer.count(old) != 1:
        raise ValueError(f"{path}: a footer entry appears {footer.count(old)} times in the raw footer; expected once")
    return footer.replace(old, new)
