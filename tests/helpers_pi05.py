"""Tiny pi0.5 inputs shared by the pi05 test modules: a checkpoint, a tokenizer and a mixed batch."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from steering_core.pi05 import Pi05Arch, PromptTokenizer

PROMPTS = (
    "open the top drawer of the cabinet",
    "put the bowl on the plate",
    "pick up the alphabet soup and place it in the basket",
)


@dataclass
class Batch:
    images: list[torch.Tensor]
    image_masks: list[torch.Tensor]
    tokens: torch.Tensor
    token_mask: torch.Tensor

    def args(self):
        return self.images, self.image_masks, self.tokens, self.token_mask

    def valid(self, arch: Pi05Arch) -> torch.Tensor:
        """Return the (B, S) bool mask of valid prefix positions."""
        per_image = [mask[:, None].expand(-1, arch.tokens_per_image) for mask in self.image_masks]
        return torch.cat([*per_image, self.token_mask], dim=1)

    def row(self, index: int) -> Batch:
        pick = slice(index, index + 1)
        return Batch(
            [image[pick] for image in self.images],
            [mask[pick] for mask in self.image_masks],
            self.tokens[pick],
            self.token_mask[pick],
        )


def make_batch(
    arch: Pi05Arch, tokenizer: PromptTokenizer, prompts=PROMPTS, seed: int = 0, partial: bool = True
) -> Batch:
    """Return a batch with LIBERO's camera pattern (right wrist masked for all rows) and uneven prompts.

    With `partial`, the base camera of the last row and the left wrist of the middle row are masked: a
    camera masked for some rows only must still be computed and hidden from those rows, and a masked
    camera between valid tokens must leave no gap in their position ids.
    """
    generator = torch.Generator().manual_seed(seed)
    batch = len(prompts)
    side = arch.image_size
    images = [torch.rand(batch, 3, side, side, generator=generator) * 2 - 1 for _ in range(3)]
    base, left_wrist = torch.ones(batch, dtype=torch.bool), torch.ones(batch, dtype=torch.bool)
    if partial:
        base[-1] = False
        left_wrist[batch // 2] = False
    masks = [base, left_wrist, torch.zeros(batch, dtype=torch.bool)]
    encoded = [tokenizer.tokenize(prompt) for prompt in prompts]
    tokens = torch.from_numpy(np.stack([p.ids for p in encoded]))
    token_mask = torch.from_numpy(np.stack([p.mask for p in encoded]))
    return Batch(images, masks, tokens, token_mask)


def golden_steering(golden: dict, case: str, prefix_len: int) -> list:
    """Return the Steering list of a golden case (openpi's or lerobot's fixture, README there): forward hooks at fixed
    prefix positions of every row (`prefix_len` columns), or at every action token for the expert case."""
    from steering_core.pi05 import Steering

    steerings, index = [], 0
    while f"steer.{case}.{index}.vector" in golden:
        get = lambda name: golden[f"steer.{case}.{index}.{name}"]  # noqa: E731
        layer, vector, alpha = int(get("layer")), get("vector"), float(get("alpha"))
        if case == "c_expert_layer":
            steerings.append(Steering(layer, vector, alpha, stream="expert"))
        else:
            prefix_mask = torch.zeros(2, prefix_len, dtype=torch.bool)
            prefix_mask[:, get("positions")] = True
            steerings.append(Steering(layer, vector, alpha, prefix_mask=prefix_mask))
        index += 1
    return steerings
