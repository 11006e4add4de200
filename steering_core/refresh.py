"""Demo-source change detection: which demo files were added, changed or removed since the last good run.

A scheduled refresh scans the demo source folders, compares every file's sha256 with the record
written after the last successful pipeline run, and runs the pipeline only when something differs
(or when the run config itself changed). Hashing gigabytes of hdf5 on every tick would be slow,
so a file whose size and modification time match the record keeps its recorded hash: the quick
check git and rsync use. `rehash=True` forces full hashing. A run on an existing LeRobot dataset
has no demo files: its record holds the dataset's content fingerprint (`dataset_fingerprint`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from steering_core.data.dataset import dataset_fingerprint
from steering_core.storage.fileio import sha256_file, write_json
from steering_core.storage.schema import StrictModel, read_model

if TYPE_CHECKING:
    from steering_core.config import RunConfig

logger = logging.getLogger(__name__)

SOURCES_RECORD_FILE = "refresh/last_success.json"  # under the run's output root
RECORD_FORMAT_VERSION = 1
DEMO_PATTERN = "*.hdf5"


class SourceFile(StrictModel):
    """One demo file as seen by a scan: size and mtime for the quick check, sha256 for identity."""

    size: int
    mtime_ns: int
    sha256: str


class SourcesRecord(StrictModel):
    """Every demo file under the source folders (absolute path -> file), plus the run config's hash.

    A run on an existing dataset records that dataset (absolute root, content fingerprint) instead.
    """

    format_version: int = RECORD_FORMAT_VERSION
    config_fingerprint: str = ""
    files: dict[str, SourceFile] = {}
    dataset_root: str = ""
    dataset_fingerprint: str = ""

    def with_config(self, config_fingerprint: str) -> SourcesRecord:
        """Return this record stamped with the fingerprint of the run config it was used with."""
        return self.model_copy(update={"config_fingerprint": config_fingerprint})


@dataclass(frozen=True)
class SourceChanges:
    """Demo files added, changed and removed between two scans, and whether the run config changed."""

    added: tuple[str, ...] = ()
    changed: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()
    config_changed: bool = False
    first_run: bool = False
    dataset: str = ""             # an existing dataset's root, when the run reads one in place
    dataset_changed: bool = False

    def __bool__(self) -> bool:
        return bool(self.first_run or self.config_changed or self.dataset_changed
                    or self.added or self.changed or self.removed)

    def describe(self) -> str:
        """Return a one-line account of the changes, e.g. `2 added (a.hdf5, b.hdf5), 0 changed, 0 removed`."""
        if self.first_run:
            return "no record of a successful run yet: running the whole pipeline"
        if self.dataset:
            text = f"dataset {self.dataset}: content {'changed' if self.dataset_changed else 'unchanged'}"
        else:
            text = ", ".join(_describe_files(label, files) for label, files in
                             (("added", self.added), ("changed", self.changed), ("removed", self.removed)))
        return f"{text}; run config changed" if self.config_changed else text


def _describe_files(label: str, files: Sequence[str], shown: int = 3) -> str:
    """Return `N label (name, name, ...)` with at most `shown` base names."""
    if not files:
        return f"0 {label}"
    names = ", ".join(Path(f).name for f in files[:shown])
    more = f", +{len(files) - shown} more" if len(files) > shown else ""
    return f"{len(files)} {label} ({names}{more})"


def list_demo_files(folders: Iterable[str | os.PathLike], pattern: str = DEMO_PATTERN) -> list[Path]:
    """Return the sorted absolute paths of the demo files matching `pattern` directly inside each folder.

    Not recursive, like the filter step, which selects only files directly inside its input folders.
    """
    found: set[Path] = set()
    missing = []
    for folder in folders:
        folder = Path(folder)
        if not folder.is_dir():
            missing.append(str(folder))
            continue
        found.update(p.resolve() for p in folder.glob(pattern) if p.is_file())
    if missing:
        raise FileNotFoundError(
            f"demo source folder(s) not found: {', '.join(missing)}; "
            "fix `sources` in the run config or mount the folders"
        )
    return sorted(found)


def scan_sources(
    folders: Iterable[str | os.PathLike],
    *,
    pattern: str = DEMO_PATTERN,
    previous: SourcesRecord | None = None,
    rehash: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> SourcesRecord:
    """Return the current record of every demo file under `folders`.

    A file whose size and mtime equal those in `previous` keeps its recorded sha256 unless
    `rehash`; every other file is hashed. `progress(done, total)` is called after each file.
    """
    paths = list_demo_files(folders, pattern)
    known = previous.files if previous is not None and not rehash else {}
    files: dict[str, SourceFile] = {}
    hashed = 0
    for done, path in enumerate(paths, start=1):
        stat = path.stat()
        old = known.get(str(path))
        if old is not None and old.size == stat.st_size and old.mtime_ns == stat.st_mtime_ns:
            files[str(path)] = old
        else:
            files[str(path)] = SourceFile(size=stat.st_size, mtime_ns=stat.st_mtime_ns, sha256=sha256_file(path))
            hashed += 1
        if progress is not None:
            progress(done, len(paths))
    logger.info("scanned %d demo files (%d hashed, %d unchanged by size and mtime)",
                len(paths), hashed, len(paths) - hashed)
    return SourcesRecord(files=files)


def scan_dataset(root: str | os.PathLike) -> SourcesRecord:
    """Return the record of an existing LeRobot dataset: its absolute root and content fingerprint."""
    root = Path(root).resolve()
    fingerprint = dataset_fingerprint(root)
    logger.info("dataset %s: content fingerprint %s", root, fingerprint[:12])
    return SourcesRecord(dataset_root=str(root), dataset_fingerprint=fingerprint)


def scan_inputs(config: RunConfig, *, previous: SourcesRecord | None = None, rehash: bool = False) -> SourcesRecord:
    """Return the current record of what the run reads: its hdf5 demo files, or its existing dataset."""
    if config.sources is None:
        return scan_dataset(config.dataset_root)
    return scan_sources(config.sources.folders, previous=previous, rehash=rehash)


def diff_sources(
    previous: SourcesRecord | None, current: SourcesRecord, *, config_fingerprint: str = ""
) -> SourceChanges:
    """Return what changed from `previous` (None: no successful run yet) to `current`.

    A file counts as changed when its sha256 differs, an existing dataset when its root or content
    fingerprint does; `config_fingerprint`, when given, is compared with the one stored in `previous`.
    """
    if previous is None:
        return SourceChanges(first_run=True)
    old, new = previous.files, current.files
    dataset = (current.dataset_root, current.dataset_fingerprint)
    return SourceChanges(
        added=tuple(sorted(set(new) - set(old))),
        changed=tuple(sorted(p for p in set(new) & set(old) if new[p].sha256 != old[p].sha256)),
        removed=tuple(sorted(set(old) - set(new))),
        config_changed=bool(config_fingerprint) and config_fingerprint != previous.config_fingerprint,
        dataset=current.dataset_root,
        dataset_changed=dataset != (previous.dataset_root, previous.dataset_fingerprint),
    )


def read_sources_record(path: str | os.PathLike) -> SourcesRecord | None:
    """Return the record stored at `path`, or None when no successful run has written one."""
    path = Path(path)
    if not path.exists():
        return None
    return read_model(path, SourcesRecord, what="refresh record", format_version=RECORD_FORMAT_VERSION,
                      fix="delete the file to make the next refresh run the whole pipeline")


def write_sources_record(path: str | os.PathLike, record: SourcesRecord) -> Path:
    """Write `record` atomically to `path`; return the path."""
    return write_json(path, record.model_dump(mode="json"))
