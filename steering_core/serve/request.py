"""One request's contents checked before inference: the observation's LIBERO keys and the `steering` entry.

A steering entry is `{"pair": str, "layer": int, "alpha": number, "direction"?: str, "mode"?: str,
"alpha_units"?: str}`. direction: a method the steer step wrote (`sae`, `mean_difference`, `probe`, ...; the
catalog's) or a random control `random_<k>`; none: the pair's default (`sae`, else `mean_difference`). mode "add"
(default): α times the unit vector scaled by its `alpha_units` is added. mode "clamp": each steered token's
projection on the unit vector is set to m₋ + α·(m₊ − m₋), α the level fraction (0: the negative concept's mean
level, 1: the positive's); no alpha_units, no random controls.

Every problem raises RequestError naming the key (`observation/image`, `steering[1].alpha`), what was found and
what was expected; the server sends that text back and keeps the connection.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from steering_core.pi05.observation import IMAGE_KEY, PROMPT_KEY, STATE_KEY, WRIST_IMAGE_KEY
from steering_core.pi05.steering import LAST_LM_LAYER, MAX_ALPHA, MODES
from steering_core.serve.catalog import DEFAULT_DIRECTIONS, RANDOM_CONTROLS, SteeringVector, VectorCatalog

STEERING_KEY = "steering"
IMAGE_KEYS = (IMAGE_KEY, WRIST_IMAGE_KEY)
ENTRY_KEYS = ("pair", "layer", "alpha", "direction", "alpha_units", "mode")
# add mode: residual_norm: α·R·v̂ is added, a shift of norm |α|·R (R: the vector's mean residual norm), the unit of
# the evaluation's tables; vector: α·d = α·‖d‖·v̂, the method's vector (before normalising) times α
ALPHA_UNITS = ("residual_norm", "vector")
DEFAULT_ALPHA_UNITS = "residual_norm"
DEFAULT_MODE = "add"
# the policy resizes each image to a square (224 for pi0.5) keeping its aspect: a side shorter than 1/224 of the
# other vanishes; LIBERO's cameras are square, and no camera is 16 times wider than high
MAX_IMAGE_ASPECT = 16
# the tokenizer keeps at most max_token_len (200 for pi0.5) tokens of a prompt; LIBERO's instructions are < 100
# characters, and a longer text only costs tokenizer time
MAX_PROMPT_CHARS = 2000
# each entry adds one vector to the residual stream; a combination of more than a few concepts is not an
# experiment anyone runs, and every entry costs the policy a vector on the device
MAX_STEERING_ENTRIES = 16


class RequestError(ValueError):
    """A request the server refuses; `key` names the offending observation key."""

    def __init__(self, key: str | None, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


@dataclass(frozen=True)
class AppliedSteering:
    """One steering vector of a request. mode "add": `alpha` in `alpha_units` (see ALPHA_UNITS); mode "clamp":
    `alpha` is the level fraction between the vector's `levels` (`alpha_units` None)."""

    vector: SteeringVector
    alpha: float
    alpha_units: str | None = DEFAULT_ALPHA_UNITS
    mode: str = DEFAULT_MODE

    @property
    def vector_alpha(self) -> float | None:
        """Return the factor the unit vector is multiplied by in add mode (None in clamp mode)."""
        if self.mode == "clamp":
            return None
        return self.alpha * (self.vector.norm if self.alpha_units == "vector" else self.vector.mean_residual_norm)

    def describe(self) -> dict:
        """Return the JSON-ready record reported back in the result's `steering` list."""
        v = self.vector
        return {"pair": v.pair, "layer": v.layer, "direction": v.direction, "mode": self.mode, "alpha": self.alpha,
                "alpha_units": self.alpha_units, "vector_alpha": self.vector_alpha,
                "levels": None if v.levels is None else list(v.levels), "norm": v.norm,
                "mean_residual_norm": v.mean_residual_norm}


def check_observation(observation: Any, max_rows: int = 1, max_state_dim: int | None = None) -> int:
    """Return the number of frames of `observation`, or raise RequestError unless it is what openpi's LIBERO
    client sends: one frame, or up to `max_rows` frames along a leading batch dimension (openpi PR #941).

    Expected: the two images uint8 (H, W, 3) (batched: (B, H, W, 3)) with neither side more than MAX_IMAGE_ASPECT
    times the other, the state a finite real-valued (D,) array with 1 <= D <= `max_state_dim` (the policy's
    metadata `state_dim`; None: no bound) ((B, D)), the prompt a str of at most MAX_PROMPT_CHARS characters (B of
    them, as a list or array of str).
    """
    if not isinstance(observation, dict):
        raise RequestError(None, f"the message must be an observation dict, got {type(observation).__name__}")
    image = _required(observation, IMAGE_KEY)
    batched = isinstance(image, np.ndarray) and image.ndim == 4
    rows = image.shape[0] if batched else 1
    if batched and not 1 <= rows <= max_rows:
        raise RequestError(IMAGE_KEY, f"a batch of {rows} frames; this server takes 1 to {max_rows} per request "
                                      "(serve --max-batch)")
    lead = (rows,) if batched else ()
    for key in IMAGE_KEYS:
        image = _required(observation, key)
        shape = image.shape if isinstance(image, np.ndarray) else ()
        if (not isinstance(image, np.ndarray) or image.dtype != np.uint8 or shape[:-3] != lead or image.ndim != len(lead) + 3
                or shape[-1] != 3):
            raise RequestError(key, f"expected a uint8 {'(B, ' if batched else '('}H, W, 3) array"
                                    f"{f' with B = {rows}' if batched else ''}, got {_describe(image)}")
        height, width = shape[-3:-1]
        if min(height, width) == 0 or max(height, width) > MAX_IMAGE_ASPECT * min(height, width):
            raise RequestError(key, f"image of {height}x{width} pixels; expected both sides at least 1 and neither "
                                    f"more than {MAX_IMAGE_ASPECT} times the other")
    state = _required(observation, STATE_KEY)
    if (not isinstance(state, np.ndarray) or state.dtype.kind not in "fiu" or state.ndim != len(lead) + 1
            or state.shape[:-1] != lead or state.shape[-1] == 0):
        raise RequestError(STATE_KEY, f"expected a real-valued {'(B, D)' if batched else '(D,)'} array with D >= 1"
                                      f"{f' and B = {rows}' if batched else ''}, got {_describe(state)}")
    if max_state_dim is not None and state.shape[-1] > max_state_dim:
        raise RequestError(STATE_KEY, f"{state.shape[-1]} dimensions; this policy takes at most {max_state_dim} "
                                      "(the state width its norm stats describe)")
    if not np.isfinite(state).all():
        flat = state.reshape(-1)
        bad = np.flatnonzero(~np.isfinite(flat))
        raise RequestError(STATE_KEY, f"the state is not finite: {flat[bad[0]]} at flat index {bad[0]} "
                                      f"({bad.size} of {state.size} values are NaN or infinite)")
    prompt = _required(observation, PROMPT_KEY)
    prompts = _prompts(prompt, rows) if batched else [prompt]
    if not all(isinstance(text, str) for text in prompts):
        raise RequestError(PROMPT_KEY, f"expected {f'{rows} str (a list or array)' if batched else 'a str'}, got "
                                       f"{_describe(prompt)}")
    longest = max(len(text) for text in prompts)
    if longest > MAX_PROMPT_CHARS:
        raise RequestError(PROMPT_KEY, f"{longest} characters; expected at most {MAX_PROMPT_CHARS}")
    return rows


def _prompts(value: Any, rows: int) -> list[Any]:
    """Return the prompts of a batched observation (a list or 1-D array of `rows` str), or [value] to be refused."""
    if isinstance(value, np.ndarray) and value.ndim == 1 and value.dtype.kind == "U":
        value = value.tolist()
    return list(value) if isinstance(value, list) and len(value) == rows else [value]


@dataclass(frozen=True)
class SteeringLimits:
    """What a server accepts beyond its catalog: |α| up to `max_alpha` (residual_norm units; clamps: level
    fractions), and language-model layers below `lm_depth - 1` (the last layer's output only feeds the final norm,
    which no action reads)."""

    max_alpha: float = MAX_ALPHA
    lm_depth: int | None = None  # None: the model's depth is unknown, every catalog layer passes


def parse_steering(
    value: Any, catalog: VectorCatalog, key: str = STEERING_KEY, limits: SteeringLimits = SteeringLimits()
) -> tuple[AppliedSteering, ...]:
    """Return the vectors a `steering` entry selects: None or [] selects none.

    `value` is one entry (module docstring) or a list of at most MAX_STEERING_ENTRIES, clamping each layer at
    most once; the |alpha| of its add entries together stay within `limits.max_alpha` (their vectors add up).
    """
    if value is None:
        return ()
    if isinstance(value, Mapping):
        return (_parse_entry(value, catalog, key, limits),)
    if isinstance(value, list | tuple):
        if len(value) > MAX_STEERING_ENTRIES:
            raise RequestError(key, f"{len(value)} entries; expected at most {MAX_STEERING_ENTRIES}")
        entries = tuple(_parse_entry(entry, catalog, f"{key}[{i}]", limits) for i, entry in enumerate(value))
        clamped: dict[int, int] = {}  # layer -> the entry clamping it
        for i, entry in enumerate(entries):
            layer = entry.vector.layer
            if entry.mode == "clamp" and clamped.setdefault(layer, i) != i:
                raise RequestError(f"{key}[{i}].layer", f"layer {layer} is clamped by {key}[{clamped[layer]}] too; "
                                                        "a projection takes one level: clamp a layer once")
        total = sum(_bounded_size(entry)[0] for entry in entries if entry.mode == "add")
        if total > limits.max_alpha:  # the vectors add up: the bound is on their sum, not on each
            raise RequestError(key, f"the entries' |alpha| add up to {total:g} (residual_norm units), above the "
                                    f"server's bound {limits.max_alpha:g} on their sum (serve --max-alpha)")
        return entries
    raise RequestError(key, f"expected a dict like {{'pair': 'open_vs_close', 'layer': 12, 'alpha': 4.0}} "
                            f"or a list of them, got {_describe(value)}")


def parse_steering_option(text: str) -> dict:
    """Return the steering entry of a command-line spec `pair:layer:alpha[:direction[:alpha_units|mode]]`: a last
    part naming a mode (`open_vs_close:12:0.5:probe:clamp`) is the entry's mode, any other its alpha_units."""
    parts = text.split(":")
    if len(parts) not in (3, 4, 5):
        raise ValueError(f"steering {text!r} must look like pair:layer:alpha[:direction[:alpha_units|mode]], "
                         "e.g. open_vs_close:12:2.0 or open_vs_close:12:0.5:sae:clamp")
    try:
        entry = {"pair": parts[0], "layer": int(parts[1]), "alpha": float(parts[2])}
    except ValueError:
        raise ValueError(f"steering {text!r}: layer must be an integer and alpha a number") from None
    if len(parts) > 3:
        entry["direction"] = parts[3]
    if len(parts) > 4:
        entry["mode" if parts[4] in MODES else "alpha_units"] = parts[4]
    return entry


def _parse_entry(entry: Any, catalog: VectorCatalog, key: str, limits: SteeringLimits) -> AppliedSteering:
    if not isinstance(entry, Mapping):
        raise RequestError(key, f"expected a dict with pair, layer, alpha (and optional direction, alpha_units, "
                                f"mode), got {_describe(entry)}")
    unknown = sorted(str(k) for k in entry if k not in ENTRY_KEYS)
    if unknown:
        raise RequestError(key, f"unknown key(s) {unknown}; expected {list(ENTRY_KEYS)}")
    pair, layer, alpha = (_required(entry, name, f"{key}.{name}") for name in ENTRY_KEYS[:3])
    direction, mode = entry.get("direction"), entry.get("mode", DEFAULT_MODE)
    if not isinstance(pair, str):
        raise RequestError(f"{key}.pair", f"expected a str, got {_describe(pair)}")
    if isinstance(layer, bool) or not isinstance(layer, int | np.integer):
        raise RequestError(f"{key}.layer", f"expected an integer, got {_describe(layer)}")
    if isinstance(alpha, bool) or not isinstance(alpha, int | float | np.integer | np.floating) \
            or not math.isfinite(alpha):
        raise RequestError(f"{key}.alpha", f"expected a finite number, got {_describe(alpha)}")
    if direction is not None and not isinstance(direction, str):
        raise RequestError(f"{key}.direction", f"expected a str, got {_describe(direction)}")
    if not isinstance(mode, str) or mode not in MODES:
        raise RequestError(f"{key}.mode", f"expected one of {list(MODES)}, got {_describe(mode)}")
    if pair not in catalog.pairs:
        raise RequestError(f"{key}.pair", f"unknown pair {pair!r}; the server has {catalog.pairs}")
    if int(layer) not in catalog.layers(pair):
        raise RequestError(f"{key}.layer", f"pair {pair!r} has no vectors at layer {int(layer)}; "
                                           f"it has layers {catalog.layers(pair)}")
    if limits.lm_depth is not None and int(layer) == limits.lm_depth - 1:
        raise RequestError(f"{key}.layer", f"layer {int(layer)}: {LAST_LM_LAYER}; use a layer below {int(layer)}")
    vector = catalog.get(pair, int(layer), direction)
    offered = catalog.directions(pair, int(layer))
    if vector is None:
        controls = f" and random_0..random_{RANDOM_CONTROLS - 1}" if catalog.default_direction(pair, int(layer)) else ""
        missing = f"no default direction ({' or '.join(DEFAULT_DIRECTIONS)})" if direction is None \
            else f"no {direction!r} direction"
        raise RequestError(f"{key}.direction", f"pair {pair!r} at layer {int(layer)} has {missing}; "
                                               f"it has {offered}{controls}")
    if mode == "clamp":
        applied = _clamp_entry(entry, vector, float(alpha), key, offered)
    else:
        applied = _add_entry(entry, vector, float(alpha), key)
    size, unit = _bounded_size(applied)
    if size > limits.max_alpha:
        raise RequestError(f"{key}.alpha", f"|alpha| is {size:g} in {unit} units, above the server's bound "
                                           f"{limits.max_alpha:g} (serve --max-alpha)")
    return applied


def _clamp_entry(entry: Mapping, vector: SteeringVector, alpha: float, key: str, offered: list[str]) -> AppliedSteering:
    """Return a clamp entry; RequestError for alpha_units given, or a vector without two distinct levels."""
    if "alpha_units" in entry:
        raise RequestError(f"{key}.alpha_units", "mode 'clamp' takes alpha as the level fraction (0: the negative "
                                                 "concept's mean level, 1: the positive's), in no units; drop it")
    if vector.levels is None:
        raise RequestError(f"{key}.mode", f"{vector.direction!r} is a random control, with no concept levels to "
                                          f"clamp to; use mode 'add', or clamp one of {offered}")
    if vector.levels[0] == vector.levels[1]:
        raise RequestError(f"{key}.mode", f"{vector.path} has equal levels m- = m+ = {vector.levels[0]:g}: the "
                                          "concepts do not differ along it; use mode 'add'")
    return AppliedSteering(vector, alpha, None, "clamp")


def _add_entry(entry: Mapping, vector: SteeringVector, alpha: float, key: str) -> AppliedSteering:
    """Return an add entry; RequestError for unknown alpha_units, or residual_norm units without a recorded R."""
    units = entry.get("alpha_units", DEFAULT_ALPHA_UNITS)
    if units not in ALPHA_UNITS:
        raise RequestError(f"{key}.alpha_units", f"expected one of {list(ALPHA_UNITS)}, got {_describe(units)}")
    if units == "residual_norm" and vector.mean_residual_norm is None:
        raise RequestError(f"{key}.alpha_units", f"{vector.path} has no recorded mean_residual_norm (concept "
                                                 "statistics older than the record; re-run the steer step), so alpha "
                                                 "cannot be in residual_norm units; send \"alpha_units\": \"vector\"")
    return AppliedSteering(vector, alpha, units)


def _bounded_size(applied: AppliedSteering) -> tuple[float, str]:
    """Return |α| in level fractions (clamp), else in residual_norm units (vector units for a vector without a
    recorded R), and that unit."""
    vector = applied.vector
    if applied.mode == "clamp":
        return abs(applied.alpha), "level-fraction"
    if applied.alpha_units == "vector" and vector.mean_residual_norm is not None:
        return abs(applied.alpha) * vector.norm / vector.mean_residual_norm, "residual_norm"
    return abs(applied.alpha), applied.alpha_units


def _required(mapping: Mapping, name: str, key: str | None = None) -> Any:
    if name not in mapping:
        present = sorted(str(k) for k in mapping)
        raise RequestError(key or name, f"missing; the request has {present}")
    return mapping[name]


def _describe(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"{value.dtype} array of shape {value.shape}"
    text = repr(value)
    return f"{type(value).__name__} {text[:60] + '...' if len(text) > 60 else text}"
