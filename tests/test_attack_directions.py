"""The bad-input table, round four, area "directions": a direction must be a direction.

An SAE weight stored as integers or holding no normal float32 value, and normalisation statistics whose scale
cannot be real (beyond `MAX_STAT_MAGNITUDE`, or a negative std): each refused in one line naming the file and
tensor, before anything is written (`helpers_attack`). An SAE whose decoder maps the concepts' difference to zero
(a `residual_direction` of length 0) is refused naming the pair and direction, before any pair folder is written.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from helpers_attack import Attack, Case, World, assert_refused, good, registrar
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.pi05.norm_stats import MAX_STAT_MAGNITUDE, norm_stats_path

CASES: list[Attack] = []
case = registrar(CASES)


def sae_with(world: World, tmp_path: Path, change: Callable[[dict[str, torch.Tensor]], None]) -> Path:
    """Copy the layer-1 SAE under `tmp_path`, apply `change` to its weights; return the weights file."""
    folder = tmp_path / "sae_layer01"
    shutil.copytree(world.sae(1), folder)
    path = folder / "sae_weights.safetensors"
    weights = load_file(path)
    change(weights)
    save_file(weights, path)
    return path


def steer_argv(world: World, tmp_path: Path, sae: Path, *extra: str) -> list:
    argv = [str(arg) for arg in good(world, tmp_path)["steer"]]
    argv[argv.index("--sae") + 1] = str(sae)
    return ["steer", *argv, *extra]


def sae_weights_case(name: str, tensor: str, change: Callable[[torch.Tensor], torch.Tensor], expect: str) -> None:
    @case(f"steer_sae_{tensor}_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        path = sae_with(world, tmp_path, lambda weights: weights.update({tensor: change(weights[tensor])}))
        return Case(steer_argv(world, tmp_path, path.parent), (str(path), f"`{tensor}`", expect))


sae_weights_case("int32", "W_enc", lambda t: (t * 100).to(torch.int32), "torch.int32, expected floating point")
sae_weights_case("int64", "b_dec", lambda t: t.to(torch.int64), "torch.int64, expected floating point")
sae_weights_case("subnormal", "W_dec", lambda t: torch.full_like(t, 1e-40), "all zeros or subnormal")
sae_weights_case("subnormal", "W_enc", lambda t: t.sign() * 1e-39, "all zeros or subnormal")


def norm_stats_case(name: str, feature: str, statistic: str, value: float, expect: str) -> None:
    """`evaluate` with a checkpoint copy whose norm_stats.json `feature.statistic` holds `value` in one dimension."""
    @case(f"evaluate_norm_stats_{feature}_{statistic}_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        checkpoint = tmp_path / "checkpoint"
        shutil.copytree(world.checkpoint, checkpoint)
        path = norm_stats_path(checkpoint)
        stats = json.loads(path.read_text())
        stats["norm_stats"][feature][statistic][2] = value
        path.write_text(json.dumps(stats))
        argv = [str(arg) for arg in good(world, tmp_path)["evaluate"]]
        argv[argv.index("--checkpoint-path") + 1] = str(checkpoint)
        return Case(["evaluate", *argv], (str(path), f"`{feature}.{statistic}`", expect))


norm_stats_case("1e38", "actions", "std", 1e38, f"expected magnitudes up to {MAX_STAT_MAGNITUDE:g}")
norm_stats_case("1e7", "actions", "q99", 1e7, f"expected magnitudes up to {MAX_STAT_MAGNITUDE:g}")
norm_stats_case("minus_1e9", "state", "mean", -1e9, f"expected magnitudes up to {MAX_STAT_MAGNITUDE:g}")
norm_stats_case("negative", "actions", "std", -0.5, "expected a spread of at least 0")


@pytest.mark.parametrize("attack", CASES, ids=lambda f: f.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)


def test_steer_refuses_an_sae_decoding_the_difference_to_zero(attack_world, tmp_path, monkeypatch):
    """A decoder tiny but not zero, on one latent only, which never fires: the decoded difference is exactly 0, and
    nothing is kept: not the pair folder, nor the SAE pass's concept statistics computed first (steer leaves its
    layer folder as it found it)."""
    def change(weights: dict[str, torch.Tensor]) -> None:
        weights["W_enc"][:, 0] = 0.0
        weights["b_enc"][0] = -1.0  # ReLU(-1) = 0: latent 0 is dead, its mean difference is 0
        weights["W_dec"].zero_()
        weights["W_dec"][0] = 1e-30

    monkeypatch.chdir(tmp_path)
    path = sae_with(attack_world, tmp_path, change)
    result = CliRunner().invoke(app, steer_argv(attack_world, tmp_path, path.parent, "--methods", "mean_difference"))
    lines = result.output.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1 and "Traceback" not in result.output, result.output
    for name in ("error: pair 'open_vs_close', layer 1, residual_direction", str(path.parent), "length is 0"):
        assert name in lines[0], (name, lines[0])
    assert not (tmp_path / "steering" / "layer01").exists()
