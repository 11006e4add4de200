"""The residual run format: shards written atomically, read with plain or ranged reads, checked by sha256.

A run folder holds

    <run>/run.json                                   the run's spec (written before any shard)
    <run>/<token_type>/layerNN/shard-<key>.safetensors   residual rows of one episode group
    <run>/<token_type>/layerNN/shard-<key>.json          its sidecar record (rows, sha256, inputs)
    <run>/metadata.json                              spec + every shard record (`write_run_metadata`)

A shard holds `residuals` (rows, width) in the run's storage dtype and, per row, int64
`index` (global dataset index), `episode_index`, `frame_index`, `token_position` (prefix
position) and `token_id`, sorted by (index, token_position). Shards of the action token types
(`decision`, `adarms`: one row per frame and denoising step) hold an int64 `step` column too and are
sorted by (index, step); older shards without it stay readable. Shards are keyed by episode
group, so adding demos never touches existing shards; each shard has its own sidecar, so
several workers can write one run without sharing a file. `metadata.json` is rebuilt from
`run.json` and the sidecars whenever a worker finishes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from safetensors.torch import save_file

from steering_core.devices import DTYPE_NAMES, DTYPES, SAFETENSORS_DTYPES
from steering_core.layout import layer_dir
from steering_core.remote.reads import RemoteFile, remote_file
from steering_core.storage.fileio import Crc32, atomic_path, feed_file, sha256_file, sha256_json, write_json
from steering_core.storage.schema import M, StrictModel, read_model
from steering_core.tensor_files import TensorLocation, layout_of, open_read, read_rows_into, readable, require_finite

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
RUN_FILE = "run.json"
METADATA_FILE = "metadata.json"
SHARD_FILE = "shard-{key}.safetensors"
SIDECAR_FILE = "shard-{key}.json"
SHARD_KEY = "{group:05d}"  # group = episode_index // episodes_per_shard

TokenType = Literal["instructions", "prompt", "last", "decision", "adarms"]
ACTION_TOKEN_TYPES = ("decision", "adarms")  # rows per frame and denoising step of the action expert
StorageDtype = Literal["float32", "bfloat16", "float16"]
STORAGE_DTYPES: dict[str, torch.dtype] = {name: DTYPES[name] for name in StorageDtype.__args__}
_DTYPE_NAMES = {code: DTYPE_NAMES[dtype] for code, dtype in SAFETENSORS_DTYPES.items()}  # safetensors header names
RESIDUALS = "residuals"
HEADER_KEY = "latent_steering"  # safetensors metadata entry: JSON of format_version, layer, key, token_type
ROW_COLUMNS: tuple[str, ...] = ("index", "episode_index", "frame_index", "token_position", "token_id")
SHARD_FIX = "the shard is damaged; re-run capture to rewrite it"
STEP = "step"  # the extra column of the action token types: denoising step 0..num_steps-1


def row_columns(token_type: str) -> tuple[str, ...]:
    """Return the per-row int64 columns of a token type's shards (the action types add `step`)."""
    return (*ROW_COLUMNS, STEP) if token_type in ACTION_TOKEN_TYPES else ROW_COLUMNS


class RunSpec(StrictModel):
    """What a run's shards hold (`run.json`); `identity()` is what every shard depends on."""

    format_version: int = FORMAT_VERSION
    token_type: TokenType
    layers: tuple[int, ...]
    width: int
    storage_dtype: StorageDtype = "float32"
    episodes_per_shard: int = 1
    inputs: dict[str, Any]  # fingerprints the rows depend on: checkpoint, arch, tokenizer, prompt format
    sources: dict[str, Any] = {}  # where inputs were read from (paths): recorded, never compared

    def identity(self) -> str:
        """Return the sha256 of everything but `sources`: equal identities give equal shards."""
        return sha256_json(self.model_dump(mode="json", exclude={"sources"}))


class ShardRecord(StrictModel):
    """The sidecar of one shard: enough to trust it without opening it."""

    format_version: int = FORMAT_VERSION
    file: str  # relative to the run folder, POSIX separators
    layer: int
    key: str
    episodes: tuple[int, ...]
    rows: int
    width: int
    dtype: StorageDtype
    sha256: str
    inputs: str  # fingerprint of the run identity + episode contents; resume compares it
    crc32: int | None = None  # CRC-32 (zlib's) of the file: slicing's check for damage (records before it have none)
    tasks: dict[str, dict[str, Any]] = {}  # task text -> token selection record (see capture)


class RunMetadata(StrictModel):
    """`metadata.json`: the run spec, its identity and every shard record."""

    format_version: int = FORMAT_VERSION
    run: RunSpec
    run_fingerprint: str  # RunSpec.identity() plus every shard's sha256
    episodes: tuple[int, ...]  # episodes present in every layer
    shards: tuple[ShardRecord, ...]
    tasks: dict[str, dict[str, Any]]  # merged from the sidecars

    def layer_shards(self, layer: int) -> tuple[ShardRecord, ...]:
        """Return the shard records of one layer, in episode order."""
        return tuple(record for record in self.shards if record.layer == layer)


@dataclass(frozen=True)
class ShardRows:
    """Rows of one shard in memory: `residuals` (rows, width) float, the rest (rows,) int64 (`step`: action types)."""

    residuals: torch.Tensor
    index: torch.Tensor
    episode_index: torch.Tensor
    frame_index: torch.Tensor
    token_position: torch.Tensor
    token_id: torch.Tensor
    step: torch.Tensor | None = None

    def columns(self) -> dict[str, torch.Tensor]:
        """Return the per-row int64 columns by name (`step` only when set)."""
        names = ROW_COLUMNS if self.step is None else (*ROW_COLUMNS, STEP)
        return {name: getattr(self, name) for name in names}


def shard_key(group: int) -> str:
    """Return the key of an episode group, e.g. `00003`."""
    return SHARD_KEY.format(group=group)


def group_episodes(episodes: Iterable[int], episodes_per_shard: int) -> dict[str, tuple[int, ...]]:
    """Return shard key -> sorted episode indices, grouping episode e into e // episodes_per_shard."""
    if episodes_per_shard < 1:
        raise ValueError(f"episodes_per_shard is {episodes_per_shard}, expected a positive integer")
    groups: dict[int, list[int]] = {}
    for episode in sorted(set(int(e) for e in episodes)):
        groups.setdefault(episode // episodes_per_shard, []).append(episode)
    return {shard_key(group): tuple(members) for group, members in sorted(groups.items())}


def layer_path(run_dir: str | os.PathLike, token_type: str, layer: int) -> Path:
    """Return `<run>/<token_type>/layerNN`."""
    return Path(run_dir) / token_type / layer_dir(layer)


def shard_path(run_dir: str | os.PathLike, token_type: str, layer: int, key: str) -> Path:
    """Return the path of one shard file."""
    return layer_path(run_dir, token_type, layer) / SHARD_FILE.format(key=key)


def sidecar_path(run_dir: str | os.PathLike, token_type: str, layer: int, key: str) -> Path:
    """Return the path of one shard's sidecar record."""
    return layer_path(run_dir, token_type, layer) / SIDECAR_FILE.format(key=key)


def check_run_spec(run_dir: str | os.PathLike, spec: RunSpec) -> None:
    """Raise if the folder already holds a run of another identity (a new folder passes)."""
    path = Path(run_dir) / RUN_FILE
    if not path.exists():
        return
    existing = read_run_spec(run_dir)
    if existing.identity() != spec.identity():
        old, new = existing.model_dump(mode="json"), spec.model_dump(mode="json")
        changed = sorted(k for k in new if k != "sources" and old.get(k) != new.get(k))
        raise ValueError(
            f"{path}: the run folder holds a capture with other settings (differs in {', '.join(changed)}); "
            "choose a new output folder or remove this one"
        )


def write_run_spec(run_dir: str | os.PathLike, spec: RunSpec) -> Path:
    """Write `run.json` (sources updated); refuse if the folder already holds a run of another identity."""
    check_run_spec(run_dir, spec)
    return write_json(Path(run_dir) / RUN_FILE, spec.model_dump(mode="json"))


def read_run_spec(run_dir: str | os.PathLike) -> RunSpec:
    """Return the validated `run.json` of a run folder."""
    return _read_versioned(Path(run_dir) / RUN_FILE, RunSpec, "run spec")


def write_shard(
    run_dir: str | os.PathLike,
    spec: RunSpec,
    layer: int,
    key: str,
    rows: ShardRows,
    *,
    episodes: Sequence[int],
    inputs: str,
    tasks: dict[str, dict[str, Any]] | None = None,
) -> ShardRecord:
    """Write one shard and then its sidecar, each atomically; return the sidecar record.

    Residuals are cast to the run's storage dtype. The bytes depend only on the rows,
    the layer and the key, so recomputing a shard reproduces it exactly.
    """
    _validate_rows(rows, spec, layer, key)
    path = shard_path(run_dir, spec.token_type, layer, key)
    require_finite(rows.residuals, path, RESIDUALS, "the model produced them; check the checkpoint and the frames")
    keys = [rows.token_position.numpy(), *([rows.step.numpy()] if rows.step is not None else []), rows.index.numpy()]
    order = np.lexsort(keys)  # sort by index, then step (action types), then position
    order_t = torch.from_numpy(order)
    tensors = {RESIDUALS: rows.residuals.detach().to("cpu", STORAGE_DTYPES[spec.storage_dtype])[order_t].contiguous()}
    tensors.update({name: column.to(torch.int64)[order_t].contiguous() for name, column in rows.columns().items()})
    header = {"format_version": FORMAT_VERSION, "layer": layer, "key": key, "token_type": spec.token_type}
    with atomic_path(path) as tmp:
        # one metadata entry holding canonical JSON: safetensors orders several entries at random
        save_file(tensors, str(tmp), metadata={HEADER_KEY: json.dumps(header, sort_keys=True)})
        digest, crc = hashlib.sha256(), Crc32()
        feed_file(tmp, digest, crc)  # one read for both
    record = ShardRecord(
        file=path.relative_to(run_dir).as_posix(),
        layer=layer,
        key=key,
        episodes=tuple(sorted(int(e) for e in episodes)),
        rows=int(rows.residuals.shape[0]),
        width=spec.width,
        dtype=spec.storage_dtype,
        sha256=digest.hexdigest(),
        inputs=inputs,
        tasks=tasks or {},
        crc32=crc.value,
    )
    write_json(sidecar_path(run_dir, spec.token_type, layer, key), record.model_dump(mode="json"))
    return record


def read_shard_record(path: str | os.PathLike) -> ShardRecord:
    """Return a validated sidecar record."""
    return _read_versioned(path, ShardRecord, "shard record")


def find_complete_shard(
    run_dir: str | os.PathLike, spec: RunSpec, layer: int, key: str, inputs: str
) -> ShardRecord | None:
    """Return the record of a complete, checksum-valid shard computed from `inputs`, else None.

    A missing or unreadable sidecar, a missing file, other inputs or a sha256 mismatch all
    mean the shard must be (re)computed; the reason is logged.
    """
    sidecar = sidecar_path(run_dir, spec.token_type, layer, key)
    path = shard_path(run_dir, spec.token_type, layer, key)
    if not sidecar.exists():
        return None
    try:
        record = read_shard_record(sidecar)
    except ValueError as err:
        logger.info("redoing %s: %s", path.name, err)
        return None
    if record.inputs != inputs or record.dtype != spec.storage_dtype or record.width != spec.width:
        logger.info("redoing %s (layer %d): computed from other inputs", path.name, layer)
        return None
    if not _holds(path, record.sha256):
        logger.info("redoing %s (layer %d): file missing or sha256 mismatch", path.name, layer)
        return None
    return record


def _holds(path: Path, sha256: str) -> bool:
    """Return True if the shard `path` holds bytes of this sha256: here, or published in the bucket of a mounted
    root (its publication record's sha256; the object's size and ETag checked against the record, never fetched)."""
    if path.exists():
        return sha256_file(path) == sha256
    try:
        remote = remote_file(path)
    except (ValueError, FileNotFoundError) as err:  # changed or gone since it was published: computed again
        logger.info("%s", err)
        return False
    return remote is not None and remote.sha256 == sha256


class ShardReader:
    """An open, validated shard: row columns as numpy, residual rows read with plain (or ranged) reads."""

    def __init__(self, path: Path, source: Path | RemoteFile, handle: Any, locations: dict[str, TensorLocation],
                 rows: int, width: int, dtype: str, names: tuple[str, ...]):
        self.path, self._handle, self._locations = path, handle, locations
        self.source = source  # the file or checked object read: `open_read(source)` opens it again unchecked
        self.rows, self.width, self.dtype = rows, width, dtype
        self.column_names = names  # ROW_COLUMNS, plus `step` in shards of the action token types

    def columns(self, names: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """Return the requested per-row columns (default all of the shard's), each (rows,) int64.

        One read of the bytes from the first column to the last (int64 tensors lie side by side in a
        safetensors file), viewed as the columns.
        """
        where = [self._locations[name] for name in names or self.column_names]
        start = min(location.offset for location in where)
        block = np.empty(max(location.offset + 8 * self.rows for location in where) - start, dtype=np.uint8)
        self._handle.seek(start)
        if self._handle.readinto(block) != block.size:
            raise ValueError(f"{self.path}: the file ends inside its row columns; it is truncated, re-run capture")
        return {location.name: block[location.offset - start : location.offset - start + 8 * self.rows].view("<i8")
                for location in where}

    def residuals(self, start: int = 0, stop: int | None = None) -> torch.Tensor:
        """Return residual rows [start, stop) as (stop - start, width) in the storage dtype."""
        location = self._locations[RESIDUALS]
        out = torch.empty((self.rows if stop is None else stop) - start, self.width, dtype=location.dtype)
        require_finite(read_rows_into(self._handle, location, start, out), self.path, RESIDUALS, SHARD_FIX, start)
        return out

    def residual_location(self) -> TensorLocation:
        """Return where the residual matrix lies in the file, for `steering_core.tensor_files.read_rows_into`."""
        return self._locations[RESIDUALS]


def checksum_mismatch(path: Path, kind: str, found: str, expected: str) -> str:
    """Return the error text of a shard whose bytes no longer match its record's `kind` (sha256 or CRC-32)."""
    return (f"{path}: {kind} is {found}, expected {expected} from its record; the file changed after capture, "
            "re-run capture to rewrite it")


@contextlib.contextmanager
def open_shard(
    path: str | os.PathLike,
    *,
    width: int | None = None,
    dtype: str | None = None,
    rows: int | None = None,
    sha256: str | None = None,
) -> Iterator[ShardReader]:
    """Yield an open shard after checking its keys, shapes and dtypes (and sha256 if given).

    The shard is read with plain reads of its file or, absent here under a mounted URL root, with ranged
    reads of its published object (`open_read`): its header, then whatever the reader asks for. A remote
    shard's identity check is its object's size and ETag against its publication record (done on open);
    `sha256` is checked for local files only, as it would fetch the whole object.
    Every problem is collected and raised once as a ValueError naming the file.
    """
    path = Path(path)
    source = readable(path)
    with open_read(source, missing="shard not found; re-run capture to write it") as (handle, size):
        if sha256 is not None and isinstance(source, Path) and (found := sha256_file(path)) != sha256:
            raise ValueError(checksum_mismatch(path, "sha256", found, sha256))
        try:
            layout, locations = layout_of(path, handle, size)
        except ValueError as err:
            raise ValueError(f"{path}: not a readable safetensors file ({err}); re-run capture to rewrite it") from None
        header = _header(layout)
        found_rows, found_width, found_dtype = _validate_shard(path, layout, width, dtype, rows, header)
        yield ShardReader(path, source, handle, locations, found_rows, found_width, found_dtype,
                          row_columns(header.get("token_type", "")))


def write_run_metadata(run_dir: str | os.PathLike) -> Path:
    """(Re)build `metadata.json` from `run.json` and every sidecar; return its path.

    Safe to call from any worker at any time: it reads only finished sidecars. Each sidecar's shard must be
    here or, under a mounted URL root, published in the bucket (a shard another machine captured).
    """
    run_dir = Path(run_dir)
    spec = read_run_spec(run_dir)
    records: list[ShardRecord] = []
    problems: list[str] = []
    for layer in spec.layers:
        for sidecar in sorted(layer_path(run_dir, spec.token_type, layer).glob(SIDECAR_FILE.format(key="*"))):
            record = read_shard_record(sidecar)
            if not _present(run_dir / record.file):
                problems.append(f"{sidecar}: its shard {record.file} is missing; re-run capture")
            elif record.layer != layer:
                problems.append(f"{sidecar}: `layer` is {record.layer}, expected {layer} from its folder")
            else:
                records.append(record)
    if problems:
        raise ValueError("\n".join(problems))
    records.sort(key=lambda r: (r.layer, r.episodes))
    per_layer = [{e for r in records if r.layer == layer for e in r.episodes} for layer in spec.layers]
    episodes = sorted(set.intersection(*per_layer)) if per_layer else []
    tasks: dict[str, dict[str, Any]] = {}
    for record in records:
        tasks.update(record.tasks)
    metadata = RunMetadata(
        run=spec,
        run_fingerprint=sha256_json({"run": spec.identity(), "shards": [(r.file, r.sha256) for r in records]}),
        episodes=tuple(episodes),
        shards=tuple(records),
        tasks=dict(sorted(tasks.items())),
    )
    return write_json(run_dir / METADATA_FILE, metadata.model_dump(mode="json"))


def _present(path: Path) -> bool:
    """Return whether a shard is here, or published in the bucket of its mounted root (`remote_file`)."""
    try:
        return path.is_file() or remote_file(path) is not None
    except FileNotFoundError:  # listed by its publication record, gone from the bucket
        return False


def read_run_metadata(run_dir: str | os.PathLike) -> RunMetadata:
    """Return the validated `metadata.json` of a run folder."""
    path = Path(run_dir) / METADATA_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: run metadata not found; run capture into {Path(run_dir)} first")
    return _read_versioned(path, RunMetadata, "run metadata")


def _header(layout: dict[str, Any]) -> dict[str, Any]:
    """Return the shard's own header entry from its safetensors header, or {} when absent or unreadable."""
    metadata = layout.get("__metadata__")
    try:
        header = json.loads(metadata.get(HEADER_KEY, "{}") if isinstance(metadata, dict) else "{}")
    except (json.JSONDecodeError, TypeError):
        return {}
    return header if isinstance(header, dict) else {}


def _read_versioned(path: str | os.PathLike, model: type[M], what: str) -> M:
    """Return a run-folder JSON record validated as `model`, checking this module's format_version."""
    return read_model(path, model, what=what, format_version=FORMAT_VERSION,
                      fix="it was written by another version of latent-steering, re-run capture")


def _validate_rows(rows: ShardRows, spec: RunSpec, layer: int, key: str) -> None:
    """Raise once listing every shape/dtype problem of rows about to be written."""
    name = SHARD_FILE.format(key=key)
    problems = []
    if layer not in spec.layers:
        problems.append(f"layer {layer} is not one of the run's layers {list(spec.layers)}")
    residuals = rows.residuals
    if residuals.ndim != 2 or residuals.shape[1] != spec.width or not residuals.is_floating_point():
        problems.append(
            f"`{RESIDUALS}` is {tuple(residuals.shape)} {residuals.dtype}, expected (*, {spec.width}) floating point"
        )
    n_rows = residuals.shape[0] if residuals.ndim else -1
    if (rows.step is not None) != (spec.token_type in ACTION_TOKEN_TYPES):
        problems.append(f"`{STEP}` is {'set' if rows.step is not None else 'missing'}; token type "
                        f"{spec.token_type!r} expects it {'set' if rows.step is None else 'unset'}")
    for column, values in rows.columns().items():
        if values.ndim != 1 or values.shape[0] != n_rows or values.is_floating_point():
            problems.append(f"`{column}` is {tuple(values.shape)} {values.dtype}, expected ({n_rows},) integer")
    if problems:
        raise ValueError(f"{name} (layer {layer}): " + "; ".join(problems))


def _validate_shard(
    path: Path, layout: dict[str, Any], width: int | None, dtype: str | None, rows: int | None, header: dict[str, Any]
) -> tuple[int, int, str]:
    """Return (rows, width, dtype) of a shard from its safetensors header; raise once listing every problem."""
    fix = f"re-run capture for layer {header.get('layer', '?')}"
    keys = set(layout) - {"__metadata__"}
    columns = row_columns(header.get("token_type", ""))
    expected_keys = {RESIDUALS, *columns}
    problems = []
    if header.get("format_version") != FORMAT_VERSION:
        problems.append(f"header `format_version` is {header.get('format_version')!r}, expected {FORMAT_VERSION}")
    if keys != expected_keys:
        missing, unexpected = sorted(expected_keys - keys), sorted(keys - expected_keys)
        problems.append(f"tensors missing {missing}, unexpected {unexpected}")
    found_rows, found_width, found_dtype = -1, -1, "?"
    if RESIDUALS in keys:
        shape = tuple(layout[RESIDUALS]["shape"])
        found_dtype = _DTYPE_NAMES.get(layout[RESIDUALS]["dtype"], layout[RESIDUALS]["dtype"])
        if (
            len(shape) != 2
            or found_dtype not in STORAGE_DTYPES
            or (width is not None and shape[1] != width)
            or (rows is not None and shape[0] != rows)
            or (dtype is not None and found_dtype != dtype)
        ):
            problems.append(
                f"`{RESIDUALS}` is {shape} {found_dtype}, expected ({'*' if rows is None else rows}, "
                f"{'*' if width is None else width}) {dtype or ' or '.join(STORAGE_DTYPES)}"
            )
        else:
            found_rows, found_width = shape
    for column in columns:
        if column in keys:
            shape, stored = layout[column]["shape"], layout[column]["dtype"]
            if stored != "I64" or len(shape) != 1 or (found_rows >= 0 and shape[0] != found_rows):
                n = "*" if found_rows < 0 else found_rows
                problems.append(f"`{column}` is {tuple(shape)} {stored}, expected ({n},) I64")
    if problems:
        raise ValueError(f"{path}: " + "; ".join(problems) + f"; {fix}")
    return found_rows, found_width, found_dtype
