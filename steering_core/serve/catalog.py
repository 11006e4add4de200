"""The steering vectors a server offers: every residual-space direction under the steer step's output root.

Layout read (steering_core.vectors.directions): `<root>/layerNN/<pair>/directions.json` lists the pair's files;
`residual_direction.safetensors` (the SAE-decoded direction, or the mean difference when no SAE was used) and,
with an SAE, `mean_difference_direction.safetensors`. Direction kinds served: "residual" and "mean_difference".
`latent_direction` lives in the SAE's latent space, not the residual stream, so it cannot be added and is not
offered. Vectors are loaded from the safetensors copies (no pickle) as float32 (width,) CPU tensors, with the
pair's `mean_residual_norm` (R, the residual_norm α unit) and `include_decoder_bias` from directions.json.

Controls: "random_<k>" (k = 0..RANDOM_CONTROLS - 1) is a norm-matched random direction of the pair's residual
vector at that layer (`random_control`), derived on request rather than stored.
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
from steering_core.tensor_files import load_safetensors, require_finite
from steering_core.vectors.directions import MEAN_DIFFERENCE_FILE, RESIDUAL_DIRECTION_FILE

logger = logging.getLogger(__name__)

DEFAULT_DIRECTION = "residual"
DIRECTION_FILES = {"residual": RESIDUAL_DIRECTION_FILE, "mean_difference": MEAN_DIFFERENCE_FILE}
_LAYER_FOLDER = re.compile(r"layer(\d+)")
RANDOM_CONTROLS = 1000  # random_0 .. random_999: plenty of controls, a bounded set of vectors a client can ask for
_RANDOM = re.compile(r"random_(0|[1-9]\d*)")
RANDOM_DERIVATION = (
    f"random_<k> (k = 0..{RANDOM_CONTROLS - 1}): an isotropic Gaussian direction scaled to the norm of the pair's "
    "residual vector at that layer, with its mean_residual_norm; drawn in float64 by a CPU torch.Generator seeded "
    "with zlib.crc32(b'<pair>/<layer>/random_<k>'), then rounded to float32 "
    "(steering_core.serve.catalog.random_direction). Not the evaluation's covariance-shaped random_NN nulls."
)


@dataclass(frozen=True)
class SteeringVector:
    """One stored direction: float32 (width,) `vector`, its L2 `norm` (‖d‖), and where it came from.

    `mean_residual_norm` is R, the mean norm of the rows it was computed from (None: phase-3 outputs older than
    the record, usable in vector units only); `include_decoder_bias`: the SAE's b_dec is part of the vector.
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

    def describe(self) -> dict:
        """Return the JSON-ready entry a client sees in the server metadata."""
        return {"pair": self.pair, "layer": self.layer, "direction": self.direction, "norm": self.norm,
                "mean_residual_norm": self.mean_residual_norm, "include_decoder_bias": self.include_decoder_bias,
                "width": int(self.vector.numel()), "direction_space": self.direction_space}


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

    def get(self, pair: str, layer: int, direction: str = DEFAULT_DIRECTION) -> SteeringVector | None:
        """Return the vector (for "random_<k>", the residual vector's random control), or None when the catalog
        has no such entry."""
        match = _RANDOM.fullmatch(direction)
        if match is None or int(match.group(1)) >= RANDOM_CONTROLS:
            return self._vectors.get((pair, layer, direction))
        residual = self._vectors.get((pair, layer, DEFAULT_DIRECTION))
        return None if residual is None else random_control(residual, int(match.group(1)))

    @property
    def pairs(self) -> list[str]:
        return sorted({pair for pair, _, _ in self._vectors})

    def layers(self, pair: str) -> list[int]:
        """Return the layers holding vectors of `pair`."""
        return sorted({layer for p, layer, _ in self._vectors if p == pair})

    def directions(self, pair: str, layer: int) -> list[str]:
        """Return the direction kinds stored for `pair` at `layer`."""
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


def random_control(residual: SteeringVector, k: int) -> SteeringVector:
    """Return the "random_<k>" control of a residual vector: its norm, R and width, a random direction."""
    vector = random_direction(residual.pair, residual.layer, k, residual.vector.numel(), residual.norm)
    return replace(residual, direction=f"random_{k}", vector=vector, norm=float(vector.norm()),
                   include_decoder_bias=False)


def _read_pair(pair_path: Path, layer: int) -> list[SteeringVector]:
    summary_path = pair_path / PAIR_SUMMARY_FILE
    summary = read_json(summary_path)
    files = summary.get("files") if isinstance(summary, dict) else None
    if not isinstance(files, dict):
        raise ValueError(f"{summary_path}: no `files` table; expected the steer step's directions.json")
    vectors = []
    for direction, stem in DIRECTION_FILES.items():
        entry = files.get(stem)
        if entry is None:
            continue
        path = pair_path / entry["safetensors"]
        try:
            vector = load_safetensors(path)[entry["tensor"]]
        except (OSError, KeyError) as err:
            raise ValueError(f"{path}: cannot read tensor {entry.get('tensor')!r} ({err})") from None
        if vector.ndim != 1 or not vector.is_floating_point():
            raise ValueError(f"{path}: direction is {vector.dtype} {tuple(vector.shape)}, "
                             "expected a float (width,) vector")
        require_finite(vector, path, entry["tensor"], "re-run steer to rewrite the pair's directions")
        vector = vector.float()
        vectors.append(SteeringVector(
            pair=summary.get("pair", pair_path.name), layer=layer, direction=direction, vector=vector,
            norm=float(vector.norm()), path=path, direction_space=str(summary.get("direction_space", "residual")),
            mean_residual_norm=_positive_number(summary.get("mean_residual_norm"), summary_path),
            include_decoder_bias=direction == "residual" and summary.get("include_decoder_bias") is True,
        ))
    return vectors


def _positive_number(value: object, where: Path) -> float | None:
    """Return a recorded mean residual norm (None when absent); raise unless it is a positive finite number."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf:
        raise ValueError(f"{where}: mean_residual_norm is {value!r}, expected a positive finite number")
    return float(value)
