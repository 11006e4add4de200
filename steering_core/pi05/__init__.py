"""pi0.5's prefix: architecture, lazy checkpoint loading, SigLIP + Gemma forward, prompts and images.

`Pi05Prefix` (which imports transformers) is loaded on first access, so data-loading workers that only
tokenize or preprocess stay light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from steering_core.pi05.arch import Pi05Arch
from steering_core.pi05.norm_stats import (
    NormStats,
    discretize_state,
    quantile_normalize,
    read_norm_stats,
)
from steering_core.pi05.preprocess import libero_camera_slots
from steering_core.pi05.tokenizer import PromptFormat, PromptTokenizer, TokenizedPrompt

if TYPE_CHECKING:
    from steering_core.pi05.model import Pi05Prefix

__all__ = [
    "NormStats",
    "Pi05Arch",
    "Pi05Prefix",
    "PromptFormat",
    "PromptTokenizer",
    "TokenizedPrompt",
    "discretize_state",
    "libero_camera_slots",
    "quantile_normalize",
    "read_norm_stats",
]


def __getattr__(name: str) -> Any:
    """Import `Pi05Prefix` on first use (PEP 562)."""
    if name == "Pi05Prefix":
        from steering_core.pi05.model import Pi05Prefix

        return Pi05Prefix
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
