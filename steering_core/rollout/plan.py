"""The task runs of a (pair, layer): one `RolloutJob` per (cell, chunk of initial states), in a fixed order."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from steering_core.rollout.grid import cells, chunks
from steering_core.rollout.run import RolloutJob
from steering_core.rollout.settings import RolloutPair, RolloutSettings

if TYPE_CHECKING:
    from steering_core.config import RunConfig


def pair_jobs(pair: str, layer: int, tasks: RolloutPair, settings: RolloutSettings, *, other_pairs: list[str],
              vectors_root: Path, output_dir: Path, sides: tuple[str, ...] | None = None) -> list[RolloutJob]:
    """Return the jobs of every cell of (pair, layer) (of `sides` only, when given); `output_dir` is the pair's
    folder, each cell writes into `output_dir/<cell name>/`."""
    jobs = []
    for cell in cells(pair, layer, settings, other_pairs):
        if sides is not None and cell.side not in sides:
            continue
        for index, states in enumerate(chunks(settings)):
            jobs.append(RolloutJob(cell=cell, tasks=tasks, init_states=states, chunk=index, vectors_root=vectors_root,
                                   output_dir=output_dir / cell.name))
    return jobs


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
