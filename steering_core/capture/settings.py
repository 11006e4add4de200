"""What a capture computes: its settings, the token rows it keeps, and the inputs it checks before loading a model."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator

from steering_core.capture.shards import ACTION_TOKEN_TYPES, StorageDtype, TokenType
from steering_core.data.dataset import DatasetMeta
from steering_core.pi05 import Pi05Arch, PromptFormat, PromptTokenizer, TokenizedPrompt
from steering_core.pi05.arch import ExpertArch
from steering_core.pi05.checkpoint import (
    Checkpoint,
    check_expert_tensors,
    check_prefix_layout,
    expert_arch_from_checkpoint,
)
from steering_core.pi05.preprocess import LIBERO_IMAGE_KEYS
from steering_core.pi05.robot_side import RobotSide
from steering_core.pi05.spec import ModelSpec
from steering_core.storage.schema import StrictModel

STATE_KEY = "state"  # the dataset feature the discrete-state prompt reads
CAMERA_DTYPES = ("image", "video")
N_CAMERAS = 3  # pi0.5's camera slots: base, left wrist, right wrist (absent in LIBERO, mask False)


class CaptureSettings(StrictModel):
    """What to capture and how; the seed's `save_residuals.py` flags plus the new ones."""

    model: ModelSpec  # the checkpoint, tokenizer and how they are read (prompt format, horizon, statistics, arch)
    layers: tuple[int, ...] = (12,)  # the seed's SAE layer; decision/adarms: action expert layers
    token_type: TokenType = "instructions"
    # decision / adarms only: the full sampler runs per frame from noise drawn by a generator seeded
    # with (noise_seed, the frame's global index), so re-capturing gives the same rows
    num_steps: int = Field(10, ge=1, le=1000)  # Euler denoising steps (openpi's default)
    noise_seed: int = Field(0, ge=0, lt=2**31)
    skip_norm_stats: bool = False  # the seed's flag: never read norm stats (the libero format needs none)
    # frames per forward pass; the seed used 128 on a large GPU. 1024 frames of pi0.5's ~800-token prefix at width
    # 2048 are 3.4 GB of bf16 activations per layer, more than any GPU holds with the model's intermediates
    batch_size: int = Field(32, ge=1, le=1024)
    device: str | None = None  # None: the model spec's, else CUDA when available, else CPU
    dtype: str | None = None  # compute dtype; None: the model spec's, else the layout's bfloat16 policy on CUDA
    storage_dtype: StorageDtype = "float32"
    episodes_per_shard: int = Field(1, ge=1, le=100_000)  # 1: adding demos never rewrites a shard
    # DataLoader processes decoding frames; None: one per usable core less one, at most 8 (capture.frames.frame_workers)
    num_workers: int | None = Field(None, ge=0, le=256)
    video_backend: str | None = None  # lerobot's decoder for video datasets (None: lerobot's default)

    @property
    def arch(self) -> Pi05Arch:
        """Return the model's dimensions."""
        return self.model.arch

    @property
    def run_device(self) -> str | None:
        """Return the device the capture runs on: its own setting, else the model spec's (None: auto)."""
        return self.device or self.model.device

    @property
    def run_dtype(self) -> str | None:
        """Return the compute dtype: its own setting, else the model spec's (None: the device's default)."""
        return self.dtype or self.model.dtype

    @field_validator("layers")
    @classmethod
    def _layers_sorted(cls, layers: tuple[int, ...]) -> tuple[int, ...]:
        if not layers:
            raise ValueError("layers is empty; pass at least one decoder layer, e.g. 12")
        return tuple(sorted(set(layers)))


@dataclass(frozen=True)
class CaptureInputs:
    """The checked inputs of a capture: the checkpoint, tokenizer, the checkpoint's robot side (statistics, cameras,
    prompt format, horizon) and whether the prompt reads the state."""

    checkpoint: Checkpoint
    tokenizer: PromptTokenizer
    robot: RobotSide
    expert_arch: ExpertArch | None = None  # the action expert's dimensions (decision / adarms captures)

    @property
    def model_file(self) -> Path:
        return self.checkpoint.model_file

    @property
    def reads_state(self) -> bool:
        """Return whether the prompt carries the state (the discrete-state format)."""
        return self.robot.prompt_format is PromptFormat.DISCRETE_STATE


def select_tokens(prompt: TokenizedPrompt, token_type: str) -> np.ndarray:
    """Return the language indices (n,) int64 a token type keeps from one tokenised prompt.

    `instructions`: the task's own tokens; `prompt`: every valid token (BOS, scaffolding, state);
    `last`: the last valid token. The action token types (decision, adarms) keep no prompt token.
    """
    if token_type in ACTION_TOKEN_TYPES:
        return np.zeros(0, dtype=np.int64)
    if token_type == "instructions":
        return np.arange(*prompt.instruction, dtype=np.int64)
    if token_type == "prompt":
        return np.arange(prompt.n_valid, dtype=np.int64)
    if token_type == "last":
        return np.array([prompt.n_valid - 1], dtype=np.int64)
    raise ValueError(f"token_type {token_type!r} unknown; expected instructions, prompt, last, decision or adarms")


def check_inputs(meta: DatasetMeta, settings: CaptureSettings) -> CaptureInputs:
    """Return the checkpoint, tokenizer and robot side after checking every input once (no model loaded)."""
    inputs = check_model_inputs(settings)
    discrete = inputs.reads_state
    problems = []
    features = meta.info["features"]
    needed = [*LIBERO_IMAGE_KEYS, *([STATE_KEY] if discrete else [])]
    for name in needed:
        found = features.get(name, {}).get("dtype")
        wanted = CAMERA_DTYPES if name in LIBERO_IMAGE_KEYS else None
        if name not in features or (wanted and found not in wanted):
            problems.append(
                f"{meta.root}: feature `{name}` is {'missing' if name not in features else repr(found)}, "
                f"expected {'a camera (image or video)' if wanted else 'present'}; the dataset has "
                f"{sorted(features)} (convert LIBERO with `latent-steering convert`)"
            )
    if problems:
        raise ValueError("\n".join(problems))
    return inputs


def check_model_inputs(settings: CaptureSettings) -> CaptureInputs:
    """Return the checked checkpoint, tokenizer and robot side: everything but the dataset (no model loaded).

    The checkpoint's header must hold every prefix tensor up to the deepest layer with the arch's shapes;
    the action token types need the whole prefix and the action expert, whose layers `layers` then name.
    """
    checkpoint = settings.model.resolve()
    robot = settings.model.robot_side(checkpoint)
    tokenizer = settings.model.prompt_tokenizer(robot)
    discrete = robot.prompt_format is PromptFormat.DISCRETE_STATE
    problems = []
    expert_arch = None
    depth, stream = settings.arch.depth, "language model"
    if settings.token_type in ACTION_TOKEN_TYPES:
        check_prefix_layout(checkpoint, settings.arch, settings.arch.depth - 1)
        expert_arch = expert_arch_from_checkpoint(checkpoint, settings.arch)
        check_expert_tensors(checkpoint, expert_arch)
        depth, stream = expert_arch.depth, f"action expert ({settings.token_type} token type)"
    bad_layers = [layer for layer in settings.layers if not 0 <= layer < depth]
    if bad_layers:
        problems.append(
            f"layers {bad_layers} out of range: the {stream} has {depth} decoder layers (0..{depth - 1})"
        )
    if tokenizer.vocab_size > settings.arch.vocab_size:
        problems.append(
            f"{tokenizer.path}: {tokenizer.vocab_size} pieces, more than the model's vocab_size "
            f"{settings.arch.vocab_size}; pass the tokenizer the checkpoint was trained with"
        )
    if discrete and settings.skip_norm_stats:
        problems.append(
            "the discrete_state prompt needs the quantile-normalised state: drop --skip-norm-stats, "
            "or use the libero prompt format (pi05_libero)"
        )
    if problems:
        raise ValueError("\n".join(problems))
    if expert_arch is None:
        check_prefix_layout(checkpoint, settings.arch, max(settings.layers))
    if discrete:
        robot.normalization.check_state()  # read now, not at the first frame
    return CaptureInputs(checkpoint, tokenizer, robot, expert_arch)
