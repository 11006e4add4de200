"""Dimensions of pi0.5's prefix model: PaliGemma's Gemma-2B language model and SigLIP So400m/14."""

from __future__ import annotations

import os

from pydantic import PositiveInt, model_validator

from steering_core.storage.schema import StrictModel, read_model


class Pi05Arch(StrictModel):
    """Prefix dimensions; the defaults are the released pi0.5 checkpoints (gemma_2b + SigLIP So400m/14).

    Tests and the demo pass tiny dimensions explicitly (`steering_core.synthetic.pi05.tiny_arch`).
    """

    # Gemma-2B language model (openpi variant "gemma_2b"; its LoRA variant keeps these sizes)
    width: PositiveInt = 2048
    depth: PositiveInt = 18
    mlp_dim: PositiveInt = 16384
    num_heads: PositiveInt = 8
    num_kv_heads: PositiveInt = 1  # multi-query attention: one K/V head shared by all query heads
    head_dim: PositiveInt = 256  # num_heads * head_dim need not equal width (openpi's "dummy": 8 x 16 vs 64)
    vocab_size: PositiveInt = 257152  # Gemma's 256000 + 1024 <locNNNN> + 128 <segNNN> PaliGemma tokens
    # SigLIP So400m/14 vision tower
    vision_width: PositiveInt = 1152
    vision_depth: PositiveInt = 27
    vision_mlp_dim: PositiveInt = 4304  # So400m's shape-optimised MLP size, not a multiple of the width
    vision_heads: PositiveInt = 16  # 16 heads of 72
    patch_size: PositiveInt = 14
    image_size: PositiveInt = 224

    @model_validator(mode="after")
    def _check_divisibility(self) -> Pi05Arch:
        problems = []
        if self.num_heads % self.num_kv_heads:
            problems.append(f"num_heads {self.num_heads} is not a multiple of num_kv_heads {self.num_kv_heads}")
        if self.vision_width % self.vision_heads:
            problems.append(f"vision_width {self.vision_width} is not a multiple of vision_heads {self.vision_heads}")
        if self.image_size % self.patch_size:
            problems.append(f"image_size {self.image_size} is not a multiple of patch_size {self.patch_size}")
        if self.head_dim % 2:
            problems.append(f"head_dim {self.head_dim} is odd; rotary embeddings rotate pairs of dimensions")
        if problems:
            raise ValueError("; ".join(problems))
        return self

    @property
    def grid_size(self) -> int:
        """Return the number of patches along each side of an image (224 / 14 = 16)."""
        return self.image_size // self.patch_size

    @property
    def tokens_per_image(self) -> int:
        """Return the number of image tokens per camera (16 x 16 = 256)."""
        return self.grid_size**2

    @property
    def vision_head_dim(self) -> int:
        """Return the width of one SigLIP attention head (1152 / 16 = 72)."""
        return self.vision_width // self.vision_heads

    def prefix_length(self, n_images: int, n_tokens: int) -> int:
        """Return the prefix length for `n_images` cameras and `n_tokens` language slots (3, 200 -> 968)."""
        return n_images * self.tokens_per_image + n_tokens


class ExpertArch(StrictModel):
    """Action expert dimensions; the defaults are openpi's gemma_300m, pi0.5's expert (spec 10.1).

    Depth, heads, KV heads and head_dim must equal the language model's: the expert's attention reads the
    language model's per-layer keys and values (`check_pairs_with`).
    """

    width: PositiveInt = 1024
    depth: PositiveInt = 18
    mlp_dim: PositiveInt = 4096
    num_heads: PositiveInt = 8
    num_kv_heads: PositiveInt = 1
    head_dim: PositiveInt = 256
    action_dim: PositiveInt = 32  # pi0.5 pads actions (and state) to 32

    def check_pairs_with(self, arch: Pi05Arch) -> None:
        """Raise unless this expert can attend to the KV cache of a language model of `arch`."""
        mismatched = [
            f"{name} {getattr(self, name)} (language model: {getattr(arch, name)})"
            for name in ("depth", "num_heads", "num_kv_heads", "head_dim")
            if getattr(self, name) != getattr(arch, name)
        ]
        if mismatched:
            raise ValueError(
                "action expert does not pair with the language model layer by layer: " + ", ".join(mismatched)
            )


def read_arch(path: str | os.PathLike | None) -> Pi05Arch:
    """Return the dimensions in the JSON file `path` (an `--arch-file`), or the released checkpoints' when None."""
    return Pi05Arch() if path is None else read_model(path, Pi05Arch, what="Pi05Arch file (pi0.5 dimensions)")
