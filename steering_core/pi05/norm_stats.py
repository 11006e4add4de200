"""openpi's `norm_stats.json`: reading it, quantile-normalising a state and discretising it (spec 4.3-4.4).

Only the discrete-state prompt format needs this: pi05_libero never puts the state in the prompt.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from steering_core.storage.fileio import read_json

NORM_STATS_FILE = "norm_stats.json"
ASSETS_DIR = "assets"
LIBERO_ASSET_ID = "physical-intelligence/libero"  # pi05_libero's data repo id doubles as its asset id
QUANTILE_EPS = 1e-6  # openpi's guard against q99 == q01
# 256 bins over [-1, 1): digitize against the left edges, minus one (spec 4.3)
STATE_BIN_EDGES = np.linspace(-1.0, 1.0, 256 + 1)[:-1]

# A statistic's magnitude beyond which its scale cannot be real: a robot's states and actions are metres, radians,
# gripper widths and actions in [-1, 1] (LIBERO's 8 state and 7 action values stay within a few units); 1e6 is five
# orders beyond them, while a model run in units of 1e38 only rounds.
MAX_STAT_MAGNITUDE = 1e6
_SPREADS = ("std",)  # statistics that are a scale: not negative
_REQUIRED_FIELDS = ("mean", "std")
_QUANTILE_FIELDS = ("q01", "q99")


@dataclass(frozen=True)
class NormStats:
    """Per-dimension statistics of one feature, float64 vectors of equal length (q01/q99 may be absent)."""

    mean: np.ndarray
    std: np.ndarray
    q01: np.ndarray | None
    q99: np.ndarray | None


def norm_stats_path(checkpoint: str | os.PathLike, asset_id: str = LIBERO_ASSET_ID) -> Path:
    """Return `<checkpoint>/assets/<asset_id>/norm_stats.json`, or `checkpoint` itself if it is a JSON file."""
    checkpoint = Path(checkpoint)
    if checkpoint.suffix == ".json":
        return checkpoint
    folder = checkpoint.parent if checkpoint.suffix == ".safetensors" else checkpoint
    return folder / ASSETS_DIR / asset_id / NORM_STATS_FILE


def read_norm_stats(checkpoint: str | os.PathLike, asset_id: str = LIBERO_ASSET_ID) -> dict[str, NormStats]:
    """Return feature name -> NormStats from a norm_stats.json file or a checkpoint's assets folder."""
    path = norm_stats_path(checkpoint, asset_id)
    if not path.is_file():
        hint = ""
        if path != Path(checkpoint):  # derived from a checkpoint: list the asset ids it does have
            assets = path.parents[len(Path(asset_id).parts)]
            found = sorted(str(p.parent.relative_to(assets)) for p in assets.glob(f"**/{NORM_STATS_FILE}"))
            hint = f" (asset ids with norm stats in {assets}: {', '.join(found) or 'none'})"
        raise FileNotFoundError(
            f"{path}: norm stats not found{hint}; pass the asset id the checkpoint was trained with or a "
            "norm_stats.json file, or use the LIBERO prompt format, which needs no state"
        )
    payload = read_json(path)
    entries = payload.get("norm_stats") if isinstance(payload, dict) else None
    if not isinstance(entries, dict):
        raise ValueError(f"{path}: expected an object with a `norm_stats` mapping, found {type(payload).__name__}")
    problems: list[str] = []
    stats = {name: _parse_entry(name, entry, problems) for name, entry in entries.items()}
    if problems:
        raise ValueError(f"{path}: " + "; ".join(problems) + "; re-create it with openpi's compute_norm_stats.py")
    return stats


def _parse_entry(name: str, entry: object, problems: list[str]) -> NormStats:
    """Return one feature's NormStats, appending a message to `problems` for each bad field."""
    fields: dict[str, np.ndarray | None] = {}
    if not isinstance(entry, dict):
        problems.append(f"`{name}` is {type(entry).__name__}, expected an object with mean, std, q01, q99")
        entry = {}
    for field in _REQUIRED_FIELDS + _QUANTILE_FIELDS:
        value = entry.get(field)
        if value is None and field in _QUANTILE_FIELDS:
            fields[field] = None
            continue
        try:
            vector = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            vector = np.empty((0, 0))
        if vector.ndim != 1 or not np.isfinite(vector).all():
            problems.append(f"`{name}.{field}` is {value!r:.60}, expected a list of finite numbers")
        elif problem := scale_problem(vector, field):
            problems.append(f"`{name}.{field}` {problem}")
        fields[field] = vector
    lengths = {field: len(v) for field, v in fields.items() if v is not None and v.ndim == 1}
    if len(set(lengths.values())) > 1:
        problems.append(f"`{name}` fields have different lengths {lengths}")
    return NormStats(**fields)


def scale_problem(vector: np.ndarray, statistic: str) -> str | None:
    """Return what makes a finite normalisation statistic's scale unreal (`MAX_STAT_MAGNITUDE`; a negative `std`),
    else None."""
    largest = float(np.abs(vector).max()) if vector.size else 0.0
    if largest > MAX_STAT_MAGNITUDE:
        return f"holds {largest:g}, expected magnitudes up to {MAX_STAT_MAGNITUDE:g} (a robot's states and actions)"
    if statistic in _SPREADS and (vector < 0).any():
        return f"holds {float(vector.min()):g}, expected a spread of at least 0"
    return None


def quantile_normalize(values: np.ndarray, stats: NormStats) -> np.ndarray:
    """Return (x - q01) / (q99 - q01 + 1e-6) * 2 - 1 as float64, stats truncated to x's length, not clipped.

    `values` is (..., D) with D at most the stats' length (openpi truncates the stats, spec 4.4).
    """
    if stats.q01 is None or stats.q99 is None:
        raise ValueError("norm stats have no q01/q99: pi0.5 normalises with quantiles; re-compute the norm stats")
    values = np.asarray(values, dtype=np.float64)
    dim = values.shape[-1]
    if dim > len(stats.q01):
        raise ValueError(f"state has {dim} dimensions but the norm stats only {len(stats.q01)}")
    q01, q99 = stats.q01[:dim], stats.q99[:dim]
    return (values - q01) / (q99 - q01 + QUANTILE_EPS) * 2.0 - 1.0


def discretize_state(normalized: np.ndarray) -> np.ndarray:
    """Return the 256-bin index of each value as int64: floor((x + 1) * 128), -1 below -1, 255 from 0.9921875."""
    return np.digitize(np.asarray(normalized, dtype=np.float64), STATE_BIN_EDGES).astype(np.int64) - 1


def quantile_unnormalize(values: np.ndarray, stats: NormStats) -> np.ndarray:
    """Return (x + 1) / 2 * (q99 - q01 + 1e-6) + q01 as float64 on x's leading len(q01) dims (spec 10.8).

    `values` is (..., D); dims beyond the stats pass through unchanged (openpi's model actions are 32 wide,
    LIBERO's stats 7). Stats longer than D are an error, as in openpi.
    """
    if stats.q01 is None or stats.q99 is None:
        raise ValueError("norm stats have no q01/q99: pi0.5 un-normalises with quantiles; re-compute the norm stats")
    values = np.asarray(values, dtype=np.float64)
    dim, stats_dim = values.shape[-1], len(stats.q01)
    if stats_dim > dim:
        raise ValueError(f"values have {dim} dimensions but the norm stats {stats_dim}; expected at most {dim}")
    head = (values[..., :stats_dim] + 1.0) / 2.0 * (stats.q99 - stats.q01 + QUANTILE_EPS) + stats.q01
    return np.concatenate([head, values[..., stats_dim:]], axis=-1)
