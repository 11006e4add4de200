"""Cache records: where a finished task run's record lives, and the checks it passes before Prefect reads it.

Records live under `<output_root>/.prefect-cache/`, beside the outputs they describe (a file there, or an object
when the root mirrors a bucket). The output root may be shared, so a record is checked as plain JSON first
(`read_cache_record`): one naming pickle or any other serializer is refused. A record whose summary lists an
output that is gone is dropped before lookup (`drop_if_outputs_missing`), so the task runs again.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path
from typing import Any

from steering_core.remote import filesystems, publish
from steering_core.storage import mirrors

logger = logging.getLogger(__name__)

CACHE_DIR = ".prefect-cache"  # under the output root: one record per finished task run
OUTPUTS = "outputs"           # key of a task summary that lists the files the task wrote


def cache_store(output_root: str | os.PathLike) -> Path:
    """Return the folder holding task results and cache records for runs writing under `output_root`."""
    return Path(output_root).resolve() / CACHE_DIR


def drop_if_outputs_missing(store: Path, key: str) -> None:
    """Delete a cache record that is not plain JSON of our schema, or whose summary lists a vanished output.

    Runs before Prefect looks the key up, so Prefect only ever reads records checked here. On a bucket root the
    record is an object beside the outputs, and an output counts as there when it is published.
    """
    location = record_location(store, key)
    data = read_record_bytes(location)
    if data is None:
        return
    try:
        result = parse_cache_record(location, data)
    except ValueError as err:  # tampered or damaged: never handed to Prefect's deserializers; recompute instead
        logger.warning("refused cache record: %s; the task will run again", err)
        delete_record(location)
        return
    outputs = result.get(OUTPUTS, []) if isinstance(result, dict) else []
    missing = [p for p in outputs if not (publish.is_published(p) if mirrors.is_url(p) else Path(p).exists())]
    if missing:
        logger.info("%s: cached outputs are gone (%s); the task will run again", key, ", ".join(missing[:3]))
        delete_record(location)


def record_location(store: Path, key: str) -> Path | str:
    """Return where the cache record `key` lives: a file of `store`, or its object when `store` mirrors a bucket."""
    url = mirrors.url_of(store)
    return store / key if url is None else f"{url}/{key}"


def read_record_bytes(location: Path | str) -> bytes | None:
    """Return the bytes of a cache record (a file, or an object URL), or None when there is none."""
    if not mirrors.is_url(location):
        return Path(location).read_bytes() if Path(location).is_file() else None
    fs, path = filesystems.object_path(location)
    try:
        return fs.cat_file(path)
    except FileNotFoundError:
        return None


def delete_record(location: Path | str) -> None:
    """Delete the cache record at `location` (a file, or an object URL); nothing when it is gone already."""
    if isinstance(location, Path):
        location.unlink(missing_ok=True)
        return
    fs, path = filesystems.object_path(location)
    with contextlib.suppress(FileNotFoundError):
        fs.rm_file(path)
    fs.invalidate_cache()


# The only serializer a record may name: Prefect's JSON serializer exactly as `RESULTS` writes it. Any
# other (pickle, or JSON with another library, encoder or decoder) would import and run named code.
_JSON_SERIALIZER = {
    "type": "json", "jsonlib": "json", "object_encoder": "prefect.serializers.prefect_json_object_encoder",
    "object_decoder": "prefect.serializers.prefect_json_object_decoder", "dumps_kwargs": {}, "loads_kwargs": {},
}
_METADATA_KEYS = {"storage_key", "expiration", "serializer", "prefect_version", "storage_block_id"}
_CODE_KEYS = ("__class__", "__exc_type__")  # Prefect's JSON decoder imports what these name


def read_cache_record(path: str | os.PathLike) -> Any:
    """Return the task summary held by a cache record, read with the standard `json` module only.

    The record must be `{"metadata": {...}, "result": "<JSON text>"}` with the JSON serializer above, no
    storage block, `storage_key` naming the record itself, and a summary of plain JSON values (no key
    that Prefect's decoder would turn into an import). ValueError naming the file otherwise.
    """
    return parse_cache_record(Path(path), Path(path).read_bytes())


def parse_cache_record(path: Path | str, data: bytes) -> Any:
    """Return the task summary of the cache record `data` stored at `path` (a file or an object URL); see
    `read_cache_record`."""

    def refuse(why: str) -> ValueError:
        return ValueError(f"{path}: {why}; expected a JSON task summary written by this project")

    try:
        record = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise refuse("not JSON") from None
    if not isinstance(record, dict) or set(record) != {"metadata", "result"} or not isinstance(record["metadata"], dict):
        raise refuse("not a result record")
    metadata = record["metadata"]
    if set(metadata) - _METADATA_KEYS:
        raise refuse(f"unknown metadata {sorted(set(metadata) - _METADATA_KEYS)}")
    serializer = metadata.get("serializer")
    if serializer != _JSON_SERIALIZER:
        kind = serializer.get("type") if isinstance(serializer, dict) else serializer
        raise refuse(f"serializer {kind!r} with settings {serializer!r} (only Prefect's plain JSON serializer)")
    on_bucket = mirrors.is_url(path)  # kept through our saved block, which names records by key alone
    names = {str(path), str(path).rsplit("/", 1)[-1]} if on_bucket else {str(path)}
    if (metadata.get("storage_block_id") is not None and not on_bucket) or metadata.get("storage_key") not in names:
        raise refuse(f"storage {metadata.get('storage_block_id')!r}, {metadata.get('storage_key')!r} is not this file")
    if not isinstance(record["result"], str):
        raise refuse("result is not JSON text")
    try:
        summary = json.loads(record["result"])
    except json.JSONDecodeError:
        raise refuse("result is not valid JSON") from None
    if found := _code_keys(summary):
        raise refuse(f"result holds {found!r}, which Prefect's decoder would import")
    return summary


def _code_keys(value: Any) -> str | None:
    """Return the first key of `value` (nested) that Prefect's JSON decoder treats as code, or None."""
    if isinstance(value, dict):
        for key, item in value.items():
            if key in _CODE_KEYS:
                return key
            if found := _code_keys(item):
                return found
    elif isinstance(value, list):
        for item in value:
            if found := _code_keys(item):
                return found
    return None
