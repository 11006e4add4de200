"""A pair's two slice files, checked against each other and against their slices' index.json (steer, evaluate).

A pairs config names each side's slice file and concept label by hand; the slices `slice` writes carry an
index.json saying which layer they hold and which concept each file is. Refused, one line per pairs config: one
file or one label on both sides, slices of another layer than the one steered, a file its index.json does not
list or lists under another concept than the side's label (another pair's slice, say), and two sides cut from
different concept maps. Slices without an index.json (the seed's) are checked for the first two only, and an
index.json without a `layer` or `concepts` for what it does not say.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from steering_core.layout import SLICE_INDEX_FILE
from steering_core.pairs import SIDES, same_text
from steering_core.storage.fileio import read_json

PairSlices = tuple[str, tuple[str, str], tuple[Path, Path]]  # (pair name, (positive, negative) labels, files)


def slice_index(path: Path) -> dict[str, Any] | None:
    """Return the index.json beside a slice file, or None when there is none (or it is not a JSON object)."""
    index_path = path.parent / SLICE_INDEX_FILE
    if not index_path.is_file():
        return None
    index = read_json(index_path)
    return index if isinstance(index, dict) else None


def indexed_concepts(index: dict[str, Any], path: Path) -> list[str] | None:
    """Return the concepts an index.json lists `path` under (its `.pt` or `.safetensors` copy); None when the index
    lists no concepts."""
    entries = index.get("concepts")
    if not isinstance(entries, dict):
        return None
    return [concept for concept, entry in entries.items()
            if isinstance(entry, dict) and path.name in (entry.get("pt"), entry.get("safetensors"))]


def pair_slice_problems(name: str, labels: tuple[str, str], files: tuple[Path, Path], layer: int) -> list[str]:
    """Return what is wrong with one pair's (positive, negative) labels and slice files for steering `layer`."""
    problems = []
    if same_text(*labels):
        problems.append(f"positive_label and negative_label are both {labels[0]!r}; a pair contrasts two concepts")
    if files[0].resolve() == files[1].resolve():
        problems.append(f"positive_path and negative_path are both {files[0]}; a pair contrasts two slices")
    indexes = [slice_index(path) if path.is_file() else None for path in files]
    for side, label, path, index in zip(SIDES, labels, files, indexes, strict=True):
        if index is None:
            continue
        where = f"{side}_path {path}"
        if index.get("layer", layer) != layer:
            problems.append(f"{where} holds layer {index['layer']!r} slices (its {SLICE_INDEX_FILE}), expected "
                            f"layer {layer}; point it at the layer{layer:02d} slices")
        concepts = indexed_concepts(index, path)
        if concepts == []:
            problems.append(f"{where} is not a slice its {SLICE_INDEX_FILE} lists")
        elif concepts is not None and label not in concepts:
            problems.append(f"{where} holds concept {concepts[0]!r} (its {SLICE_INDEX_FILE}), not the pair's "
                            f"{side}_label {label!r}; point it at this pair's {label!r} slice")
    maps = [index.get("concept_map") for index in indexes if index is not None]
    if len(maps) == 2 and maps[0] != maps[1]:
        problems.append(f"its two slices come from different concept maps ({maps[0]}, {maps[1]}); take both sides "
                        "from one pair's slices")
    return [f"pair {name!r}: {problem}" for problem in problems]


def check_pair_slices(pairs: Iterable[PairSlices], layer: int, where: Path) -> None:
    """Raise one ValueError naming the pairs config `where` and every problem of its pairs' slices."""
    problems = [problem for name, labels, files in pairs for problem in pair_slice_problems(name, labels, files, layer)]
    if problems:
        raise ValueError(f"{where}: " + "; ".join(problems))
