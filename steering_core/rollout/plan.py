"""The task runs of a (pair, layer): one `RolloutJob` per (cell, chunk of initial states), in a fixed order."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from steering_core.layout import PAIR_SUMMARY_FILE, layer_dir
from steering_core.rollout.grid import cells, chunks
from steering_core.rollout.run import RolloutJob
from steering_core.rollout.settings import RolloutPair, RolloutSettings
from steering_core.storage.fileio import read_json

if TYPE_CHECKING:
    from steering_core.config import RunConfig


def pair_jobs(pair: str, layer: int, tasks: RolloutPair, settings: RolloutSettings, *, other_pairs: list[str],
              vectors_root: Path, output_dir: Path, sides: tuple[str, ...] | None = None) -> list[RolloutJob]:
    """Return the jobs of every cell of (pair, layer) (of `sides` only, when given); `output_dir` is the pair's
    folder, each cell writes into `output_dir/<cell name>/`. Refuses a method phase 3 did not write (`check_methods_written`)."""
    check_methods_written(vectors_root, pair, layer, settings.methods)
    if settings.wrong_concept and other_pairs:
        check_methods_written(vectors_root, other_pairs[0], layer, settings.methods[:1])
    jobs = []
    for cell in cells(pair, layer, settings, other_pairs):
        if sides is not None and cell.side not in sides:
            continue
        for index, states in enumerate(chunks(settings)):
            jobs.append(RolloutJob(cell=cell, tasks=tasks, init_states=states, chunk=index, vectors_root=vectors_root,
                                   output_dir=output_dir / cell.name))
    return jobs


def check_methods_written(vectors_root: Path, pair: str, layer: int, methods: tuple[str, ...]) -> None:
    """Raise one ValueError naming `rollout.methods` unless the pair's directions.json at `layer` lists every one
    of `methods` (phase 3 writes the methods of `steering.methods`)."""
    path = vectors_root / layer_dir(layer) / pair / PAIR_SUMMARY_FILE
    if not path.is_file():
        raise FileNotFoundError(f"rollout.methods {list(methods)}: pair {pair!r}, layer {layer} has no {path}; run "
                                "the steer step (phase 3) first")
    listed = list(read_json(path).get("methods", {}))
    missing = [name for name in methods if name not in listed]
    if missing:
        raise ValueError(f"rollout.methods {list(methods)}: pair {pair!r}, layer {layer} has no {missing} direction "
                         f"(phase 3 wrote {listed} in {path}); roll out those, or add the method to steering.methods "
                         "and re-run the steer step")


def by_cell(jobs: list[RolloutJob]) -> dict[Path, list[RolloutJob]]:
    """Return the jobs grouped by their cell folder, in order."""
    groups: dict[Path, list[RolloutJob]] = {}
    for job in jobs:
        groups.setdefault(job.output_dir, []).append(job)
    return groups


def config_jobs(config: RunConfig, name: str, layer: int, sides: tuple[str, ...] | None = None) -> list[RolloutJob]:
    """Return the jobs of (pair, layer) of a run config (of `sides` only, when given); the wrong-concept control
    uses the next rolled-out pair at the same layer."""
    pairs = [pair for pair, at in config.rollout_targets() if at == layer]
    others = pairs[pairs.index(name) + 1:] + pairs[:pairs.index(name)]
    return pair_jobs(name, layer, config.rollout.pairs[name], config.rollout.settings(), other_pairs=others,
                     vectors_root=config.steering_root, output_dir=config.rollout_layer_path(layer) / name, sides=sides)


def layer_cells(config: RunConfig, layer: int) -> dict[str, list[Path]]:
    """Return pair -> its cell folders of the current grid, for every rolled-out pair at `layer`, in order."""
    return {name: list(by_cell(config_jobs(config, name, layer))) for name, at in config.rollout_targets()
            if at == layer}


def write_layer_report(config: RunConfig, layer: int) -> Path:
    """Write the reports of the pairs done at `layer` and the layer's summary.md (see report.write_layer)."""
    from steering_core.rollout.report import write_layer

    return write_layer(config.rollout_layer_path(layer), layer_cells(config, layer), note=config.rollout.note)
