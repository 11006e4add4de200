"""lerobot's pi0.5 folder besides the weights: `config.json` (its `PI05Config`) and the processor pipelines
(`policy_preprocessor.json`, `policy_postprocessor.json` and the normalizer statistics they name), checked on read.

Spec 17.2-17.4: the camera features in `input_features` order (present ones first, then `empty_cameras`), the
state and action widths, the chunk size, the tokenizer's length, and per feature type the normalisation mode the
processors apply with their statistics and epsilon.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from steering_core.pi05.layouts import CONFIG_FILE, LEROBOT_POSTPROCESSOR, LEROBOT_PREPROCESSOR
from steering_core.pi05.norm_stats import scale_problem
from steering_core.storage.fileio import read_json
from steering_core.tensor_files import check_safetensors

STATE_FEATURE = "observation.state"
ACTION_FEATURE = "action"
IMAGE_PREFIX = "observation.images."
NORMALIZER_STEPS = {"normalizer_processor": LEROBOT_PREPROCESSOR, "unnormalizer_processor": LEROBOT_POSTPROCESSOR}
TOKENIZER_STEP = "tokenizer_processor"
STATE_PROMPT_STEP = "pi05_prepare_state_tokenizer_processor_step"
MODES = ("IDENTITY", "MEAN_STD", "MIN_MAX", "QUANTILES", "QUANTILE10")
MODE_STATS = {"MEAN_STD": ("mean", "std"), "MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"),
              "QUANTILE10": ("q10", "q90")}


@dataclass(frozen=True)
class FeatureNorm:
    """How lerobot (un)normalises one feature: the mode, its two statistics (float32) and the processor's epsilon."""

    mode: str
    stats: dict[str, np.ndarray]  # every statistic of the feature in the file, e.g. {"mean": ..., "q01": ...}
    eps: float
    source: Path  # the statistics file

    def pair(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the mode's two statistics, e.g. (q01, q99) for QUANTILES, (mean, std) for MEAN_STD."""
        low, high = MODE_STATS[self.mode]
        return self.stats[low], self.stats[high]


@dataclass(frozen=True)
class LerobotFolder:
    """The checked non-weight files of a lerobot pi0.5 folder."""

    folder: Path
    chunk_size: int
    n_action_steps: int
    max_state_dim: int
    max_action_dim: int
    image_resolution: tuple[int, int]
    tokenizer_max_length: int
    cameras: tuple[str, ...]  # input_features' VISUAL keys in order, the empty cameras last
    empty_cameras: int
    state_dim: int
    action_dim: int  # the robot's: output_features.action's width
    state: FeatureNorm
    action: FeatureNorm
    tokenizer_name: str


def read_lerobot_folder(folder: Path, config: dict[str, Any]) -> LerobotFolder:
    """Return the checked `config.json` and processor files of a lerobot pi0.5 folder; one ValueError names the
    file, the field and what was expected."""
    path = folder / CONFIG_FILE
    inputs, outputs = _features(path, config, "input_features"), _features(path, config, "output_features")
    cameras = tuple(key for key, feature in inputs.items() if feature.get("type") == "VISUAL")
    empty = _int(path, config, "empty_cameras", minimum=0)
    # lerobot's validate_features adds the empty cameras after the configured ones (when they are not listed)
    cameras += tuple(f"{IMAGE_PREFIX}empty_camera_{i}" for i in range(empty) if f"{IMAGE_PREFIX}empty_camera_{i}" not in cameras)
    max_state, max_action = _int(path, config, "max_state_dim"), _int(path, config, "max_action_dim")
    state_dim = _width(path, inputs, STATE_FEATURE, "input_features", max_state)
    action_dim = _width(path, outputs, ACTION_FEATURE, "output_features", max_action)
    resolution = config.get("image_resolution")
    if not (isinstance(resolution, list) and len(resolution) == 2 and resolution[0] == resolution[1]
            and all(isinstance(v, int) and v > 0 for v in resolution)):
        raise ValueError(f"{path}: `image_resolution` is {resolution!r}, expected a square [size, size]")
    if not [key for key in cameras if not key.startswith(f"{IMAGE_PREFIX}empty_camera_")]:
        raise ValueError(f"{path}: `input_features` has no VISUAL feature; expected the policy's cameras")
    modes = _modes(path, config)
    pre, post = (_pipeline(folder / name) for name in (LEROBOT_PREPROCESSOR, LEROBOT_POSTPROCESSOR))
    state = _feature_norm(folder, pre, "normalizer_processor", STATE_FEATURE, modes["STATE"], state_dim)
    action = _feature_norm(folder, post, "unnormalizer_processor", ACTION_FEATURE, modes["ACTION"], action_dim)
    tokenizer = _step(folder / LEROBOT_PREPROCESSOR, pre, TOKENIZER_STEP)["config"]
    _step(folder / LEROBOT_PREPROCESSOR, pre, STATE_PROMPT_STEP)  # the prompt carries the discretised state
    length = _int(path, config, "tokenizer_max_length")
    if tokenizer.get("max_length") != length:
        raise ValueError(f"{folder / LEROBOT_PREPROCESSOR}: the tokenizer step's max_length is "
                         f"{tokenizer.get('max_length')!r}, {CONFIG_FILE}'s tokenizer_max_length {length}; expected "
                         "the same length")
    return LerobotFolder(
        folder=folder, chunk_size=_int(path, config, "chunk_size"), n_action_steps=_int(path, config, "n_action_steps"),
        max_state_dim=max_state, max_action_dim=max_action, image_resolution=tuple(resolution),
        tokenizer_max_length=length, cameras=cameras, empty_cameras=empty, state_dim=state_dim,
        action_dim=action_dim, state=state, action=action, tokenizer_name=str(tokenizer.get("tokenizer_name")),
    )


def _int(path: Path, config: dict[str, Any], field: str, minimum: int = 1) -> int:
    value = config.get(field)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{path}: `{field}` is {value!r}, expected an integer of at least {minimum}")
    return value


def _features(path: Path, config: dict[str, Any], field: str) -> dict[str, dict[str, Any]]:
    features = config.get(field)
    if not isinstance(features, dict) or not all(isinstance(v, dict) for v in features.values()):
        raise ValueError(f"{path}: `{field}` is {type(features).__name__}, expected an object of features "
                         "({'type': ..., 'shape': [...]})")
    return features


def _width(path: Path, features: dict[str, dict[str, Any]], key: str, field: str, maximum: int) -> int:
    shape = features.get(key, {}).get("shape")
    if not (isinstance(shape, list) and len(shape) == 1 and isinstance(shape[0], int) and 0 < shape[0] <= maximum):
        raise ValueError(f"{path}: `{field}.{key}.shape` is {shape!r}, expected [width] with 0 < width <= {maximum}")
    return shape[0]


def _modes(path: Path, config: dict[str, Any]) -> dict[str, str]:
    mapping = config.get("normalization_mapping")
    if not isinstance(mapping, dict) or any(mapping.get(t) not in MODES for t in ("STATE", "ACTION")):
        raise ValueError(f"{path}: `normalization_mapping` is {mapping!r}, expected STATE and ACTION modes among "
                         f"{', '.join(MODES)}")
    return mapping


def _pipeline(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found; a lerobot pi0.5 folder holds {LEROBOT_PREPROCESSOR} and "
                                f"{LEROBOT_POSTPROCESSOR} (PI05Policy's processors, saved with save_pretrained)")
    payload = read_json(path)
    steps = payload.get("steps") if isinstance(payload, dict) else None
    if not isinstance(steps, list) or not all(isinstance(step, dict) for step in steps):
        raise ValueError(f"{path}: expected an object with a `steps` list (a lerobot processor pipeline)")
    return steps


def _step(path: Path, steps: list[dict[str, Any]], name: str) -> dict[str, Any]:
    found = [step for step in steps if step.get("registry_name") == name]
    if len(found) != 1 or not isinstance(found[0].get("config", {}), dict):
        raise ValueError(f"{path}: {len(found)} `{name}` steps, expected one (lerobot's pi0.5 processors); found "
                         f"{[step.get('registry_name') for step in steps]}")
    return {"config": {}, **found[0]}


def _feature_norm(folder: Path, steps: list[dict[str, Any]], step_name: str, feature: str, mode: str,
                  width: int) -> FeatureNorm:
    """Return one feature's normalisation from its (un)normalizer step; the mode must be config.json's."""
    path = folder / NORMALIZER_STEPS[step_name]
    step = _step(path, steps, step_name)
    config = step["config"]
    applied = config.get("norm_map", {}).get("STATE" if feature == STATE_FEATURE else "ACTION")
    if applied != mode:
        raise ValueError(f"{path}: the {step_name} step normalises {feature} with {applied!r}, {CONFIG_FILE}'s "
                         f"normalization_mapping says {mode!r}; expected the same mode")
    eps = config.get("eps")
    if isinstance(eps, bool) or not isinstance(eps, int | float) or not 0 <= eps < 1:
        raise ValueError(f"{path}: the {step_name} step's eps is {eps!r}, expected a number in [0, 1)")
    name = step.get("state_file")
    if mode == "IDENTITY" and name is None:
        return FeatureNorm(mode, {}, float(eps), path)
    if not isinstance(name, str) or Path(name).name != name:
        raise ValueError(f"{path}: the {step_name} step's state_file is {name!r}, expected a file name in its folder")
    state_file = folder / name
    if not state_file.is_file():
        raise FileNotFoundError(f"{state_file}: the {step_name} step's statistics file is missing; expected it "
                                f"beside {path.name}")
    return FeatureNorm(mode, _feature_stats(state_file, feature, width, MODE_STATS.get(mode, ())), float(eps),
                       state_file)


def _feature_stats(path: Path, feature: str, width: int, needed: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Return statistic name -> float32 vector of one feature in a processor's safetensors file, each checked
    finite and `width` wide; `needed` must be among them."""
    from safetensors.numpy import load_file

    check_safetensors(path)
    # every per-dimension statistic; `count` (frames seen, shape (1,)) is not one
    stored = {key.removeprefix(f"{feature}."): value for key, value in load_file(str(path)).items()
              if key.startswith(f"{feature}.") and key != f"{feature}.count"}
    if missing := [name for name in needed if name not in stored]:
        raise ValueError(f"{path}: no {', '.join(f'`{feature}.{name}`' for name in missing)}; expected them for "
                         f"its normalisation mode (found {sorted(stored)})")
    for name, vector in stored.items():
        if vector.shape != (width,) or not np.issubdtype(vector.dtype, np.floating) or not np.isfinite(vector).all():
            raise ValueError(f"{path}: `{feature}.{name}` is {vector.shape} {vector.dtype}, expected ({width},) "
                             f"finite floats (the width {CONFIG_FILE}'s features give)")
        if problem := scale_problem(vector, name):
            raise ValueError(f"{path}: `{feature}.{name}` {problem}; re-create the statistics")
    return {name: vector.astype(np.float32) for name, vector in stored.items()}
