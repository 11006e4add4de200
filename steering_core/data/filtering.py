"""Select LIBERO demo files by task text or file-name glob into a filtered folder.

The folder holds the selected `.hdf5` files (symlinks by default, copies on request) and
`selection.json`, which records for each file its source path, instruction and sha256 so
later steps (and the scheduled refresh) can tell exactly what was selected.
"""

from __future__ import annotations

import difflib
import fnmatch
import logging
import os
import shutil
from pathlib import Path
from typing import Literal

from pydantic import Field

from steering_core.data.libero import InstructionSource, read_instruction_with_source, validate_file
from steering_core.layout import SELECTION_FILE
from steering_core.storage.fileio import atomic_dir, sha256_file, write_json
from steering_core.storage.schema import StrictModel, read_model

logger = logging.getLogger(__name__)

SELECTION_FORMAT_VERSION = 1
DEMO_FILE_GLOB = "*.hdf5"
_CLOSE_MATCHES = 5


class FilterSettings(StrictModel):
    """What to select: files whose instruction matches a task text, or whose name matches a glob."""

    tasks: tuple[str, ...] = ()
    globs: tuple[str, ...] = ()
    match: Literal["exact", "ignore_case"] = "ignore_case"  # ignore_case also collapses whitespace
    mode: Literal["symlink", "copy"] = "symlink"


class SelectedFile(StrictModel):
    """One entry of `selection.json`."""

    name: str
    source: str                       # absolute path of the source file
    instruction: str
    instruction_source: InstructionSource
    sha256: str
    num_demos: int = Field(ge=1)


class Selection(StrictModel):
    """The content of `selection.json`."""

    format_version: int = SELECTION_FORMAT_VERSION
    settings: FilterSettings
    files: tuple[SelectedFile, ...]


def filter_demos(
    input_dirs: list[str | Path] | tuple[str | Path, ...],
    output_dir: str | Path,
    settings: FilterSettings,
) -> Selection:
    """Return the selection written to `output_dir` (links or copies + `selection.json`).

    Raises `ValueError` listing every task text that matches no file (with the closest
    available instructions) and every glob that matches nothing. Re-running with the same
    inputs and settings leaves an identical folder untouched.
    """
    output_dir = Path(output_dir)
    chosen, instructions = select_files(input_dirs, output_dir, settings)
    files = []
    for path in chosen:
        info = validate_file(path)
        text, source = instructions[path]
        files.append(
            SelectedFile(
                name=path.name,
                source=str(path.resolve()),
                instruction=text,
                instruction_source=source,
                sha256=sha256_file(path),
                num_demos=info.num_demos,
            )
        )
    _warn_duplicates(files)
    selection = Selection(settings=settings, files=tuple(files))

    if _unchanged(output_dir, selection):
        logger.info("%s: selection unchanged (%d files); nothing to do", output_dir, len(files))
        return selection
    _check_replaceable(output_dir)
    with atomic_dir(output_dir, overwrite=True) as tmp:
        tmp.mkdir()
        for entry in files:
            if settings.mode == "copy":
                shutil.copy2(entry.source, tmp / entry.name)
            else:
                os.symlink(entry.source, tmp / entry.name)
        write_json(tmp / SELECTION_FILE, selection.model_dump(mode="json"))
    logger.info("%s: selected %d file(s) (%s)", output_dir, len(files), settings.mode)
    return selection


def select_files(
    input_dirs: list[str | Path] | tuple[str | Path, ...], output_dir: str | Path, settings: FilterSettings
) -> tuple[list[Path], dict[Path, tuple[str, InstructionSource]]]:
    """Return (selected files sorted by name, readable file -> (instruction, source)); nothing is written.

    Reads only each file's attributes. Raises as `filter_demos` does, naming unreadable files when a
    task text matches nothing (a truncated demo may be the file it was meant to match).
    """
    if not settings.tasks and not settings.globs:
        raise ValueError("nothing to select: pass at least one task text (--task) or file-name glob (--glob)")
    candidates = _candidates(input_dirs, Path(output_dir))
    instructions = _instructions(candidates)
    return _choose(candidates, instructions, settings), instructions


def read_selection(folder: str | Path) -> Selection:
    """Return the validated `selection.json` of a filtered folder."""
    return read_model(Path(folder) / SELECTION_FILE, Selection, what="selection record",
                      fix="re-run `latent-steering filter`", format_version=SELECTION_FORMAT_VERSION)


def normalize_task(text: str, match: Literal["exact", "ignore_case"]) -> str:
    """Return the form of `text` compared under `match` (stripped; casefolded, single-spaced if ignore_case)."""
    return text.strip() if match == "exact" else " ".join(text.split()).casefold()


# ----------------------------------------------------------------------------- internals


def _candidates(input_dirs: list[str | Path] | tuple[str | Path, ...], output_dir: Path) -> list[Path]:
    """Return every `*.hdf5` directly inside the input folders, sorted by name; names must be unique."""
    if not input_dirs:
        raise ValueError("no input folder given: pass --input-dir at least once")
    found: dict[str, Path] = {}
    clashes: list[str] = []
    for folder in map(Path, input_dirs):
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: input folder not found")
        if folder.resolve() == output_dir.resolve():
            raise ValueError(f"{folder}: the input folder is also the output folder; choose another --output-dir")
        for path in sorted(folder.glob(DEMO_FILE_GLOB)):
            if path.name in found and found[path.name].resolve() != path.resolve():
                clashes.append(f"{path.name} in both {found[path.name].parent} and {folder}")
            found.setdefault(path.name, path)
    if clashes:
        raise ValueError(
            "two input files share a name, so they cannot sit in one filtered folder: " + "; ".join(clashes)
        )
    if not found:
        raise ValueError(f"no {DEMO_FILE_GLOB} files in {', '.join(str(d) for d in input_dirs)}")
    return [found[name] for name in sorted(found)]


def _instructions(candidates: list[Path]) -> dict[Path, tuple[str, InstructionSource]]:
    """Return each readable candidate's (instruction, source); unreadable files are skipped with a warning."""
    result = {}
    for path in candidates:
        try:
            result[path] = read_instruction_with_source(path)
        except ValueError as err:
            logger.warning("skipping %s for task matching: %s", path, err)
    return result


def _choose(
    candidates: list[Path], instructions: dict[Path, tuple[str, InstructionSource]], settings: FilterSettings
) -> list[Path]:
    """Return the selected paths (sorted by name); raise once for every task or glob that matched nothing."""
    problems = []
    chosen: set[Path] = set()
    for task in settings.tasks:
        wanted = normalize_task(task, settings.match)
        hits = {p for p, (text, _) in instructions.items() if normalize_task(text, settings.match) == wanted}
        if not hits:
            problems.append(_unknown_task_message(task, sorted({text for text, _ in instructions.values()})))
        chosen |= hits
    for pattern in settings.globs:
        hits = {p for p in candidates if fnmatch.fnmatchcase(p.name, pattern)}
        if not hits:
            problems.append(f"glob {pattern!r} matches no file name among {len(candidates)} candidate(s)")
        chosen |= hits
    if problems:
        if unreadable := [p.name for p in candidates if p not in instructions]:
            problems.append(f"{len(unreadable)} file(s) could not be read, so their instructions are unknown "
                            f"(see the warnings above): {', '.join(unreadable[:5])}")
        raise ValueError("cannot select demo files: " + "; ".join(problems))
    return sorted(chosen, key=lambda p: p.name)


def _unknown_task_message(task: str, available: list[str]) -> str:
    """Return the error line for a task text that matched nothing, naming the closest instructions."""
    folded = {text.casefold(): text for text in available}
    close = difflib.get_close_matches(task.casefold(), list(folded), n=_CLOSE_MATCHES, cutoff=0.0)
    listed = "; ".join(repr(folded[c]) for c in close) or "(no readable instructions in the input folders)"
    return f"task {task!r} matches no file's instruction; closest available: {listed}"


def _warn_duplicates(files: list[SelectedFile]) -> None:
    """Warn about every selected file that is a byte-identical copy of another: its demos would become new episodes."""
    first: dict[str, SelectedFile] = {}
    for entry in files:
        original = first.setdefault(entry.sha256, entry)
        if original is not entry:
            logger.warning("%s is a byte-identical copy of %s (sha256 %s): its %d demo(s) are added again as new "
                           "episodes; remove one of the two files unless that is intended",
                           entry.source, original.source, entry.sha256[:12], entry.num_demos)


def _unchanged(output_dir: Path, selection: Selection) -> bool:
    """Return True when `output_dir` already holds exactly this selection."""
    if not (output_dir / SELECTION_FILE).is_file():
        return False
    try:
        existing = read_selection(output_dir)
    except ValueError:
        return False
    if existing != selection:
        return False
    present = {p.name for p in output_dir.iterdir() if p.name != SELECTION_FILE}
    return present == {f.name for f in selection.files} and all((output_dir / f.name).exists() for f in selection.files)


def _check_replaceable(output_dir: Path) -> None:
    """Refuse to replace a non-empty folder that is not a previous filter output."""
    if output_dir.exists() and any(output_dir.iterdir()) and not (output_dir / SELECTION_FILE).is_file():
        raise ValueError(
            f"{output_dir}: exists, is not empty and has no {SELECTION_FILE}, so it is not a filter output; "
            "choose another --output-dir or empty it"
        )
