"""The registry of direction methods: how a steering direction is computed from one pair's training data.

A method has a name (the word every phase uses: the file `<name>_direction.safetensors`, the evaluation's
rows, the server's `direction`, `rollout.methods`), what it reads (`needs_sae`, `reads_rows`), and a function of
the pair's `PairData` returning an unnormalised (width,) direction pointing from the negative concept to the
positive one, with a JSON record of how it was chosen. `direction_file.write_method_direction` stores it as a
unit vector with the two concepts' mean projections on it (the clamp mode's levels).

Adding a method: a module in this package whose function is decorated with `register_method`, imported by
`steering_core.vectors.methods`, and its test (docs/development.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import torch
from pydantic import AfterValidator

from steering_core.pairs import SIDES
from steering_core.sae.model import Sae
from steering_core.vectors.concept_stats import ConceptStats
from steering_core.vectors.slice_rows import read_slice_episodes, read_slice_rows


@dataclass(frozen=True)
class SliceRows:
    """The training rows of one concept: (rows, width) residuals and their (rows,) int64 episodes (None: the slice
    records none)."""

    rows: torch.Tensor
    episodes: torch.Tensor | None


@dataclass(frozen=True)
class PairData:
    """What a method may read of one pair at one layer: the concepts' streaming statistics, their training slices
    (read on first use), the SAE (None: residual-space methods only) and the method settings."""

    pair: str
    layer: int
    stats: dict[str, ConceptStats]    # side -> statistics (residual means; latent means with an SAE)
    slices: tuple[Path, Path]         # (positive, negative) training slice files, as the pairs config names them
    sae: Sae | None
    settings: Any                     # SteeringSettings: top_k, probe and sae_effect options, direction_file
    _rows: dict[str, SliceRows] = field(default_factory=dict, compare=False, repr=False)

    def rows(self, side: str) -> SliceRows:
        """Return one side's training rows and episodes (read once, then kept)."""
        if side not in self._rows:
            path = self.slices[SIDES.index(side)]
            self._rows[side] = SliceRows(read_slice_rows(path), read_slice_episodes(path))
        return self._rows[side]

    @property
    def where(self) -> str:
        """Return `pair <name>, layer <L>` for error messages."""
        return f"pair {self.pair!r}, layer {self.layer}"


@dataclass(frozen=True)
class MethodResult:
    """A method's (width,) direction (any positive norm, pointing to the positive concept) and its record."""

    direction: torch.Tensor
    record: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DirectionMethod:
    """A registered method: its name, what it reads, and its function of `PairData`."""

    name: str
    compute: Callable[[PairData], MethodResult]
    description: str
    needs_sae: bool = False
    reads_rows: bool = False
    needs_file: bool = False


METHODS: dict[str, DirectionMethod] = {}


def register_method(name: str, description: str, *, needs_sae: bool = False, reads_rows: bool = False,
                    needs_file: bool = False) -> Callable[[Callable[[PairData], MethodResult]], Callable]:
    """Register the decorated function as the method `name`; refuse a name registered twice."""

    def register(compute: Callable[[PairData], MethodResult]) -> Callable[[PairData], MethodResult]:
        if name in METHODS:
            raise ValueError(f"direction method {name!r} is already registered to {METHODS[name].compute.__qualname__}")
        METHODS[name] = DirectionMethod(name, compute, description, needs_sae, reads_rows, needs_file)
        return compute

    return register


def method(name: str) -> DirectionMethod:
    """Return the registered method `name`; ValueError listing the registered ones otherwise."""
    if name not in METHODS:
        raise ValueError(f"unknown direction method {name!r}; registered: {sorted(METHODS)}")
    return METHODS[name]


def check_method_names(names: tuple[str, ...]) -> tuple[str, ...]:
    """Return `names` (a setting's list of methods); ValueError for an unregistered name, a repeat, or none."""
    unknown = [name for name in names if name not in METHODS]
    if unknown:
        raise ValueError(f"methods {list(names)}: {unknown} not registered; registered: {sorted(METHODS)}")
    if not names or len(set(names)) != len(names):
        raise ValueError(f"methods {list(names)}: give at least one direction method, each once")
    return names


# a settings field of method names (steering.methods, evaluate.methods, rollout.methods), checked as a type so that
# the run config's sections check it too
MethodNames = Annotated[tuple[str, ...], AfterValidator(check_method_names)]
