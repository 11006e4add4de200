"""Run the policy for every frame, noise seed, direction and α: the raw actions of a dose-response.

Per batch of frames of one task and per noise seed, one `sample_actions_sweep` call takes the
unsteered entry (α = 0, shared by every direction) and one entry per (direction, α ≠ 0), so the
prefix below the steered layer is computed once for all of them; one `sample_actions` call with
the other task's instruction gives the swap reference. No frame runs twice with the same inputs.
Every frame is steered toward the other task: a negative-task frame at +α, a positive-task frame at −α
(d points from the negative task to the positive one), against its own swap (other − own instruction).
Steering adds ±α · R · d / ‖d‖ (R: the layer's mean residual norm), i.e. α · R / ‖d‖ in units of the
direction itself: in the language model (`stream="lm"`) at the instruction tokens of the prefix, in the
action expert (`stream="expert"`) at every action token of every denoising step.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from steering_core.evaluate.frames import EvalFrame
from steering_core.pairs import SIDES, other_side, toward_sign
from steering_core.reporting.progress import ProgressCallback

logger = logging.getLogger(__name__)


class SweepPolicy(Protocol):
    """What the evaluation needs of a policy (`steering_core.pi05.Pi05Policy` provides it)."""

    action_horizon: int
    action_dim: int
    normalization: Any  # the robot side: `action_std()` gives the std the metrics divide by, `source` its file

    def sample_actions(self, images: list[torch.Tensor], image_masks: list[torch.Tensor], tokens: torch.Tensor,
                       token_mask: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = 10,
                       steering: Any = None, generator: Any = None) -> torch.Tensor: ...

    def sample_actions_sweep(self, images: list[torch.Tensor], image_masks: list[torch.Tensor], tokens: torch.Tensor,
                             token_mask: torch.Tensor, steerings: list[Any], noise: torch.Tensor | None = None,
                             num_steps: int = 10) -> torch.Tensor: ...

    def robot_actions(self, actions: torch.Tensor | np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class Prompt:
    """A tokenised prompt per row: tokens (B, T) int64, token_mask (B, T) bool, instruction_mask (B, T) bool."""

    tokens: torch.Tensor
    token_mask: torch.Tensor
    instruction_mask: torch.Tensor

    def to(self, device: torch.device) -> Prompt:
        return Prompt(*(t.to(device) for t in (self.tokens, self.token_mask, self.instruction_mask)))


class Prompts(Protocol):
    """Each side's task prompt for a batch of frames (`of`): the same tokens for every frame, or each frame's own
    where the checkpoint's prompt carries the state (lerobot's pi0.5, openpi's discrete-state format)."""

    def of(self, side: str, states: np.ndarray | None, count: int) -> Prompt:
        """Return the prompt (count, T) of `side`'s task for `count` frames of `states` (count, D), or None."""
        ...


@dataclass(frozen=True)
class TaskPrompts:
    """One tokenised prompt (1, T) per side, shared by every frame: the state stays out of the prompt."""

    prompts: dict[str, Prompt]

    def of(self, side: str, states: np.ndarray | None, count: int) -> Prompt:
        prompt = self.prompts[side]
        return Prompt(*(t.expand(count, -1) for t in (prompt.tokens, prompt.token_mask, prompt.instruction_mask)))


@dataclass
class SweepActions:
    """Robot actions of a dose-response: steered (dirs, alphas, frames, seeds, H, 7) toward the other task,
    swap (frames, seeds, H, 7) = the other task's instruction − the frame's own."""

    steered: torch.Tensor
    swap: torch.Tensor
    own: torch.Tensor  # (frames, seeds, H, 7): unsteered, the frame's own instruction


def frame_noise(frame: EvalFrame, seed: int, base_seed: int, horizon: int, dim: int) -> torch.Tensor:
    """Return the (horizon, dim) float32 noise of one frame and seed, the same for every α and direction."""
    key = hashlib.sha256(f"{base_seed}:{frame.episode_index}:{frame.frame_index}:{seed}".encode()).digest()
    generator = torch.Generator().manual_seed(int.from_bytes(key[:8], "little") & (2**63 - 1))
    return torch.randn(horizon, dim, generator=generator)


def run_sweep(
    policy: SweepPolicy,
    make_steering: Callable[..., Any],
    frames: Sequence[EvalFrame],
    load: Callable[[Sequence[EvalFrame]], dict[str, Any]],
    prompts: Prompts,
    directions: dict[str, torch.Tensor],
    *,
    layer: int,
    alphas: tuple[float, ...],
    mean_residual_norm: float,
    noise_seeds: int,
    seed: int,
    num_steps: int,
    batch_size: int,
    entries_per_call: int,
    progress: ProgressCallback | None = None,  # (policy calls done, in total)
    stream: str = "lm",
    push: dict[str, float] | None = None,
    clamps: dict[str, tuple[float, float]] | None = None,
) -> SweepActions:
    """Return the robot actions of every (direction, α, frame, seed) and the instruction-swap reference.

    `make_steering(layer=, vector=, alpha=, token_mask=)` builds one `Steering` of the language model
    (`make_steering(layer=, vector=, alpha=, stream="expert")` of the action expert); `load(frames)` returns
    {"images", "image_masks"} of all frames (CPU; each batch moves to the policy's device) and their "states" (or
    None); `prompts.of(side, states, count)` gives a batch's prompts under the "positive"/"negative" task. At most
    `entries_per_call` steered entries go into one sweep call.
    A direction is added as α · R · push · d/‖d‖ (R = `mean_residual_norm`; `push` 1 unless given); a direction
    named in `clamps` (name -> (m₋, m₊), its concepts' mean levels) is clamped instead
    (`make_steering(..., mode="clamp", levels=(m_own, m_other))`): each steered token's projection on d/‖d‖ is set to
    m_own + α · (m_other − m_own), the frame's own task's level at α = 0 and the other task's at α = 1.
    """
    names = list(directions)
    push, clamps = push or {}, clamps or {}
    unit = {name: directions[name].float() / directions[name].float().norm() * mean_residual_norm * push.get(name, 1.0)
            for name in names}
    nonzero = [(d, a) for d, name in enumerate(names) for a, alpha in enumerate(alphas) if alpha != 0.0]
    zero = alphas.index(0.0)
    horizon, dim = policy.action_horizon, policy.action_dim
    batches = [(side, [i for i, f in enumerate(frames) if f.side == side][start : start + batch_size])
               for side in SIDES
               for start in range(0, sum(f.side == side for f in frames), batch_size)]
    steered = torch.zeros(len(names), len(alphas), len(frames), noise_seeds, horizon, 7, dtype=torch.float64)
    own = torch.zeros(len(frames), noise_seeds, horizon, 7, dtype=torch.float64)
    other = torch.zeros_like(own)
    chunks = [nonzero[i : i + entries_per_call] for i in range(0, len(nonzero), entries_per_call)] or [[]]
    device = getattr(policy, "device", torch.device("cpu"))
    everything = load(frames)
    states = everything.get("states")
    total, done = len(batches) * noise_seeds * len(chunks), 0
    for side, members in batches:
        batch_frames = [frames[i] for i in members]
        index = torch.tensor(members)
        inputs = {key: [t[index].to(device) for t in everything[key]] for key in ("images", "image_masks")}
        size = len(members)
        batch_states = None if states is None else states[members]
        mine = prompts.of(side, batch_states, size).to(device)
        theirs = prompts.of(other_side(side), batch_states, size).to(device)
        tokens, token_mask = mine.tokens, mine.token_mask
        # where the steering adds: the instruction tokens, or (expert) every action token, which takes no mask
        where = {"stream": "expert"} if stream == "expert" else {"token_mask": mine.instruction_mask}
        toward = toward_sign(side)

        def steering(name: str, alpha: float) -> Any:
            vector = unit[name].to(device)
            if name not in clamps:
                return make_steering(layer=layer, vector=vector, alpha=toward * alpha, **where)
            negative, positive = clamps[name]
            levels = (negative, positive) if side == "negative" else (positive, negative)  # (own, other)
            return make_steering(layer=layer, vector=vector, alpha=alpha, mode="clamp", levels=levels, **where)

        for s in range(noise_seeds):
            noise = torch.stack([frame_noise(f, s, seed, horizon, dim) for f in batch_frames]).to(device)
            for number, chunk in enumerate(chunks):
                # the unsteered entry rides with the first chunk only: it is shared by every direction
                entries = ([None] if number == 0 else []) + [steering(names[d], alphas[a]) for d, a in chunk]
                actions = policy.sample_actions_sweep(inputs["images"], inputs["image_masks"], tokens, token_mask,
                                                      entries, noise=noise, num_steps=num_steps)  # (E, B, H, 32)
                robot = _robot(policy, actions)
                if number == 0:
                    own[index, s] = steered[:, zero, index, s] = robot[0]
                    robot = robot[1:]
                for e, (d, a) in enumerate(chunk):
                    steered[d, a, index, s] = robot[e]
                done += 1
                if progress is not None:
                    progress(done, total)
            swapped = policy.sample_actions(inputs["images"], inputs["image_masks"], theirs.tokens, theirs.token_mask,
                                            noise=noise, num_steps=num_steps)
            other[index, s] = _robot(policy, swapped)
    logger.info("sweep: %d frames x %d seeds x %d entries", len(frames), noise_seeds, 1 + len(nonzero))
    return SweepActions(steered=steered, swap=other - own, own=own)


def _robot(policy: SweepPolicy, actions: torch.Tensor) -> torch.Tensor:
    """Return the policy's robot actions (..., H, 7) of model actions as float64 on the CPU."""
    return torch.from_numpy(np.asarray(policy.robot_actions(actions.float().cpu()), dtype=np.float64))
