"""A small fake policy for the evaluation tests: its actions read the instruction residual along a planted direction.

The "residual" of a frame at the steered layer is r = mean(token embeddings of the instruction) + base(frame)
+ α·v (steering at the instruction tokens). Actions = ⟨r, u⟩ · A + β · tanh(⟨r, w_f⟩) · b_f + 0.1 · noise, with u
the planted direction, A a fixed (H, 32) pattern and (w_f, b_f) a per-frame nonlinearity (so efficacy varies a
little between frames). The two instructions' embeddings differ by `gap` · u, so steering with u reproduces the
instruction swap at α = gap / R (R: the residual norm unit): efficacy exactly 1 up to the nonlinearity.
With `stream="expert"` the same residual stands for the action expert's (steered at every action token, no
token mask): the evaluation's expert pathway must build its steerings that way. With `saturate=True` the
actions are tanh(⟨r, u⟩ − midpoint) · A + 0.1 · noise instead: each instruction sits on a plateau, so pushing a
frame past its own instruction changes nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import torch

from steering_core.evaluate.frames import EvalFrame
from steering_core.evaluate.sweep import Prompt, TaskPrompts

HORIZON, ACTION_DIM, T = 4, 32, 6
# robot actions = model actions[:7] * 2 + 0.5; the norm stats' std per robot dimension (the efficacy's unit)
ACTION_STD = np.array([1.0, 1.0, 2.0, 0.5, 0.5, 0.5, 4.0] + [1.0] * (ACTION_DIM - 7))
POSITIVE_IDS, NEGATIVE_IDS = [0, 1, 2, 3, 7, 8], [0, 4, 5, 6, 7, 8]
INSTRUCTION = torch.tensor([[False, True, True, True, False, False]])


@dataclass(frozen=True)
class FakeSteering:
    layer: int
    vector: torch.Tensor
    alpha: float = 1.0
    token_mask: torch.Tensor | None = None
    stream: str = "lm"
    mode: str = "add"
    levels: tuple[float, float] | None = None


class FakePolicy:
    """Implements the sweep contract of Pi05Policy on a linear-plus-small-nonlinearity toy model."""

    action_horizon, action_dim = HORIZON, ACTION_DIM

    def __init__(self, width: int, planted: torch.Tensor, gap: float, *, depth: int = 4, beta: float = 3.0,
                 stream: str = "lm", saturate: bool = False):
        gen = torch.Generator().manual_seed(123)
        self.width, self.depth, self.beta, self.stream, self.saturate = width, depth, beta, stream, saturate
        self.normalization = SimpleNamespace(source="the fake policy's statistics",
                                             action_std=lambda: np.asarray(ACTION_STD, dtype=np.float64))
        self.u = planted.double() / planted.double().norm()
        self.embed = torch.randn(10, width, generator=gen, dtype=torch.float64)
        # the instruction tokens' mean embeddings differ by exactly gap * u
        self.embed[4:7] = self.embed[1:4] - gap * self.u
        self.gap = gap
        self.pattern = torch.randn(HORIZON, ACTION_DIM, generator=gen, dtype=torch.float64)
        self.calls = {"sample_actions": 0, "sweep_entries": 0, "sweep_calls": 0}
        self.seen: set[tuple] = set()

    def _frame_terms(self, images: list[torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        terms = []
        for b in range(images[0].shape[0]):
            key = int(images[0][b, 0, 0, 0])
            gen = torch.Generator().manual_seed(1000 + key)
            base = torch.randn(self.width, generator=gen, dtype=torch.float64)
            w = torch.randn(self.width, generator=gen, dtype=torch.float64) / self.width**0.5
            bias = torch.randn(HORIZON, ACTION_DIM, generator=gen, dtype=torch.float64)
            terms.append((base, w, bias))
        return terms

    def sample_actions(self, images, image_masks, tokens, token_mask, noise=None, num_steps=10, steering=None,
                       generator=None):
        self.calls["sample_actions"] += 1
        return self._actions(images, tokens, noise, steering)

    def sample_actions_sweep(self, images, image_masks, tokens, token_mask, steerings, noise=None, num_steps=10):
        self.calls["sweep_calls"] += 1
        self.calls["sweep_entries"] += len(steerings)
        return torch.stack([self._actions(images, tokens, noise, s) for s in steerings])

    def _actions(self, images, tokens, noise, steering) -> torch.Tensor:
        batch = tokens.shape[0]
        key = (tuple(int(images[0][b, 0, 0, 0]) for b in range(batch)), tuple(tokens[:, 1].tolist()),
               float(noise.sum()), None if steering is None else (steering.alpha, float(steering.vector.sum()),
                                                                  steering.mode, steering.levels))
        assert key not in self.seen, "the same inputs ran twice"
        self.seen.add(key)
        instruction = INSTRUCTION.expand(batch, -1)
        r = torch.stack([self.embed[tokens[b][instruction[b]]].mean(0) for b in range(batch)])
        if steering is not None:
            assert steering.layer < self.depth and steering.stream == self.stream
            if self.stream == "lm":
                assert torch.equal(steering.token_mask, instruction)
            else:
                assert steering.token_mask is None
            if steering.mode == "clamp":  # the mean of per-token clamps is the clamp of the mean (a linear map)
                unit = steering.vector.double() / steering.vector.double().norm()
                start, end = steering.levels
                r = r + ((start + steering.alpha * (end - start)) - r @ unit)[:, None] * unit
            else:
                r = r + steering.alpha * steering.vector.double()
        if self.saturate:  # the two instructions' projections sit at midpoint ± gap / 2: both on a plateau
            midpoint = float(self.embed[1:4].mean(0) @ self.u) - self.gap / 2
            return (torch.tanh((r @ self.u - midpoint) * 6 / self.gap)[:, None, None] * self.pattern
                    + 0.1 * noise.double()).float()
        out = []
        for b, (base, w, bias) in enumerate(self._frame_terms(images)):
            resid = r[b] + base
            out.append((resid @ self.u) * self.pattern + self.beta * torch.tanh(resid @ w) * bias
                       + 0.1 * noise[b].double())
        return torch.stack(out).float()

    def robot_actions(self, actions):
        return np.asarray(actions, dtype=np.float64)[..., :7] * 2.0 + 0.5


def prompts() -> TaskPrompts:
    mask = torch.ones(1, T, dtype=torch.bool)
    return TaskPrompts({"positive": Prompt(torch.tensor([POSITIVE_IDS]), mask, INSTRUCTION),
                        "negative": Prompt(torch.tensor([NEGATIVE_IDS]), mask, INSTRUCTION)})


def load(frames: Sequence[EvalFrame]) -> dict:
    """Images whose first pixel is the frame's global index (the fake policy's frame identity)."""
    image = torch.zeros(len(frames), 3, 2, 2)
    image[:, 0, 0, 0] = torch.tensor([float(f.index) for f in frames])
    masks = [torch.ones(len(frames), dtype=torch.bool)] * 3
    return {"images": [image, image.clone(), image.clone()], "image_masks": masks}
