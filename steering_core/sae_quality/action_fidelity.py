"""How much of π0.5's behaviour survives an SAE: actions with a layer's instruction-token residuals replaced.

For each held-out frame and one fixed noise draw, the policy runs unchanged (a), with the layer's residuals
at the instruction tokens replaced by an SAE's reconstruction (a_recon), and with them zeroed (a_zero).
Δ_recon = mean over frames of ‖a_recon − a‖, Δ_zero likewise (robot actions over the horizon, each dimension
in units of its std from the checkpoint's norm stats), and recovered = 1 − Δ_recon / Δ_zero: 1 when the
reconstruction changes nothing, 0 when it changes the actions as much as deleting the residuals does
(the policy's own "loss recovered").
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import numpy as np
import torch

from steering_core.evaluate.frames import EvalFrame
from steering_core.evaluate.pair import action_scale
from steering_core.evaluate.sweep import Prompts, frame_noise
from steering_core.pi05.steering import Splice
from steering_core.reporting.progress import ProgressCallback
from steering_core.sae.model import Sae

logger = logging.getLogger(__name__)

Reconstruction = Callable[[torch.Tensor], torch.Tensor]  # rows (n, width) float32 -> (n, width)
FrameLoader = Callable[[Sequence[EvalFrame]], dict[str, Any]]  # -> {"images": [...], "image_masks": [...]}


class SplicePolicy(Protocol):
    """What the measurement needs of a policy (`steering_core.pi05.Pi05Policy` provides it)."""

    action_horizon: int
    action_dim: int
    norm_stats: dict[str, Any]

    def sample_actions(self, images: list[torch.Tensor], image_masks: list[torch.Tensor], tokens: torch.Tensor,
                       token_mask: torch.Tensor, noise: torch.Tensor | None = None, num_steps: int = 10,
                       steering: Any = None, generator: Any = None, splice: Splice | None = None) -> torch.Tensor: ...

    def robot_actions(self, actions: torch.Tensor | np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class ActionFidelity:
    """One reconstruction's action change over `frames` frames (action std units)."""

    frames: int
    delta_recon: float          # mean ‖a_recon − a‖
    delta_zero: float           # mean ‖a_zero − a‖ (the same for every reconstruction)
    recovered: float | None     # 1 − delta_recon / delta_zero; None when zeroing changes nothing

    def as_json(self) -> dict[str, Any]:
        return asdict(self)


def sae_reconstruction(sae: Sae) -> Reconstruction:
    """Return the function rows (n, d_in) -> the SAE's reconstruction (n, d_in)."""
    return lambda rows: sae.reconstruct(rows)[0]


def zero_ablation(rows: torch.Tensor) -> torch.Tensor:
    """Return zeros shaped like `rows`: the residuals deleted."""
    return torch.zeros_like(rows)


def action_fidelity(
    policy: SplicePolicy,
    layer: int,
    reconstructions: Mapping[str, Reconstruction],
    frames: Sequence[EvalFrame],
    load: FrameLoader,
    prompts: Prompts,
    *,
    seed: int = 0,
    num_steps: int = 10,
    batch_size: int = 8,
    progress: ProgressCallback | None = None,  # (policy calls done, in total)
) -> dict[str, ActionFidelity]:
    """Return {name: ActionFidelity} of each reconstruction spliced into language-model layer `layer`.

    `load(frames)` returns the frames' cameras and states ({"images", "image_masks", "states"}, CPU, as
    `load_frames`); `prompts.of(side, ...)` gives each frame's prompt under its own side's task, whose
    `instruction_mask` picks the spliced positions. A frame's
    noise is `frame_noise(frame, 0, seed, ...)`: the same for the unchanged, zeroed and reconstructed runs.
    """
    if not frames:
        raise ValueError("action_fidelity: no frames; hold out episodes with frames of the pair's tasks")
    std = action_scale(policy)
    device = getattr(policy, "device", torch.device("cpu"))
    names = list(reconstructions)
    sums, zeroed = dict.fromkeys(names, 0.0), 0.0  # Σ over frames of ‖Δ‖ per reconstruction, and zeroed
    batches = [frames[i : i + batch_size] for i in range(0, len(frames), batch_size)]
    total, done = len(batches) * (2 + len(names)), 0
    for batch in batches:
        loaded = load(batch)
        inputs = {key: [t.to(device) for t in loaded[key]] for key in ("images", "image_masks")}
        states = loaded.get("states")
        rows = [prompts.of(f.side, None if states is None else states[i : i + 1], 1) for i, f in enumerate(batch)]
        tokens, token_mask, instruction_mask = (
            torch.cat([getattr(row, field) for row in rows]).to(device)
            for field in ("tokens", "token_mask", "instruction_mask"))
        noise = torch.stack([frame_noise(f, 0, seed, policy.action_horizon, policy.action_dim) for f in batch])

        def run(replace: Reconstruction | None) -> torch.Tensor:
            nonlocal done
            splice = None if replace is None else Splice(layer, replace, token_mask=instruction_mask)
            actions = policy.sample_actions(inputs["images"], inputs["image_masks"], tokens, token_mask,
                                            noise=noise.to(device), num_steps=num_steps, splice=splice)
            done += 1
            if progress is not None:
                progress(done, total)
            robot = np.asarray(policy.robot_actions(actions.float().cpu()), dtype=np.float64)
            return torch.from_numpy(robot) / std  # (B, H, 7) in std units

        plain = run(None)
        zeroed += float((run(zero_ablation) - plain).flatten(1).norm(dim=1).sum())
        for name, replace in reconstructions.items():
            sums[name] += float((run(replace) - plain).flatten(1).norm(dim=1).sum())
    delta_zero = zeroed / len(frames)
    results = {}
    for name in names:
        delta = sums[name] / len(frames)
        results[name] = ActionFidelity(frames=len(frames), delta_recon=delta, delta_zero=delta_zero,
                                       recovered=1.0 - delta / delta_zero if delta_zero > 0 else None)
        logger.info("layer %d, %s spliced at the instruction tokens: Δ %.4f vs zeroed %.4f over %d frames", layer,
                    name, delta, delta_zero, len(frames))
    return results
