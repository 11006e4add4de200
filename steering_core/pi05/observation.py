"""openpi's LIBERO observation dict -> checked camera slots, prompts and states (what `Pi05Policy.infer` reads)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from steering_core.pi05.preprocess import Cameras

IMAGE_KEY = "observation/image"
WRIST_IMAGE_KEY = "observation/wrist_image"
STATE_KEY = "observation/state"
PROMPT_KEY = "prompt"
REQUIRED_KEYS = (IMAGE_KEY, WRIST_IMAGE_KEY, STATE_KEY, PROMPT_KEY)


@dataclass(frozen=True)
class ObservationBatch:
    images: list[torch.Tensor]  # three camera slots (B, 3, size, size) float32 in [-1, 1]
    image_masks: list[torch.Tensor]  # (B,) bool each
    prompts: list[str]
    states: np.ndarray  # (B, D) float64
    batched: bool  # the observation had a leading batch dim

    @classmethod
    def concat(cls, batches: Sequence[ObservationBatch]) -> ObservationBatch:
        """Return the rows of `batches` in order, as one batch (several requests answered by one policy call)."""
        if len({batch.states.shape[1] for batch in batches}) > 1:
            raise ValueError(f"observation: states of widths {sorted({b.states.shape[1] for b in batches})} cannot "
                             "share a batch; expected one state width")
        slots = range(len(batches[0].images))
        return cls([torch.cat([batch.images[s] for batch in batches]) for s in slots],
                   [torch.cat([batch.image_masks[s] for batch in batches]) for s in slots],
                   [prompt for batch in batches for prompt in batch.prompts],
                   np.concatenate([batch.states for batch in batches]), True)


def _frames(name: str, value: Any, problems: list[str]) -> np.ndarray | None:
    """Return uint8 (B, H, W, 3) frames of one camera (uint8, or float in [0, 1] truncated as openpi does)."""
    array = np.asarray(value)
    if array.ndim not in (3, 4) or array.shape[-1] != 3 or not (array.dtype == np.uint8 or array.dtype.kind == "f"):
        problems.append(f"`{name}` is {array.shape} {array.dtype}, expected (H, W, 3) or (B, H, W, 3) uint8")
        return None
    if array.dtype.kind == "f":
        array = (255.0 * array).astype(np.uint8)
    return array if array.ndim == 4 else array[None]


def _channels_first(frames: np.ndarray) -> torch.Tensor:
    """Return uint8 (B, 3, H, W) from (B, H, W, 3)."""
    return torch.from_numpy(np.array(frames, copy=True)).permute(0, 3, 1, 2)  # a copy: inputs may be read-only


def observation_batch(observation: Mapping[str, Any], image_size: int, cameras: Cameras = Cameras()) -> ObservationBatch:
    """Return the model inputs of an openpi LIBERO observation, its two cameras in the checkpoint's slots
    (`cameras`); one ValueError names every bad key."""
    if not isinstance(observation, Mapping):
        raise ValueError(f"observation must be a dict with keys {REQUIRED_KEYS}, found {type(observation).__name__}")
    missing = [key for key in REQUIRED_KEYS if key not in observation]
    if missing:
        raise ValueError(f"observation: missing keys {missing}; expected {list(REQUIRED_KEYS)}, found {sorted(observation)}")
    problems: list[str] = []
    batched = np.asarray(observation[IMAGE_KEY]).ndim == 4
    image = _frames(IMAGE_KEY, observation[IMAGE_KEY], problems)
    wrist = _frames(WRIST_IMAGE_KEY, observation[WRIST_IMAGE_KEY], problems)
    prompt = observation[PROMPT_KEY]
    prompts = [prompt] if isinstance(prompt, str) else [str(p) for p in np.asarray(prompt).reshape(-1)]
    state = np.asarray(observation[STATE_KEY], dtype=np.float64)
    states = state[None] if state.ndim == 1 else state
    batch = image.shape[0] if image is not None else len(prompts)
    if wrist is not None and wrist.shape[0] != batch:
        problems.append(f"`{WRIST_IMAGE_KEY}` has batch {wrist.shape[0]}, `{IMAGE_KEY}` {batch}")
    if states.ndim != 2 or states.shape[0] != batch or not np.isfinite(states).all():
        problems.append(f"`{STATE_KEY}` is {state.shape}, expected (D,) or ({batch}, D) finite numbers")
    if len(prompts) != batch or (not batched and not isinstance(prompt, str)):
        problems.append(f"`{PROMPT_KEY}` gives {len(prompts)} prompts for a batch of {batch}; expected a str per frame")
    if problems:
        raise ValueError("observation: " + "; ".join(problems))
    images, image_masks = cameras.from_uint8(_channels_first(image), _channels_first(wrist), image_size)
    return ObservationBatch(images, image_masks, prompts, states, batched)
