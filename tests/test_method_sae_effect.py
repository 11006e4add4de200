"""Method `sae_effect`: Cohen's d against a per-latent reference, the episode vetting, its direction, bad input, and
its latent table in the layer report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from steering_core.layout import FEATURE_PAGE_FILE, PAIR_SUMMARY_FILE
from steering_core.sae.fidelity_table import FIDELITY_JSON
from steering_core.sae.formats import SaeConfig
from steering_core.sae.model import StandardSae
from steering_core.synthetic.sae import make_sae_weights, write_sae_folder
from steering_core.vectors.concept_stats import ConceptStats
from steering_core.vectors.directions import SteeringSettings, compute_steering
from steering_core.vectors.methods import METHODS, PairData
from steering_core.vectors.report import write_report

PAIR, LAYER = "open_vs_close", 12


def write_slice(path: Path, rows: torch.Tensor, episodes: list[int] | None) -> Path:
    """Write a concept slice: `residuals` (n, d_in) float32 and, unless None, `episode_index` (n,) int64."""
    tensors = {"residuals": rows.float().contiguous()}
    if episodes is not None:
        tensors["episode_index"] = torch.tensor(episodes, dtype=torch.int64)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file(tensors, path)
    return path


def pair_data(tmp_path: Path, sae: StandardSae, sides: dict[str, tuple[torch.Tensor, list[int] | None]],
              **settings) -> PairData:
    """Return the PairData of two slices written from `sides` (side -> rows, episodes)."""
    paths = tuple(write_slice(tmp_path / f"{side}.safetensors", *sides[side]) for side in ("positive", "negative"))
    stats = {side: ConceptStats(side, path, len(sides[side][0]), sides[side][0].double().mean(0), None, None, None,
                                None, None) for side, path in zip(("positive", "negative"), paths, strict=True)}
    options = SteeringSettings(pairs_config=tmp_path / "pairs.json", layer=LAYER, **settings)
    return PairData(PAIR, LAYER, stats, paths, sae, options)


def reference(sae: StandardSae, sides: dict[str, tuple[torch.Tensor, list[int]]]) -> dict[str, np.ndarray]:
    """Per latent, one at a time with numpy: Cohen's d, mean difference, distinct episodes fired, frequencies."""
    latents = {side: sae.encode(rows).double().numpy() for side, (rows, _) in sides.items()}
    pos, neg = latents["positive"], latents["negative"]
    episodes = np.concatenate([np.asarray(sides[side][1]) for side in ("positive", "negative")])
    both = np.concatenate([pos, neg])
    out = {key: np.zeros(pos.shape[1]) for key in ("d", "diff", "episodes", "freq", "freq_pos", "freq_neg")}
    for j in range(pos.shape[1]):
        a, b = pos[:, j], neg[:, j]
        pooled = np.sqrt(((len(a) - 1) * a.var(ddof=1) + (len(b) - 1) * b.var(ddof=1)) / (len(a) + len(b) - 2))
        out["diff"][j] = a.mean() - b.mean()
        out["d"][j] = out["diff"][j] / pooled if pooled > 0 else 0.0
        out["episodes"][j] = len(set(episodes[both[:, j] > 0].tolist()))
        out["freq"][j] = np.mean(both[:, j] > 0)
        out["freq_pos"][j], out["freq_neg"][j] = np.mean(a > 0), np.mean(b > 0)
    return out


def random_sides(seed: int = 0) -> dict[str, tuple[torch.Tensor, list[int]]]:
    g = torch.Generator().manual_seed(seed)
    rows = {"positive": torch.randn(37, 8, generator=g) + 0.4, "negative": torch.randn(29, 8, generator=g)}
    episodes = {"positive": torch.randint(0, 6, (37,), generator=g).tolist(),
                "negative": torch.randint(4, 9, (29,), generator=g).tolist()}
    return {side: (rows[side], episodes[side]) for side in rows}


def random_sae() -> StandardSae:
    """A random tiny SAE (d_in 8, d_sae 24) whose latents 0..3 never fire."""
    weights = make_sae_weights(8, 24, seed=3)
    weights["b_enc"][:4] = -100.0
    return StandardSae(SaeConfig(d_in=8, d_sae=24, source="tiny"), weights)


def test_cohen_d_and_frequencies_match_a_per_latent_reference_whatever_the_batch_size(tmp_path):
    sae, sides = random_sae(), random_sides()
    expected = reference(sae, sides)
    records = [METHODS["sae_effect"].compute(pair_data(tmp_path / str(size), sae, sides, top_k=24,
                                                       effect_min_episodes=1, batch_size=size)).record
               for size in (5, 512)]
    record, other = records
    assert [item["latent"] for item in record["latents"]] == [item["latent"] for item in other["latents"]]
    assert [item["cohen_d"] for item in record["latents"]] == pytest.approx(
        [item["cohen_d"] for item in other["latents"]], rel=1e-6)  # float32 encoding differs by batch shape
    kept = [j for j in range(24) if expected["freq"][j] > 0 and expected["d"][j] != 0]
    assert len(kept) == 20
    assert [item["latent"] for item in record["latents"]] == sorted(kept, key=lambda j: -abs(expected["d"][j]))
    for item in record["latents"]:
        j = item["latent"]
        assert item["cohen_d"] == pytest.approx(expected["d"][j], rel=1e-6)
        assert item["mean_difference"] == pytest.approx(expected["diff"][j], rel=1e-6)
        assert item["episodes"] == expected["episodes"][j]
        assert (item["frequency"], item["frequency_positive"], item["frequency_negative"]) == pytest.approx(
            (expected["freq"][j], expected["freq_pos"][j], expected["freq_neg"][j]))
    assert record["excluded"]["never_fire"] == 24 - len(kept)
    assert record["training_episodes"] == {side: len(set(sides[side][1])) for side in sides}
    assert record["rows"] == {"positive": 37, "negative": 29} and record["min_episodes"] == 1
    json.dumps(record, allow_nan=False)  # JSON-able as it stands


def test_direction_is_the_hand_sum_of_the_chosen_decoder_rows(tmp_path):
    sae, sides = random_sae(), random_sides(1)
    result = METHODS["sae_effect"].compute(pair_data(tmp_path, sae, sides, top_k=4, effect_min_episodes=2))
    expected = reference(sae, sides)
    chosen = [item["latent"] for item in result.record["latents"]]
    assert len(chosen) == 4
    hand = sum(expected["diff"][j] * sae.W_dec[j].double() for j in chosen)
    torch.testing.assert_close(result.direction, hand.float(), rtol=1e-5, atol=1e-6)
    assert result.direction.dtype == torch.float32 and result.direction.shape == (8,)


def identity_sae(width: int = 5) -> StandardSae:
    """latents = ReLU(rows): every activation is set by hand."""
    weights = {"W_enc": torch.eye(width), "b_enc": torch.zeros(width),
               "W_dec": torch.randn(width, width, generator=torch.Generator().manual_seed(0)), "b_dec": torch.zeros(width)}
    return StandardSae(SaeConfig(d_in=width, d_sae=width, source="identity"), weights)


def vetting_sides() -> dict[str, tuple[torch.Tensor, list[int]]]:
    """Five latents over episodes 0, 1 (positive) and 2, 3 (negative): latent 0 fires only in episode 0 with a
    large effect, 1 and 4 in every episode with smaller ones, 2 never, 3 alike on both sides (zero effect)."""
    g = torch.Generator().manual_seed(2)
    n = 20
    pos, neg = torch.zeros(n, 5), torch.zeros(n, 5)
    pos[:10, 0] = 5 + 0.1 * torch.randn(10, generator=g)        # episode 0 only
    pos[:, 1] = 1.0 + 0.8 * torch.randn(n, generator=g).abs()
    neg[:, 1] = 0.9 + 0.8 * torch.randn(n, generator=g).abs()
    pos[:, 2] = neg[:, 2] = -1.0                                 # ReLU: never fires
    pos[:, 3] = neg[:, 3] = torch.arange(n, dtype=torch.float32) % 4 + 1  # equal means
    pos[::2, 4] = 0.5                                            # fires in episodes 0..3, less on the negative side
    neg[::4, 4] = 0.5
    return {"positive": (pos, [0] * 10 + [1] * 10), "negative": (neg, [2] * 10 + [3] * 10)}


def test_a_latent_of_one_episode_is_skipped_as_memorised_and_chosen_without_vetting(tmp_path):
    sae, sides = identity_sae(), vetting_sides()
    expected = reference(sae, sides)
    assert abs(expected["d"][0]) > 2 * max(abs(expected["d"][1]), abs(expected["d"][4])) > 0
    vetted = METHODS["sae_effect"].compute(pair_data(tmp_path / "vetted", sae, sides, top_k=1))
    assert [item["latent"] for item in vetted.record["latents"]] == [max((1, 4), key=lambda j: abs(expected["d"][j]))]
    assert vetted.record["excluded"] == {"never_fire": 1, "memorised": 1, "zero_effect": 1, "zero_variance": 0}
    assert vetted.record["latents"][0]["episodes"] == 4 and vetted.record["min_episodes"] == 2
    unvetted = METHODS["sae_effect"].compute(pair_data(tmp_path / "all", sae, sides, top_k=2, effect_min_episodes=1))
    assert [item["latent"] for item in unvetted.record["latents"]][0] == 0
    assert unvetted.record["latents"][0]["episodes"] == 1 and unvetted.record["excluded"]["memorised"] == 0


def test_a_latent_without_spread_is_excluded_not_infinite(tmp_path):
    sides = vetting_sides()
    for side, value in (("positive", 2.0), ("negative", 1.0)):
        sides[side][0][:, 3] = value  # constant on each side: pooled variance 0, means differ
    record = METHODS["sae_effect"].compute(pair_data(tmp_path, identity_sae(), sides, top_k=5)).record
    assert 3 not in [item["latent"] for item in record["latents"]]
    assert record["excluded"]["zero_variance"] == 1 and record["excluded"]["zero_effect"] == 0


def test_nothing_surviving_the_vetting_is_one_error_naming_the_pair_layer_and_setting(tmp_path):
    sides = vetting_sides()
    data = pair_data(tmp_path, identity_sae(), sides, effect_min_episodes=5)
    with pytest.raises(ValueError, match=r"pair 'open_vs_close', layer 12: sae_effect: no latent fires in at least 5 "
                                         r"training episodes \(of 4\) with a non-zero effect \(4 memorised, 1 never "
                                         r"fire.*lower steering\.effect_min_episodes"):
        METHODS["sae_effect"].compute(data)


def test_slices_without_episodes_are_refused(tmp_path):
    sides = vetting_sides()
    sides["negative"] = (sides["negative"][0], None)
    data = pair_data(tmp_path, identity_sae(), sides)
    with pytest.raises(ValueError, match=r"pair 'open_vs_close', layer 12: .*negative slice .*negative\.safetensors "
                                         r"has no `episode_index` column; re-slice it with `latent-steering slice`"):
        METHODS["sae_effect"].compute(data)


def test_episodes_not_matching_the_rows_are_refused(tmp_path):
    sides = vetting_sides()
    sides["positive"] = (sides["positive"][0], sides["positive"][1][:-1])
    data = pair_data(tmp_path, identity_sae(), sides)
    with pytest.raises(ValueError, match=r"positive slice .* has 20 rows and 19 episode indices, expected as many"):
        METHODS["sae_effect"].compute(data)

def steered_layer(tmp_path: Path, methods: tuple[str, ...]) -> Path:
    """Run `compute_steering` over one pair of episode-tagged slices through a tiny SAE; return the layer folder."""
    sae = write_sae_folder(tmp_path / "sae", d_in=8, d_sae=24)
    sides = random_sides(4)
    for side, (rows, episodes) in sides.items():
        write_slice(tmp_path / "slices" / f"{side}.safetensors", rows, episodes)
    pairs = {"pairs": [{"name": PAIR, "positive_label": "open", "positive_path": "slices/positive.safetensors",
                        "negative_label": "close", "negative_path": "slices/negative.safetensors"}]}
    (tmp_path / "pairs.json").write_text(json.dumps(pairs))
    return compute_steering(SteeringSettings(pairs_config=tmp_path / "pairs.json", output_root=tmp_path / "out",
                                             layer=LAYER, sae=str(sae), device="cpu", top_k=3, methods=methods,
                                             paths_relative_to="config"))


def test_report_lists_the_sae_effect_latents_linked_to_the_trained_saes_feature_page(tmp_path):
    layer_path = steered_layer(tmp_path, ("sae", "sae_effect"))
    trained = tmp_path / "saes" / "run" / "layer12"
    trained.mkdir(parents=True)
    (trained / FIDELITY_JSON).write_text(json.dumps({"verdict": "keep the trained SAE", "saes": {}}))
    (trained / FEATURE_PAGE_FILE).write_text("<html></html>")
    record = json.loads((layer_path / PAIR / PAIR_SUMMARY_FILE).read_text())["methods"]["sae_effect"]["record"]
    assert len(record["latents"]) == 3
    markdown = write_report(layer_path, top_k=3, trained_sae=trained).read_text()
    assert f"## {PAIR}: sae_effect latents" in markdown
    assert "| latent | Cohen's d | mean diff | episodes | fires |" in markdown
    for item in record["latents"]:
        page = f"../../saes/run/layer12/{FEATURE_PAGE_FILE}#latent-{item['latent']}"
        assert (f"| [{item['latent']}]({page}) | {item['cohen_d']:+.3f} | {item['mean_difference']:+.4f} | "
                f"{item['episodes']} | {item['frequency']:.1%} |") in markdown
    summary = json.loads((layer_path / "summary.json").read_text())
    assert summary["pairs"][0]["sae_effect"] == record
    plain = write_report(layer_path, top_k=3).read_text()  # no trained SAE: no feature page to link
    assert f"| {record['latents'][0]['latent']} | {record['latents'][0]['cohen_d']:+.3f} |" in plain


def test_report_renders_a_pair_written_before_methods(tmp_path):
    layer_path = steered_layer(tmp_path, ("sae",))
    info_path = layer_path / PAIR / PAIR_SUMMARY_FILE
    info = json.loads(info_path.read_text())
    info.pop("methods")
    info_path.write_text(json.dumps(info))
    markdown = write_report(layer_path, top_k=3).read_text()
    assert f"## {PAIR}: top latents" in markdown and "sae_effect" not in markdown
    assert json.loads((layer_path / "summary.json").read_text())["pairs"][0]["sae_effect"] is None

