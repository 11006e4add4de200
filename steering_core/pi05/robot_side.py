"""What a checkpoint's folder says about everything around the model: the statistics of its robot side, the camera
order and preprocessing, the prompt format, the action horizon and the prompt length (openpi's folder and the
arguments, or lerobot's config.json and processors, which the arguments must agree with)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from steering_core.pi05.arch import Pi05Arch
from steering_core.pi05.layouts import CONFIG_FILE, Checkpoint, LayoutName
from steering_core.pi05.lerobot_files import read_lerobot_folder
from steering_core.pi05.norm_stats import norm_stats_path as default_norm_stats_path
from steering_core.pi05.normalization import LerobotNormalization, OpenpiNormalization
from steering_core.pi05.preprocess import Cameras
from steering_core.pi05.tokenizer import MAX_TOKEN_LEN, PromptFormat

DEFAULT_HORIZON = 10  # pi05_libero's action_horizon, when the checkpoint's config.json does not say

Normalization = OpenpiNormalization | LerobotNormalization


@dataclass(frozen=True)
class RobotSide:
    """What a checkpoint's folder says about everything around the model: statistics, cameras, prompt, horizon."""

    normalization: Normalization
    cameras: Cameras
    prompt_format: PromptFormat
    action_horizon: int
    max_token_len: int


def robot_side(
    checkpoint: Checkpoint, arch: Pi05Arch, prompt_format: PromptFormat | None, norm_stats_path: str | os.PathLike | None,
    asset_id: str, action_horizon: int | None, max_token_len: int | None,
) -> RobotSide:
    """Return the statistics, camera order, prompt format, horizon and prompt length of a checkpoint: an openpi
    folder's (or the arguments'), or a lerobot folder's config.json and processors (which the arguments must agree
    with)."""
    config = checkpoint.config or {}
    if checkpoint.layout.name is LayoutName.OPENPI:
        stats_file = Path(norm_stats_path) if norm_stats_path is not None else default_norm_stats_path(
            checkpoint.folder, asset_id)
        horizon = config.get("action_horizon", DEFAULT_HORIZON) if action_horizon is None else action_horizon
        return RobotSide(OpenpiNormalization(stats_file), Cameras(), PromptFormat(prompt_format or PromptFormat.LIBERO),
                         _horizon(horizon, checkpoint), max_token_len or MAX_TOKEN_LEN)
    folder = read_lerobot_folder(checkpoint.folder, config)
    where = checkpoint.folder / CONFIG_FILE
    problems = []
    if norm_stats_path is not None:
        problems.append(f"a norm stats file ({norm_stats_path}) was given, but lerobot's statistics come from its "
                        "processor files; give none")
    if prompt_format not in (None, PromptFormat.DISCRETE_STATE):
        problems.append(f"prompt format {PromptFormat(prompt_format).value!r} was given, but lerobot's pi0.5 always "
                        "reads the discretised state in its prompt; use discrete_state")
    if folder.image_resolution[0] != arch.image_size:
        problems.append(f"image_resolution {list(folder.image_resolution)}, but the model's image_size is "
                        f"{arch.image_size} (Pi05Arch)")
    if action_horizon is not None and action_horizon != folder.chunk_size:
        problems.append(f"chunk_size {folder.chunk_size}, but an action horizon of {action_horizon} was asked for")
    if max_token_len is not None and max_token_len != folder.tokenizer_max_length:
        problems.append(f"tokenizer_max_length {folder.tokenizer_max_length}, but {max_token_len} was asked for")
    if problems:
        raise ValueError(f"{where}: " + "; ".join(problems))
    return RobotSide(LerobotNormalization(folder), Cameras.of_lerobot(folder.cameras, str(where)),
                     PromptFormat.DISCRETE_STATE, folder.chunk_size, folder.tokenizer_max_length)


def _horizon(horizon: object, checkpoint: Checkpoint) -> int:
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"{checkpoint.folder / CONFIG_FILE}: action horizon {horizon!r} must be a positive integer")
    return horizon
