"""The steering vectors a server offers: every direction method the steer step wrote under its output root.

Layout read (steering_core.vectors.directions): the `methods` table of `<root>/layerNN/<pair>/directions.json`
names one `<method>_direction.safetensors` per direction method (`steering_core.vectors.methods.direction_file`:
a unit float32 (width,) vector, its length `norm` before normalising, the concepts' mean levels (m₋, m₊) on it
and the rows' `mean_residual_norm` R). Each method is served under its registered name (`sae`, `mean_difference`,
`sae_top_k`, `probe`, ...; the seed's "residual" is `sae`). A pair folder without a `methods` table (written
before the registry) is refused: re-run steer.

DEFAULT_DIRECTIONS: a request naming no direction gets the pair's "sae" direction at that layer, or its
"mean_difference" where no SAE was used. Controls: "random_<k>" (k = 0..RANDOM_CONTROLS - 1) is a random unit
direction carrying the default direction's norm and R (`random_control`), derived on request rather than stored;
it has no levels, so it steers by adding only.
"""

from __future__ import annotations

import logging
import math
import os
import re
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from steering_core.layout import PAIR_SUMMARY_FILE
from steering_core.storage.fileio import read_json
from steering_core.vectors.methods import METHODS
from steering_core.vectors.methods.direction_file import read_method_direction

logger = logging.getLogger(__name__)

DEFAULT_DIRECTIONS = ("sae", "mean_difference")  # a request without `direction` gets the first the pair has
_LAYER_FOLDER = re.compile(r"layer(\d+)")
RANDOM_CONTROLS = 1000  # random_0 .. random_999: plenty of controls, a bounded set of vectors a client can ask for
_RANDOM = re.compile(r"random_(0|[1-9]\d*)")
# the writer stores unit vectors; the α units (request.AppliedSteering.vector_alpha) rely on it
UNIT_TOLERANCE = 1e-4
RANDOM_DERIVATION = (
    f"random_<k> (k = 0..{RANDOM_CONTROLS - 1}): an isotropic Gaussian unit direction with the norm and "
    "mean_residual_norm of the pair's default direction at that layer (sae, else mean_difference); drawn in float64 "
    "by a CPU torch.Generator seeded with zlib.crc32(b'<pair>/<layer>/random_<k>'), normalised, then rounded to "
    "float32 (steering_core.serve.catalog.random_direction with norm 1). Add mode only (no levels). Not the "
    "evaluation's covariance-shaped random_NN nulls."
)


@dataclass(frozen=True)
class SteeringVector:
    """One servable direction: a unit float32 (width,) `vector`, and where it came from.

    `norm` is the length of the method's vector before normalising (α·norm·vector is α in "vector" units);
    `mean_residual_norm` is R, the mean norm of the rows it was computed from (None: statistics older than the
    record, usable in vector units only); `levels` (m₋, m₊) are the concepts' mean projections on `vector`, the
    clamp mode's levels (None: a random control, add only); `include_decoder_bias`: the SAE's b_dec is part of it.
    """

    pair: str
    layer: int
    direction: str
    vector: torch.Tensor
    norm: float
    path: Path
    direction_space: str
    mean_residual_norm: float | None = None
    include_decoder_bias: bool = False
    levels: tuple[float, float] | None = None

    def describe(self) -> dict:
        """Return the JSON-ready entry a client sees in the server metadata."""
        method = METHODS.get(self.direction)
        return {"pair": self.pair, "layer": self.layer, "direction": self.direction,
                "description": None if method is None else method.description, "norm": self.norm,
                "mean_residual_norm": self.mean_residual_norm,
                "levels": None if self.levels is None else list(self.levels),
                "include_decoder_bias": self.include_decoder_bias, "width": int(self.vector.numel()),
                "direction_space": self.direction_space}


class VectorCatalog:
    """Steering vectors by (pair, layer, direction)."""

    def __init__(self, vectors: list[SteeringVector] | None = None) -> None:
        self._vectors = {(v.pair, v.layer, v.direction): v for v in vectors or []}

    @classmethod
    def scan(cls, root: str | os.PathLike) -> VectorCatalog:
        """Return every servable direction under `root` (the steer step's output root).

        Raises FileNotFoundError for a missing root and ValueError naming the file for an unreadable pair folder.
        """
        root = Path(root)
        if not root.is_dir():
            raise FileNotFoundError(f"steering vectors folder {root} not found; pass the steer step's output root "
                                    f"(holding layerNN/<pair>/ folders) with --vectors")
        vectors = []
        for layer_path in sorted(root.iterdir()):
            match = _LAYER_FOLDER.fullmatch(layer_path.name)
            if match is None or not layer_path.is_dir():
                continue
            for pair_path in sorted(layer_path.iterdir()):
                if (pair_path / PAIR_SUMMARY_FILE).is_file():
                    vectors.extend(_read_pair(pair_path, int(match.group(1))))
        logger.info("%s: %d steering vector(s)", root, len(vectors))
        return cls(vectors)

    def __len__(self) -> int:
        return len(self._vectors)

    def __iter__(self):
        return iter(self._vectors.values())

    def default_direction(self, pair: str, layer: int) -> str | None:
        """Return the direction a request naming none gets (the first of DEFAULT_DIRECTIONS stored), or None."""
        return next((name for name in DEFAULT_DIRECTIONS if (pair, layer, name) in self._vectors), None)

    def get(self, pair: str, layer: int, direction: str | None = None) -> SteeringVector | None:
        """Return the vector (None: the default direction; "random_<k>": the default direction's random control),
        or None when the catalog has no such entry."""
        default = self.default_direction(pair, layer)
        if direction is None:
            return None if default is None else self._vectors[(pair, layer, default)]
        match = _RANDOM.fullmatch(direction)
        if match is None or int(match.group(1)) >= RANDOM_CONTROLS:
            return self._vectors.get((pair, layer, direction))
        return None if default is None else random_control(self._vectors[(pair, layer, default)], int(match.group(1)))

    @property
    def pairs(self) -> list[str]:
        return sorted({pair for pair, _, _ in self._vectors})

    def layers(self, pair: str) -> list[int]:
        """Return the layers holding vectors of `pair`."""
        return sorted({layer for p, layer, _ in self._vectors if p == pair})

    def directions(self, pair: str, layer: int) -> list[str]:
        """Return the direction methods stored for `pair` at `layer`."""
        return sorted(kind for p, at, kind in self._vectors if (p, at) == (pair, layer))

    def describe(self) -> list[dict]:
        """Return the metadata entries, sorted by pair, layer and direction."""
        return [self._vectors[key].describe() for key in sorted(self._vectors)]


def random_direction(pair: str, layer: int, k: int, width: int, norm: float) -> torch.Tensor:
    """Return random control `k` of (pair, layer): a float32 (width,) Gaussian direction of L2 norm `norm`.

    The same on every machine and process: the seed is a CRC-32 of the name and the draw float64 on the CPU,
    where torch draws with scalar code everywhere (its float32 draws take an AVX2 path where there is one).
    """
    generator = torch.Generator().manual_seed(zlib.crc32(f"{pair}/{layer}/random_{k}".encode()))
    direction = torch.randn(width, generator=generator, dtype=torch.float64)
    return (direction * (norm / direction.norm())).float()


def random_control(default: SteeringVector, k: int) -> SteeringVector:
    """Return the "random_<k>" control of a pair's default direction: a random unit vector with its norm, R and
    width, and no levels."""
    vector = random_direction(default.pair, default.layer, k, default.vector.numel(), 1.0)
    return replace(default, direction=f"random_{k}", vector=vector, include_decoder_bias=False, levels=None)


def _read_pair(pair_path: Path, layer: int) -> list[SteeringVector]:
    summary_path = pair_path / PAIR_SUMMARY_FILE
    summary = read_json(summary_path)
    methods = summary.get("methods") if isinstance(summary, dict) else None
    if not isinstance(methods, dict) or not methods:
        raise ValueError(f"{summary_path}: no `methods` table (written before the direction methods existed); "
                         "re-run steer to write the pair's method directions")
    vectors = []
    for name, entry in methods.items():
        file = entry.get("file") if isinstance(entry, dict) else None
        if not isinstance(file, str) or not (pair_path / file).is_file():
            raise ValueError(f"{summary_path}: methods.{name}.file is {file!r}, expected the name of a file in "
                             f"{pair_path}; re-run steer")
        path = pair_path / file
        stored = read_method_direction(path)
        length = float(stored.direction.double().norm())
        if (stored.method, stored.layer) != (name, layer) or not abs(length - 1) <= UNIT_TOLERANCE:
            raise ValueError(f"{path}: method {stored.method!r}, layer {stored.layer}, length {length:.6g}; expected "
                             f"method {name!r} (as listed in {PAIR_SUMMARY_FILE}), layer {layer} and a unit vector; "
                             "re-run steer")
        vectors.append(SteeringVector(
            pair=str(summary.get("pair", pair_path.name)), layer=layer, direction=name, vector=stored.direction,
            norm=stored.norm, path=path, direction_space=str(summary.get("direction_space", "residual")),
            mean_residual_norm=_positive_number(stored.mean_residual_norm, path),
            include_decoder_bias=stored.record.get("include_decoder_bias") is True, levels=stored.levels,
        ))
    return vectors


def _positive_number(value: object, where: Path) -> float | None:
    """Return a recorded mean residual norm (None when absent); raise unless it is a positive finite number."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf:
        raise ValueError(f"{where}: mean_residual_norm is {value!r}, expected a positive finite number")
    return float(value)
