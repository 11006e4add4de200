"""Contrast manifests straight from two LIBERO hdf5 task files, as the seed's `--backend hdf5` built them.

Each demo's state is the 8-D state `convert` writes (`LiberoDemo.state8`), so the axis and windows
equal those of a manifest built from the converted dataset. Segments name the file and `demo_<k>`
(no episode index); `concept_map` joins them to a converted dataset through its
`meta/libero_sources.json`. Demos are taken in numeric key order, or in the seed's lexicographic
order (`sorted(keys)`: demo_10 before demo_2), which decides which demos `max_demos_per_task` keeps.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from steering_core.data.contrast import ContrastManifest, ContrastSettings, DemoStates, contrast
from steering_core.data.convert import DemoOrder
from steering_core.data.libero import demo_sort_key, iter_demos, validate_file


def find_task_file(path: str | os.PathLike, search_root: str | os.PathLike | None) -> Path:
    """Return a task file: the path as given if it exists, else under `search_root` (as a relative path, then by name).

    Raises FileNotFoundError naming where it looked, ValueError when the name is found more than once.
    """
    given = Path(path).expanduser()
    if given.is_file():
        return given
    if search_root is None:
        raise FileNotFoundError(f"{given}: task file not found (pass --search-root to look for it by name)")
    root = Path(search_root)
    if (root / given).is_file():
        return root / given
    found = sorted(root.rglob(given.name))
    if len(found) == 1:
        return found[0]
    if found:
        raise ValueError(f"{given.name}: found {len(found)} times under {root}: {[str(p) for p in found]}; give its path")
    raise FileNotFoundError(f"{given}: task file not found as given, under {root}, or by name anywhere below it")


def build_hdf5_manifest(
    file_a: str | os.PathLike,
    file_b: str | os.PathLike,
    settings: ContrastSettings | None = None,
    *,
    search_root: str | os.PathLike | None = None,
    demo_order: DemoOrder = "numeric",
) -> ContrastManifest:
    """Return the contrast manifest of two LIBERO task files (task A's demos against task B's).

    Labels default to the files' instructions; `settings.task_a_episodes` select demo numbers k of `demo_<k>`.
    Segment `file` fields are relative to `search_root` when the file lies under it, else as found.
    """
    settings = settings or ContrastSettings()
    path_a, path_b = find_task_file(file_a, search_root), find_task_file(file_b, search_root)
    demos_a, text_a = _demo_states(path_a, settings.task_a_episodes, settings, search_root, demo_order, "--task-a-episodes")
    demos_b, text_b = _demo_states(path_b, settings.task_b_episodes, settings, search_root, demo_order, "--task-b-episodes")
    label_a, label_b = settings.task_a_label or text_a, settings.task_b_label or text_b
    axis, segments = contrast(label_a, label_b, demos_a, demos_b, settings)
    return ContrastManifest(axis=axis, segments=segments)


def _demo_states(
    path: Path, numbers: Sequence[int] | None, settings: ContrastSettings, search_root: str | os.PathLike | None,
    demo_order: DemoOrder, flag: str,
) -> tuple[list[DemoStates], str]:
    """Return the selected demos of one file with their (frames, 8) float64 states, and the file's instruction."""
    info = validate_file(path)
    keys = sorted(info.demo_lengths) if demo_order == "lexicographic" else info.demo_keys
    if numbers is not None:
        by_number = {demo_sort_key(key): key for key in keys}
        if unknown := sorted(set(numbers) - set(by_number)):
            raise ValueError(f"{flag}: {path} has no demo(s) {unknown}; its demos are {sorted(by_number)}")
        keys = [key for key in keys if demo_sort_key(key) in set(numbers)]
    if settings.max_demos_per_task is not None:
        keys = keys[: settings.max_demos_per_task]
    shown = _relative(path, search_root)
    demos = [DemoStates(shown, demo_key, None, demo.state8().astype(np.float64))
             for demo_key, demo in zip(keys, iter_demos(path, keys), strict=True)]
    return demos, info.instruction


def _relative(path: Path, search_root: str | os.PathLike | None) -> str:
    """Return `path` relative to `search_root` when below it, else as given (posix)."""
    if search_root is not None:
        try:
            return path.resolve().relative_to(Path(search_root).resolve()).as_posix()
        except ValueError:
            pass
    return path.as_posix()
