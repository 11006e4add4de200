"""Evaluate one pair at one layer: directions + held-out frames + policy sweep -> dose_response outputs."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from steering_core.data.concept_map import ConceptMap
from steering_core.data.contrast import ContrastManifest
from steering_core.data.split import HoldoutSplit
from steering_core.evaluate.directions import check_width, entry_name, is_null
from steering_core.evaluate.frames import EvalFrame, frame_halves, select_frames
from steering_core.evaluate.metrics import (
    LIBERO_ORIENTATION,
    ROBOT_DIM,
    dose_response_metrics,
    null_band,
    null_comparison,
    state_axis_weights,
)
from steering_core.evaluate.nulls import null_directions
from steering_core.evaluate.plots import layer_label
from steering_core.evaluate.positions import check_positions
from steering_core.evaluate.report import pair_record, write_pair_outputs
from steering_core.evaluate.settings import EvaluateSettings
from steering_core.evaluate.sweep import Prompts, SweepPolicy, run_sweep
from steering_core.pairs import SIDES, toward_sign
from steering_core.reporting.progress import ProgressCallback
from steering_core.storage.fileio import atomic_dir
from steering_core.vectors.slice_rows import read_slice_rows

logger = logging.getLogger(__name__)

IN_SAMPLE_NOTE = ("holdout_fraction is 0: the frames evaluated are the frames the vectors were computed from "
                  "(in-sample evaluation)")


@dataclass(frozen=True)
class PairInputs:
    """What one pair's evaluation reads besides the policy (all from phases 1-3)."""

    name: str
    tasks: tuple[str, str]          # (positive, negative) task texts as the manifest spells them
    manifest: ContrastManifest
    concept_map: ConceptMap         # the map of the whole manifest (held-out episodes included)
    split: HoldoutSplit
    slices: tuple[Path, Path]       # training concept slices (positive, negative) of the steered layer and
                                    # stream: their mean row norm is the α unit


def mean_residual_norm(slice_paths: Sequence[Path]) -> float:
    """Return the mean row norm of concept slices (.safetensors `residuals`, or the .pt beside it)."""
    total, rows = 0.0, 0
    for path in slice_paths:
        residuals = read_slice_rows(path)
        total += float(residuals.double().norm(dim=-1).sum())
        rows += residuals.shape[0]
    if rows == 0 or not total > 0:
        raise ValueError(f"slices {[str(p) for p in slice_paths]} hold no non-zero residual rows")
    return total / rows


def action_scale(policy: SweepPolicy) -> torch.Tensor:
    """Return the (7,) float64 std of each robot action dimension, from the policy's action statistics."""
    where = policy.normalization.source
    std = torch.as_tensor(policy.normalization.action_std(), dtype=torch.float64)[:ROBOT_DIM]
    if std.numel() < ROBOT_DIM or not bool((std > 0).all()):
        raise ValueError(f"{where}: actions.std {std.tolist()} must hold {ROBOT_DIM} positive values "
                         "(the robot action dimensions)")
    return std


def evaluate_pair(
    pair: PairInputs,
    directions: dict[str, torch.Tensor],
    policy: SweepPolicy,
    make_steering: Callable[..., Any],
    load: Callable[[Sequence[EvalFrame]], dict[str, Any]],
    prompts: Prompts,
    *,
    layer: int,
    width: int,
    settings: EvaluateSettings,
    output_dir: Path,
    metadata: dict[str, Any] | None = None,
    progress: ProgressCallback | None = None,
    stream: str = "lm",
    include_decoder_bias: bool = False,
    levels: dict[str, tuple[float, float]] | None = None,
) -> Path:
    """Run the dose-response of every direction in every mode for one pair and write `output_dir` atomically;
    return it.

    `directions` maps a method to a (width,) residual direction of `layer` of `stream` ("lm": the language
    model, steered at the instruction tokens; "expert": the action expert, at every action token), the first
    one the reference whose norm the null directions take (they are built here from `pair.slices`); each is
    evaluated in every mode of `settings.modes` (entries `<method>` and `<method>:clamp`, `directions.entry_name`),
    clamp at the method's `levels` (m₋, m₊);
    `metadata` (the policy's description, input digests) is recorded as is; `include_decoder_bias` marks a
    phase-3 residual direction that carries the SAE's b_dec (recorded, and noted in the layer summary).
    """
    check_width(directions, width, f"pair {pair.name!r}", stream)
    reserved = [name for name in directions if is_null(name) or ":" in name]
    if reserved:
        raise ValueError(f"pair {pair.name!r}: direction names {reserved} are reserved for the null directions "
                         "and the modes")
    positions_note = check_positions(pair.slices, stream)
    clamps = clamp_levels(directions, levels or {}, settings.modes, f"pair {pair.name!r}, {layer_label(layer, stream)}")
    directions = {entry_name(method, mode): vector for method, vector in directions.items() for mode in settings.modes}
    scale = action_scale(policy)
    frames = select_frames(pair.manifest, pair.concept_map, pair.split, pair.tasks, settings.max_frames)
    residual_norm = mean_residual_norm(pair.slices)  # R: the α unit
    reference_norm = float(next(iter(directions.values())).norm())
    nulls, null_note = null_directions(pair.slices, reference_norm, random_count=settings.random_directions,
                                       permutations=settings.permutations, seed=settings.seed)
    directions = directions | nulls
    push = {name: float(v.norm()) / reference_norm for name, v in directions.items() if name.startswith("permuted_")}
    actions = run_sweep(
        policy, make_steering, frames, load, prompts, directions, layer=layer, alphas=settings.alphas,
        mean_residual_norm=residual_norm, noise_seeds=settings.noise_seeds, seed=settings.seed,
        num_steps=settings.num_steps, batch_size=settings.batch_size, entries_per_call=settings.entries_per_call,
        progress=progress, stream=stream, push=push, clamps=clamps,
    )
    axis = pair.manifest.axis
    means = axis.mean_delta_per_task
    sign = 1.0 if means[pair.tasks[0]] >= means[pair.tasks[1]] else -1.0
    contrast = state_axis_weights(axis.index)
    halves, halves_by = frame_halves(frames)
    names = list(directions)
    metrics = dose_response_metrics(
        actions.steered, actions.swap, scale=scale, contrast=sign * contrast,
        toward=torch.tensor([toward_sign(f.side) for f in frames], dtype=torch.float64),
        halves=torch.tensor(halves), episodes=[f.episode_index for f in frames], zero_index=settings.zero_index,
        samples=settings.bootstrap, seed=settings.seed,
    )
    metrics |= null_metrics(metrics, names)
    norms = torch.stack([directions[n].double().norm() / push.get(n, 1.0) for n in names])
    grid = torch.tensor(settings.alphas, dtype=torch.float64)[None]
    vector_scale = torch.where(torch.tensor([n in clamps for n in names])[:, None], grid,  # clamp: α is the level
                               grid * residual_norm / norms[:, None])
    head = {
        "pair": pair.name, "layer": layer, "stream": stream, "positive": pair.tasks[0], "negative": pair.tasks[1],
        "mean_residual_norm": residual_norm, "direction_norms": dict(zip(names, norms.tolist(), strict=True)),
        "action_std": scale.tolist(), "efficacy_units": "action std (the checkpoint's norm stats); *_raw: robot units",
        "contrast_axis": {"state_index": axis.index, "sign": sign, "action_weights": contrast.tolist(),
                          "orientation": list(LIBERO_ORIENTATION)},
        "episodes": {side: len({f.episode_index for f in frames if f.side == side}) for side in SIDES},
        "selection": {"by": halves_by, "halves": [[f.as_json() | {"half": h} for f, h in zip(frames, halves, strict=True)
                                                   if h == half] for half in (0, 1)],
                      "method": "best α chosen on one half, efficacy read on the other, both ways, averaged"},
        "null": {"random": settings.random_directions, "permuted": sum(n.startswith("permuted_") for n in names),
                 "kind": "random: the training rows' within-task covariance; permuted: episode labels shuffled",
                 "note": null_note},
        "split": pair.split.model_dump(mode="json"), "in_sample": pair.split.in_sample,
        "in_sample_note": IN_SAMPLE_NOTE if pair.split.in_sample else None, "note": settings.note,
        "include_decoder_bias": include_decoder_bias,
        "modes": list(settings.modes), "levels": {name: list(value) for name, value in clamps.items()},
        "positions_note": positions_note,
        "settings": settings.model_dump(mode="json", exclude={"device", "compiled"}),
        "frames": [f.as_json() for f in frames], "model": metadata or {},
    }
    record = pair_record(head, names, settings.alphas, metrics, vector_scale)
    tensors = {key: value.float() for key, value in metrics.items()}
    tensors |= {"alphas": torch.tensor(settings.alphas, dtype=torch.float32), "alphas_vector_units": vector_scale.float(),
                "actions": actions.steered.float(), "swap_actions": actions.swap.float(),
                "directions": torch.stack([directions[n].float() for n in names])}
    with atomic_dir(output_dir, overwrite=True) as staging:
        write_pair_outputs(staging, record, tensors)
    logger.info("%s %s layer %d: dose-response of %d directions on %d frames in %s", pair.name, stream, layer,
                len(names), len(frames), output_dir)
    return output_dir


def clamp_levels(directions: dict[str, torch.Tensor], levels: dict[str, tuple[float, float]], modes: tuple[str, ...],
                 where: str) -> dict[str, tuple[float, float]]:
    """Return clamp entry name -> (m₋, m₊) for every method when `modes` holds clamp; ValueError naming `where`
    and evaluate.modes for a method without levels or with equal ones (nothing to clamp between)."""
    if "clamp" not in modes:
        return {}
    problems = []
    for method in directions:
        pair_levels = levels.get(method)
        if pair_levels is None:
            problems.append(f"method {method!r} has no clamp levels")
        elif not pair_levels[0] != pair_levels[1]:
            problems.append(f"method {method!r} has equal levels m₋ = m₊ = {pair_levels[0]:.6g}: the concepts do not "
                            "differ along it")
    if problems:
        raise ValueError(f"{where}, evaluate.modes clamp: " + "; ".join(problems) + "; drop clamp from evaluate.modes")
    return {entry_name(method, "clamp"): levels[method] for method in directions}


def null_metrics(metrics: dict[str, torch.Tensor], names: list[str]) -> dict[str, torch.Tensor]:
    """Return the random null's band per α, z and p per α against it, and the best's z and p against both nulls.

    Against the random null the cross-fitted best is compared with each random direction's own cross-fitted
    best (the same selection). The permuted null is pushed at the tested direction's α in vector units, so
    the best is compared with it at that same α (all frames), where a shuffled, smaller difference pushes less.
    """
    out: dict[str, torch.Tensor] = {}
    for kind in ("random", "permuted"):
        rows = [i for i, n in enumerate(names) if n.startswith(f"{kind}_")]
        if not rows:
            continue
        per_alpha = null_comparison(metrics["efficacy"], rows)
        out[f"p_{kind}"] = per_alpha["p"]
        if kind == "permuted":
            out["best_p_permuted"] = per_alpha["p"].gather(1, metrics["best_alpha_index"][:, None])[:, 0]
        else:
            best = null_comparison(metrics["crossfit"], rows)
            out["best_p_random"] = best["p"]
            out["z"], out["best_z"] = per_alpha["z"], best["z"]
            out |= {f"random_{key}": value for key, value in null_band(metrics["efficacy"], rows).items()}
    return out
