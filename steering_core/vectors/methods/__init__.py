"""Direction methods (`registry`): every module here registers one or more; importing the package registers all."""

from steering_core.vectors.methods import basic, probe, sae_effect, supplied  # noqa: F401  (registration)
from steering_core.vectors.methods.registry import (
    METHODS,
    DirectionMethod,
    MethodNames,
    MethodResult,
    PairData,
    method,
)

__all__ = ["METHODS", "DirectionMethod", "MethodNames", "MethodResult", "PairData", "method"]
