"""pi0.5: architecture, lazy checkpoint loading, the prefix forward, the whole policy with steering,
prompts and images.

`Pi05Prefix`, `Pi05Policy` and `Steering` (which import torch models and transformers) are loaded on first
access, so data-loading workers that only tokenize or preprocess stay light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from steering_core.pi05.arch import ExpertArch, Pi05Arch
from steering_core.pi05.norm_stats import (
    NormStats,
    discretize_state,
    quantile_normalize,
    quantile_unnormalize,
    read_norm_stats,
)
from steering_core.pi05.preprocess import libero_camera_slots
from steering_core.pi05.tokenizer import PromptFormat, PromptTokenizer, TokenizedPrompt

if TYPE_CHECKING:
    from steering_core.pi05.model import Pi05Prefix
    from steering_core.pi05.policy import Pi05Policy
    from steering_core.pi05.steering import Steering

_LAZY = {
    "Pi05Prefix": "steering_core.pi05.model",
    "Pi05Policy": "steering_core.pi05.policy",
    "Steering": "steering_core.pi05.steering",
}

__all__ = [
    "ExpertArch",
    "NormStats",
    "Pi05Arch",
    "Pi05Policy",
    "Pi05Prefix",
    "PromptFormat",
    "PromptTokenizer",
    "TokenizedPrompt",
    "discretize_state",
    "libero_camera_slots",
    "quantile_normalize",
    "quantile_unnormalize",
    "read_norm_stats",
    "Steering",
]


def __getattr__(name: str) -> Any:
    """Import the model classes on first use (PEP 562)."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
