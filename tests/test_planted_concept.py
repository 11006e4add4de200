"""The pipeline finds a concept that truly exists (`steering_core.synthetic.planted`), and nothing else.

Two one-word tasks whose layer-0 residuals differ by exactly one direction d, with ‖d‖ = R. Through the real
filter -> convert -> manifest -> capture -> split -> slice -> steer -> evaluate path (the CLI steps), the
mean-difference direction must reproduce the instruction swap at α = 1 (efficacy ≈ 1), random directions
must not, and a pairs config with the concepts reversed must be refused.
"""

from __future__ import annotations

import json

import pytest
import torch
from helpers_pipeline import run_cli_steps
from safetensors.torch import load_file
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.config import load_run_config
from steering_core.demo import build_planted
from steering_core.pi05.checkpoint import EMBEDDING_KEY, MODEL_FILE
from steering_core.pi05.tokenizer import PromptTokenizer
from steering_core.storage.fileio import read_json
from steering_core.synthetic.planted import PLANTED_LAYER, PLANTED_NEGATIVE, PLANTED_POSITIVE, instruction_pairs

pytestmark = pytest.mark.slow
PAIR = "planted"


@pytest.fixture(scope="module")
def planted(tmp_path_factory):
    """Run the CLI steps on the demo's planted inputs; return (output folder, run config)."""
    root = tmp_path_factory.mktemp("planted")
    config = load_run_config(build_planted(root))
    out = root / "out"
    run_cli_steps(config, out)
    return out, config


def test_the_mean_difference_is_the_planted_direction(planted):
    out, config = planted
    embedding = load_file(config.model.checkpoint / MODEL_FILE)[EMBEDDING_KEY].double()
    (positive, negative), = instruction_pairs(PromptTokenizer(config.model.tokenizer), PLANTED_POSITIVE,
                                              PLANTED_NEGATIVE)  # one token each
    planted_direction = (embedding[positive] - embedding[negative]) * config.model.arch.width ** 0.5
    pair = out / "latent_steering" / f"layer{PLANTED_LAYER:02d}" / PAIR
    summary = read_json(pair / "directions.json")
    found = load_file(pair / summary["methods"]["mean_difference"]["file"])["direction"]
    torch.testing.assert_close(found.double(), planted_direction / planted_direction.norm(), rtol=0, atol=1e-6)
    assert summary["mean_residual_norm"] == pytest.approx(float(planted_direction.norm()), rel=1e-5)  # ‖d‖ = R


def test_evaluation_finds_the_planted_concept_and_nothing_else(planted):
    """mean_difference at α = 1 reproduces the swap in both modes (added: ‖d‖ = R; clamped: the other task's level),
    above every random direction; no other method is significantly above it, and each is reported with its nulls."""
    out, _ = planted
    record = read_json(out / "steering_eval" / f"layer{PLANTED_LAYER:02d}" / PAIR / "dose_response.json")
    assert min(record["episodes"].values()) >= 2  # selection and report halves are different episodes
    at_one = record["alphas"].index(1.0)
    n_random, n_permuted = len(record["random"]["names"]), len(record["random"]["permuted"])
    assert n_random >= 32
    for name in ("mean_difference", "mean_difference:clamp"):
        planted_entry = record["directions"][name]
        for curve in ("efficacy", "efficacy_positive", "efficacy_negative"):  # both sides reproduce their swap
            assert planted_entry[curve][at_one] == pytest.approx(1.0, abs=0.02), (name, curve)
        best = planted_entry["best"]
        assert best["alpha"] == 1.0 and not best["reversed"]
        assert best["efficacy"] == pytest.approx(1.0, abs=0.02)      # cross-fitted: chosen and read on other halves
        low, high = best["efficacy_ci"]
        assert low > 0.9 and high < 1.1
        assert best["p_random"] == pytest.approx(1 / (n_random + 1)) and best["p_random"] < 0.05
        if n_permuted:  # every relabelling of the episodes mixes the tasks, so none reaches the planted direction
            assert best["p_permuted"] == pytest.approx(1 / (n_permuted + 1))
    # the stored direction is unit: vector units are α R
    assert record["directions"]["mean_difference"]["best"]["alpha_vector"] == pytest.approx(
        record["mean_residual_norm"], rel=1e-4)
    tested = [name for name in record["directions"] if not name.startswith(("random_", "permuted_"))]
    assert {"sae", "sae:clamp", "probe", "probe:clamp"} <= set(tested)
    for name in tested:
        best = record["directions"][name]["best"]
        assert "p_random" in best and "p_random_holm" in best
        if not name.startswith("mean_difference"):  # no closer to the swap than the mean difference (same mode)
            versus = best["vs_reference"]
            assert versus["reference"] == "mean_difference" + name.partition(":")[1] + name.partition(":")[2]
            assert versus["gain_ci"][0] is None or versus["gain_ci"][0] <= 1e-9, name
    randoms = [record["directions"][name]["efficacy"][at_one] for name in record["random"]["names"]]
    assert abs(sum(randoms) / len(randoms)) < 0.2 and max(abs(value) for value in randoms) < 0.75  # near 0


def test_a_reversed_pairs_config_is_refused(planted, tmp_path):
    out, config = planted
    pairs = json.loads((out / f"layer{PLANTED_LAYER}_pairs.json").read_text())
    entry = pairs["pairs"][0]
    reversed_entry = {"name": PAIR, "positive_label": entry["negative_label"], "positive_path": entry["negative_path"],
                      "negative_label": entry["positive_label"], "negative_path": entry["positive_path"]}
    reversed_file = tmp_path / "reversed_pairs.json"
    reversed_file.write_text(json.dumps({"pairs": [reversed_entry]}))
    arch_file = out / "arch.json"
    result = CliRunner().invoke(app, [
        "evaluate", "--pairs-config", str(reversed_file), "--layer", str(PLANTED_LAYER),
        "--data-root", str(out), "--lerobot-root", str(out / "libero_lerobot" / config.dataset.repo_id),
        "--checkpoint-path", str(config.model.checkpoint), "--tokenizer-path", str(config.model.tokenizer),
        "--arch-file", str(arch_file), "--output-root", str(tmp_path / "eval"), "--device", "cpu"])
    assert result.exit_code != 0
    assert "reversed" in result.output.lower() or "positive" in result.output.lower(), result.output
    assert not (tmp_path / "eval").exists()
