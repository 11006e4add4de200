"""A pair's sign: its positive concept is the manifest's first task (`axis.mean_delta_per_task` order).

Downstream, the manifest's task order is (positive, negative): the evaluation's instruction swap and the sign of
its efficacy. A hand-written pairs config listing the concepts the other way round gives a reversed direction
that reads as success at α < 0, so it is refused. A side's concept is its label (`pair_slices` checked it against
the slices' index.json). Phase 3 finds the manifest through the slices (index.json -> concept map ->
manifest) and refuses only a reversed pair; the evaluation knows the pair's manifest and wants its two tasks.
"""

from __future__ import annotations

from pathlib import Path

from steering_core.data.concept_map import ConceptMap, read_concept_map
from steering_core.data.contrast import ContrastManifest, read_manifest
from steering_core.storage.fileio import read_json
from steering_core.vectors.pair_slices import slice_index


def task_concepts(concept_map: ConceptMap, manifest: ContrastManifest, tasks: tuple[str, ...], where: Path) -> tuple[str, ...]:
    """Return the concept name of each task text (the map's names, after any `rename`), via its segments."""
    owner = {manifest.segments[row.segment_id].task: name for name, rows in concept_map.concepts.items() for row in rows}
    missing = [task for task in tasks if task not in owner]
    if missing:
        raise ValueError(f"{where}: no concept covers task(s) {missing}; the concept map belongs to another manifest")
    return tuple(owner[task] for task in tasks)


def manifest_concepts(manifest_path: Path, concept_map_path: Path) -> tuple[str, str]:
    """Return the concepts of the manifest's (positive, negative) tasks."""
    manifest = read_manifest(manifest_path)
    tasks = tuple(manifest.axis.mean_delta_per_task)
    return task_concepts(read_concept_map(concept_map_path), manifest, tasks, concept_map_path)


def check_pair_order(name: str, found: tuple[str, str], expected: tuple[str, str], manifest: Path, where: Path) -> None:
    """Raise (one line naming both orders) unless the pair's (positive, negative) concepts are `expected`."""
    if tuple(found) != tuple(expected):
        raise ValueError(
            f"{where}: pair {name!r} has positive {found[0]!r} and negative {found[1]!r}, but its manifest {manifest} "
            f"lists positive {expected[0]!r} then negative {expected[1]!r} (axis.mean_delta_per_task); the positive "
            "concept must be the manifest's first task")


def check_slices_order(name: str, labels: tuple[str, str], files: tuple[Path, Path], where: Path) -> None:
    """Raise when the slices' own manifest lists the pair's two concepts the other way round (phase 3).

    Slices without an index.json, a concept map or a manifest that can be found are not checked.
    """
    index = slice_index(files[0])
    map_path = Path(str(index.get("concept_map"))) if index else None
    if map_path is None or not map_path.is_file():
        return
    manifest_path = Path(str(read_json(map_path).get("manifest")))
    if not manifest_path.is_file():
        return
    expected = manifest_concepts(manifest_path, map_path)
    if tuple(labels) == tuple(reversed(expected)):
        check_pair_order(name, labels, expected, manifest_path, where)
