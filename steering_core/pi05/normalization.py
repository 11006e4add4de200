"""The robot side of a checkpoint: the state as its prompt reads it, and the model's actions as robot actions.

openpi's folders carry `assets/<asset_id>/norm_stats.json` and normalise with quantiles (+1e-6, spec 4.4, 10.8);
lerobot's carry processor statistics and normalise each feature type with the mode its processors name, in
float32, as lerobot's `NormalizerProcessorStep` computes it (spec 17.4). Both are read on first use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from steering_core.pi05.layouts import CONFIG_FILE, LEROBOT_POSTPROCESSOR, LEROBOT_PREPROCESSOR
from steering_core.pi05.lerobot_files import FeatureNorm, LerobotFolder
from steering_core.pi05.norm_stats import NormStats, quantile_normalize, quantile_unnormalize, read_norm_stats

ROBOT_ACTION_DIM = 7  # LiberoOutputs keeps the first 7 of the 32 model action dimensions


class OpenpiNormalization:
    """openpi's norm_stats.json: quantile normalisation of `state`, un-normalisation of `actions`, then 7 dims."""

    def __init__(self, path: Path):
        self.source = path
        self._stats: dict[str, NormStats] | None = None

    @property
    def files(self) -> tuple[Path, ...]:
        """Return the files the statistics are read from."""
        return (self.source,)

    @property
    def stats(self) -> dict[str, NormStats]:
        """Return the file's statistics, read on first use."""
        if self._stats is None:
            self._stats = read_norm_stats(self.source)
        return self._stats

    def _entry(self, name: str, what: str) -> NormStats:
        if name not in self.stats:
            raise ValueError(f"{self.source}: no `{name}` entry for {what}; found {sorted(self.stats)}")
        return self.stats[name]

    def check(self) -> None:
        """Raise unless the robot actions can be computed (read the file now, not at the first request)."""
        self._entry("actions", "the robot actions")

    def check_state(self) -> None:
        """Raise unless the state can be normalised for the discrete-state prompt."""
        self._entry("state", "the discrete-state prompt")

    @property
    def state_dim(self) -> int | None:
        """Return the state width the statistics describe, or None without a `state` entry."""
        return len(self.stats["state"].mean) if "state" in self.stats else None

    def normalize_state(self, states: np.ndarray) -> np.ndarray:
        """Return the states (B, D) quantile-normalised (float64), as the discrete-state prompt reads them."""
        return quantile_normalize(states, self._entry("state", "the discrete-state prompt"))

    def action_std(self) -> np.ndarray:
        """Return the std of each robot action dimension (float64), the evaluation's unit."""
        return np.asarray(self._entry("actions", "the actions' unit").std, dtype=np.float64)[:ROBOT_ACTION_DIM]

    def robot_actions(self, actions: np.ndarray) -> np.ndarray:
        """Return (..., 7) float32 robot actions of model actions (..., A) (spec 10.8)."""
        stats = self._entry("actions", "the robot actions")
        return quantile_unnormalize(actions, stats)[..., :ROBOT_ACTION_DIM].astype(np.float32)


class LerobotNormalization:
    """lerobot's processor statistics: the state normalised and the actions un-normalised by their modes."""

    def __init__(self, folder: LerobotFolder):
        self.folder = folder
        self.source = folder.action.source

    @property
    def files(self) -> tuple[Path, ...]:
        """Return the files the statistics and their modes are read from (config.json, both processors)."""
        root = self.folder.folder
        return tuple(dict.fromkeys([root / CONFIG_FILE, root / LEROBOT_PREPROCESSOR, self.folder.state.source,
                                    root / LEROBOT_POSTPROCESSOR, self.folder.action.source]))

    def check(self) -> None:
        """The statistics were checked when the folder was read."""

    def check_state(self) -> None:
        """The statistics were checked when the folder was read."""

    @property
    def state_dim(self) -> int:
        return self.folder.state_dim

    def normalize_state(self, states: np.ndarray) -> np.ndarray:
        """Return the states (B, D) normalised in float32, as lerobot's preprocessor hands them to its prompt step."""
        states = np.asarray(states)
        if states.shape[-1] != self.folder.state_dim:
            raise ValueError(f"state has {states.shape[-1]} dimensions, {self.folder.folder}'s policy reads "
                             f"{self.folder.state_dim} (input_features.observation.state)")
        return _apply(self.folder.state, torch.as_tensor(states, dtype=torch.float32), inverse=False).numpy()

    def action_std(self) -> np.ndarray:
        """Return the std of each robot action dimension (float64), the evaluation's unit."""
        if "std" not in self.folder.action.stats:
            raise ValueError(f"{self.source}: no `action.std`; the evaluation reports actions in units of their std")
        return self.folder.action.stats["std"].astype(np.float64)

    def robot_actions(self, actions: np.ndarray) -> np.ndarray:
        """Return (..., action_dim) float32 robot actions: the model's first `action_dim` dims un-normalised."""
        head = torch.as_tensor(np.asarray(actions)[..., : self.folder.action_dim], dtype=torch.float32)
        return _apply(self.folder.action, head, inverse=True).numpy()


def _apply(norm: FeatureNorm, x: torch.Tensor, *, inverse: bool) -> torch.Tensor:
    """Return x (un)normalised by one feature's mode, with lerobot's formulas and operation order (float32)."""
    if norm.mode == "IDENTITY":
        return x
    low, high = (torch.from_numpy(stat) for stat in norm.pair())
    if norm.mode == "MEAN_STD":  # low, high = mean, std
        return x * high + low if inverse else (x - low) / (high + norm.eps)
    denom = high - low
    denom = torch.where(denom == 0, torch.tensor(norm.eps, dtype=torch.float32), denom)
    if norm.mode == "MIN_MAX":
        return (x + 1) / 2 * denom + low if inverse else 2 * (x - low) / denom - 1
    return (x + 1.0) * denom / 2.0 + low if inverse else 2.0 * (x - low) / denom - 1.0  # QUANTILES, QUANTILE10
