"""The policy a server serves: anything with `metadata` and `infer(observation, steering) -> dict`, and optionally
`warm_up()`, which the server runs once before it listens.

`SteeredPi05Policy` adapts `Pi05Policy`: each selected vector becomes a `Steering` on the language model's
residual stream at the prompt's instruction tokens (where the steer step measured the concepts), adding to it
(mode "add") or clamping its projection to a level between the concepts' means (mode "clamp").
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
import torch

from steering_core.serve.catalog import SteeringVector, VectorCatalog
from steering_core.serve.request import AppliedSteering


class ServedPolicy(Protocol):
    """What the server needs of a policy. `infer` may run in a worker thread, never two calls at once.

    A policy may also answer several requests in one call with `infer_batch(observations, steerings)` (a list of
    results, one per observation); the server batches requests for such a policy and calls `infer` otherwise.
    """

    @property
    def metadata(self) -> dict[str, Any]:
        """JSON-ready facts about the policy, sent to every client on connect."""

    def infer(self, observation: dict[str, Any], steering: Sequence[AppliedSteering]) -> dict[str, Any]:
        """Return at least `{"actions": np.ndarray (action_horizon, 7)}` for one checked observation."""


class SteeredPi05Policy:
    """A `Pi05Policy` steered at the instruction tokens; `noise_seed` fixes the initial noise of every request.

    With a seed, equal observations give equal actions, so steered and plain requests differ only by the
    steering (paired comparisons); without one, each request draws fresh noise as openpi does.
    """

    def __init__(self, policy: Any, noise_seed: int | None = None) -> None:
        self.policy = policy
        self.noise_seed = noise_seed
        self._vectors: dict[tuple, torch.Tensor] = {}  # (pair, layer, direction) -> the vector on the device

    @property
    def metadata(self) -> dict[str, Any]:
        return {**self.policy.metadata, "noise_seed": self.noise_seed}

    def check_catalog(self, catalog: VectorCatalog) -> None:
        """Raise ValueError listing vectors whose layer or width this model cannot take."""
        arch = self.policy.arch
        problems = [
            f"{v.path}: layer {v.layer}, width {v.vector.numel()}" for v in catalog
            if not 0 <= v.layer < arch.depth or v.vector.numel() != arch.width
        ]
        if problems:
            raise ValueError(f"steering vectors that do not fit this model (layers 0..{arch.depth - 1}, width "
                             f"{arch.width}); use vectors computed from this model's residuals:\n  "
                             + "\n  ".join(problems))

    def noise(self) -> torch.Tensor | None:
        """Return the fixed initial noise (action_horizon, action_dim) float32 of one unbatched observation, drawn
        on the CPU from `noise_seed` (the same on every device), or None for fresh noise."""
        if self.noise_seed is None:
            return None
        generator = torch.Generator().manual_seed(self.noise_seed)
        return torch.randn(self.policy.action_horizon, self.policy.action_dim, generator=generator)

    def steerings(self, prompts: Sequence[str], states: np.ndarray, rows: Sequence[slice],
                  steering: Sequence[Sequence[AppliedSteering]]) -> list:
        """Return the `Steering`s of a batch of requests at the instruction tokens of request r's own rows `rows[r]`
        of `prompts` (the other rows' masks are all False): an add entry's unit vector times its `vector_alpha`, a
        clamp entry's projection set to level fraction `alpha` of its vector's levels."""
        from steering_core.pi05.steering import Steering

        if not any(steering):
            return []
        masks = self.policy.instruction_masks(prompts, states)
        steerings = []
        for where, entries in zip(rows, steering, strict=True):
            mine = torch.zeros_like(masks)
            mine[where] = masks[where]
            for s in entries:
                vector = self._on_device(s.vector)
                if s.mode == "clamp":
                    steerings.append(Steering(layer=s.vector.layer, vector=vector, alpha=s.alpha, token_mask=mine,
                                              mode="clamp", levels=s.vector.levels))
                else:
                    steerings.append(Steering(layer=s.vector.layer, vector=vector, alpha=s.vector_alpha,
                                              token_mask=mine))
        return steerings

    def warm_up(self, max_rows: int = 1) -> None:
        """Compile the policy's denoising step for every row bucket a call of up to `max_rows` rows runs at (the
        server's --max-batch), when it runs compiled."""
        if getattr(self.policy, "compiled", False):
            from steering_core.pi05.denoise import ROW_BUCKETS, row_bucket

            largest = row_bucket(max_rows) or max(ROW_BUCKETS)
            for bucket in (b for b in ROW_BUCKETS if b <= largest):
                self.policy.warm_up(batch=bucket)

    def infer(self, observation: dict[str, Any], steering: Sequence[AppliedSteering]) -> dict[str, Any]:
        return self.infer_batch([observation], [steering])[0]

    def infer_batch(self, observations: Sequence[dict[str, Any]],
                    steering: Sequence[Sequence[AppliedSteering]]) -> list[dict[str, Any]]:
        """Return one result per observation (one frame, or frames along a leading batch dim), each steered by its
        own entries, from one policy call over all their rows, or one per group of requests clamping distinct
        layers (a call takes one clamp per layer).

        Each row keeps its prompt, its steering (masked to its own instruction tokens) and its noise, so its actions
        are those of its request alone, up to float32 rounding (the batch's prompt padding and kernel blocking).
        """
        answered: dict[int, dict[str, Any]] = {}
        for group in clamp_groups(steering):
            results = self._infer_call([observations[i] for i in group], [steering[i] for i in group])
            answered |= dict(zip(group, results, strict=True))
        return [answered[i] for i in range(len(observations))]

    def _infer_call(self, observations: Sequence[dict[str, Any]],
                    steering: Sequence[Sequence[AppliedSteering]]) -> list[dict[str, Any]]:
        """Return one result per observation from one policy call over all their rows."""
        from steering_core.pi05.observation import ObservationBatch, observation_batch

        start = time.perf_counter()
        batches = [observation_batch(observation, self.policy.arch.image_size, self.policy.cameras) for observation in observations]
        sizes = [len(batch.prompts) for batch in batches]
        ends = np.cumsum(sizes).tolist()
        rows = [slice(end - size, end) for size, end in zip(sizes, ends)]
        joined = ObservationBatch.concat(batches)
        noise = self.noise()
        robot = self.policy.infer_rows(joined, self.steerings(joined.prompts, joined.states, rows, steering) or None,
                                       None if noise is None else noise.expand(ends[-1], -1, -1))
        timing = {"infer_ms": (time.perf_counter() - start) * 1000.0, "batch_rows": ends[-1]}
        return [{"actions": robot[where] if batch.batched else robot[where][0], "policy_timing": dict(timing)}
                for batch, where in zip(batches, rows)]

    def _on_device(self, vector: SteeringVector) -> torch.Tensor:
        key = (vector.pair, vector.layer, vector.direction)
        if key not in self._vectors:
            self._vectors[key] = vector.vector.to(self.policy.device)
        return self._vectors[key]


def clamp_groups(steering: Sequence[Sequence[AppliedSteering]]) -> list[list[int]]:
    """Return the requests' indices in groups, in order, such that no two requests of a group clamp one layer:
    each request joins the first group whose clamped layers it does not share."""
    groups: list[tuple[list[int], set[int]]] = []
    for index, entries in enumerate(steering):
        layers = {s.vector.layer for s in entries if s.mode == "clamp"}
        group = next((g for g in groups if not layers & g[1]), None)
        if group is None:
            group = ([], set())
            groups.append(group)
        group[0].append(index)
        group[1].update(layers)
    return [indices for indices, _ in groups]
