"""The per-layer report: top latents by hand, summary.json/summary.md contents, readable PNG plots."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib.image
import pytest
import torch

from steering_core.synthetic.sae import write_sae_folder
from steering_core.vectors.directions import SteeringSettings, compute_steering
from steering_core.vectors.report import top_latents, write_report

D_IN, D_SAE = 12, 40


def write_pairs(root: Path, n_pairs: int) -> Path:
    """Write 2 * n_pairs concept files and a pairs config using paths relative to it; return the config."""
    pairs = []
    for i in range(n_pairs):
        entry = {"name": f"pair_{i}"}
        for j, side in enumerate(("positive", "negative")):
            gen = torch.Generator().manual_seed(10 * i + j)
            path = root / "slices" / f"concept {i}{side[0]}.pt"
            path.parent.mkdir(parents=True, exist_ok=True)
            torch.save(torch.randn(25, D_IN, generator=gen) + torch.randn(D_IN, generator=gen), path)
            entry |= {f"{side}_label": f"concept {i}{side[0]}", f"{side}_path": f"slices/{path.name}"}
        pairs.append(entry)
    (root / "pairs.json").write_text(json.dumps({"pairs": pairs}))
    return root / "pairs.json"


def run(tmp_path: Path, n_pairs: int, sae: Path | None, top_k: int = 6) -> Path:
    settings = SteeringSettings(
        pairs_config=write_pairs(tmp_path, n_pairs), output_root=tmp_path / "out", sae=str(sae) if sae else None,
        device="cpu", top_k=top_k, paths_relative_to="config",
    )
    return compute_steering(settings)


def test_top_latents_by_hand():
    direction = torch.tensor([0.1, -3.0, 2.0, 0.0, -0.5])
    firing = {"positive": torch.tensor([0.5, 0.1, 0.9, 0.0, 0.2]), "negative": torch.tensor([0.4, 0.8, 0.3, 0.0, 0.6])}
    means = {"positive": torch.tensor([1.0, 0.5, 3.0, 0.0, 0.1]), "negative": torch.tensor([0.9, 3.5, 1.0, 0.0, 0.6])}
    top = top_latents(direction, firing, means, 3, "gemma-2b-it/12-res-jb")
    assert [item["index"] for item in top] == [1, 2, 4]
    assert top[0] == {
        "index": 1, "value": -3.0, "firing_rate_positive": pytest.approx(0.1), "firing_rate_negative": pytest.approx(0.8),
        "mean_positive": 0.5, "mean_negative": 3.5, "neuronpedia": "https://neuronpedia.org/gemma-2b-it/12-res-jb/1",
    }
    assert top_latents(direction, firing, means, 1, None)[0]["neuronpedia"] is None


def test_report_with_sae(tmp_path):
    sae = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, neuronpedia_id="toy/12-res")
    layer_path = run(tmp_path, 3, sae)
    summary = json.loads((layer_path / "summary.json").read_text())
    assert summary["sae_used"] is True and summary["sae"]["neuronpedia_id"] == "toy/12-res"
    assert [pair["pair"] for pair in summary["pairs"]] == ["pair_0", "pair_1", "pair_2"]
    pair = summary["pairs"][1]
    direction = torch.load(layer_path / "pair_1" / "latent_direction.pt", weights_only=True)["latent_direction"]
    expected = torch.argsort(direction.abs(), descending=True)[:6].tolist()
    assert [item["index"] for item in pair["top_latents"]] == expected
    assert pair["top_latents"][0]["value"] == pytest.approx(float(direction[expected[0]]))
    assert pair["counts"] == {"positive": 25, "negative": 25} and pair["fidelity"]["positive"]["fvu"] > 0
    assert set(summary["pairwise"]) == {"pair_0__pair_1", "pair_0__pair_2", "pair_1__pair_2"}
    assert summary["plots"] == {
        "pairwise_cosine": "pairwise_cosine.png",
        **{f"top_latents/pair_{i}": f"top_latents_pair_{i}.png" for i in range(3)},
    }
    markdown = (layer_path / "summary.md").read_text()
    assert f"[{expected[0]}](https://neuronpedia.org/toy/12-res/{expected[0]})" in markdown
    assert "(no b_dec)" in markdown and "![pairwise cosines](pairwise_cosine.png)" in markdown
    assert "| pair_0 vs pair_1 |" in markdown
    poor = [f"{p['pair']} ({side})" for p in summary["pairs"] for side, fid in p["fidelity"].items() if fid["fvu"] > 1]
    assert poor, "a random SAE does not reconstruct random residuals"
    assert f"**FVU > 1 for {', '.join(poor)}: the SAE does not reconstruct these residuals**" in markdown
    assert "| pair | positive (rows) | negative (rows) |" in markdown  # narrow tables: the Prefect UI clips wide ones
    for name in summary["plots"].values():
        image = matplotlib.image.imread(layer_path / name)
        assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 400


def test_report_without_sae_and_a_single_pair(tmp_path):
    layer_path = run(tmp_path, 1, None)
    summary = json.loads((layer_path / "summary.json").read_text())
    assert summary["sae_used"] is False and summary["sae"] is None and summary["plots"] == {}
    assert summary["pairs"][0]["top_latents"] == [] and summary["pairwise"] == {}
    markdown = (layer_path / "summary.md").read_text()
    assert "**No SAE was used**" in markdown and "Pairwise cosines" not in markdown
    assert not list(layer_path.glob("*.png"))


def test_report_reruns_on_existing_outputs(tmp_path):
    sae = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE)
    layer_path = run(tmp_path, 2, sae, top_k=3)
    write_report(layer_path, top_k=8)
    summary = json.loads((layer_path / "summary.json").read_text())
    assert len(summary["pairs"][0]["top_latents"]) == 8
    assert summary["pairs"][0]["top_latents"][0]["neuronpedia"] is None  # this SAE has no Neuronpedia id
