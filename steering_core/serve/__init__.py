"""A steered pi0.5 policy server speaking openpi's websocket protocol (codec, vector catalog, requests, server)."""

from steering_core.serve.catalog import SteeringVector, VectorCatalog, random_control, random_direction
from steering_core.serve.episodes import EpisodeLog
from steering_core.serve.policy import ServedPolicy, SteeredPi05Policy
from steering_core.serve.request import (
    AppliedSteering,
    RequestError,
    SteeringLimits,
    parse_steering,
    parse_steering_option,
)
from steering_core.serve.server import PolicyServer

__all__ = [
    "AppliedSteering",
    "EpisodeLog",
    "PolicyServer",
    "RequestError",
    "ServedPolicy",
    "SteeredPi05Policy",
    "SteeringLimits",
    "SteeringVector",
    "VectorCatalog",
    "parse_steering",
    "parse_steering_option",
    "random_control",
    "random_direction",
]
