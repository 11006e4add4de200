"""Steering vectors: streaming statistics against in-memory ones, the seed's output files, pairwise stats, errors, CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_locks import hold_output_lock, start_waiting
from reference_formats import FORMATS
from reference_sae import ReferenceSae
from safetensors import safe_open
from safetensors.torch import save_file
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.sae.formats import WEIGHTS_FILE
from steering_core.sae.model import load_sae
from steering_core.synthetic.sae import write_sae_folder
from steering_core.vectors.concept_stats import ConceptSource, encode_concept, read_concept_stats
from steering_core.vectors.directions import SteeringSettings, compute_steering, concept_sources, read_pairs_config

D_IN, D_SAE = 16, 48
REFERENCE_PAIRS = FORMATS / "layer12_pairs.json"
SEED_KEYS = {
    "latent_mean": {"concept", "count", "mean"},
    "latent_direction": {"pair", "positive_concept", "negative_concept", "latent_direction", "latent_norm", "counts"},
    "residual_direction": {"pair", "positive_concept", "negative_concept", "residual_direction", "residual_norm", "counts"},
}
# added to the seed's direction dicts: how the concept rows were cut, and R (the α unit)
OUR_DIRECTION_KEYS = {"reduce", "mean_residual_norm"}
OUR_RESIDUAL_KEYS = OUR_DIRECTION_KEYS | {"include_decoder_bias"}
PAIRWISE_KEYS = {"latent_cosine", "residual_cosine", "latent_norm_a", "latent_norm_b", "residual_norm_a", "residual_norm_b"}


def concept_tensor(rows: int, seed: int, shift: float = 0.0) -> torch.Tensor:
    """(rows, D_IN) float32 rows around a concept-specific mean."""
    gen = torch.Generator().manual_seed(seed)
    return (torch.randn(rows, D_IN, generator=gen) + shift * torch.randn(D_IN, generator=gen) + 0.3).float()


@pytest.fixture
def sae_folder(tmp_path) -> Path:
    return write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, dtype="float64", neuronpedia_id="toy/12-res")


@pytest.fixture
def project(tmp_path, monkeypatch) -> Path:
    """A working directory holding the reference pairs config and its eight concept files (relative paths)."""
    monkeypatch.chdir(tmp_path)
    config = read_pairs_config(REFERENCE_PAIRS)
    for i, pair in enumerate(config.pairs):
        for j, side in enumerate(("positive", "negative")):
            path = tmp_path / getattr(pair, f"{side}_path")
            path.parent.mkdir(parents=True, exist_ok=True)
            torch.save(concept_tensor(30 + 7 * i + 3 * j, seed=10 * i + j, shift=1.0), path)
    shutil.copy(REFERENCE_PAIRS, tmp_path / "layer12_pairs.json")
    return tmp_path


def settings(project: Path, sae: Path | None, **overrides) -> SteeringSettings:
    values = dict(pairs_config=project / "layer12_pairs.json", output_root=project / "out", sae=str(sae) if sae else None,
                  batch_size=8, device="cpu")
    return SteeringSettings(**(values | overrides))


def reference(sae_folder: Path) -> ReferenceSae:
    return ReferenceSae.from_weights_file(sae_folder / WEIGHTS_FILE)


def test_reference_pairs_config_loads_unchanged():
    config = read_pairs_config(REFERENCE_PAIRS)
    assert [pair.name for pair in config.pairs] == ["open_drawer_main", "on_stove", "open_drawer_subset", "back_plate"]
    sources, pairs = concept_sources(config, Path("/base/pairs.json"), "config")
    assert len(sources) == 8  # same labels, different slice folders: eight files
    assert pairs["on_stove"] == (
        Path("/base/data/residuals/on_vs_off_slices/layer12/turn on the stove.pt"),
        Path("/base/data/residuals/on_vs_off_slices/layer12/turn off the stove.pt"),
    )
    assert sources[pairs["on_stove"][0]].label == "turn on the stove"


@pytest.mark.parametrize("batch_size", [1, 7, 64, 1000])
@pytest.mark.parametrize("file_format", ["pt", "pt3d", "safetensors"])
def test_streaming_statistics_equal_in_memory_ones(tmp_path, sae_folder, batch_size, file_format):
    x = concept_tensor(101, seed=3)  # 101 rows: every batch size above leaves an uneven last batch
    path = tmp_path / f"concept.{'safetensors' if file_format == 'safetensors' else 'pt'}"
    if file_format == "safetensors":
        save_file({"residuals": x, "index": torch.arange(101)}, path)
    else:
        torch.save(x[:, None, :] if file_format == "pt3d" else x, path)
    sae = load_sae(sae_folder)
    encoded_rows = []
    original = sae.encode_with_norm
    sae.encode_with_norm = lambda rows, out=None: (encoded_rows.append(len(rows)), original(rows, out))[1]
    stats = read_concept_stats(encode_concept(ConceptSource("c", path), tmp_path / "layer12", sae, batch_size=batch_size))
    assert max(encoded_rows) <= batch_size and sum(encoded_rows) == 101  # never more than one batch of latents

    ref = reference(sae_folder)
    f, _ = ref.encode(x.double().numpy())
    x_hat = ref.decode(f, {})
    xd = x.double().numpy()
    assert stats.count == 101
    np.testing.assert_allclose(stats.latent_mean.numpy(), f.mean(axis=0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(stats.firing_rate.numpy(), (f > 0).mean(axis=0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(stats.residual_mean.numpy(), xd.mean(axis=0), rtol=1e-9, atol=1e-12)
    fvu = ((xd - x_hat) ** 2).sum() / ((xd - xd.mean(axis=0)) ** 2).sum()
    assert stats.fvu == pytest.approx(fvu, rel=1e-9)
    assert stats.mean_l0 == pytest.approx((f > 0).sum(axis=1).mean(), rel=1e-12)


@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_streaming_statistics_in_low_precision_saes(tmp_path, dtype):
    """Firing counts are exact and means close to the SAE's own one-shot encode, whatever its dtype."""
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, dtype=dtype)
    x = concept_tensor(300, seed=5)  # 300 rows: more than bfloat16 counts exactly (256), so counts must widen
    torch.save(x, tmp_path / "concept.pt")
    sae = load_sae(folder)
    stats = read_concept_stats(encode_concept(ConceptSource("c", tmp_path / "concept.pt"), tmp_path / "layer12", sae,
                                              batch_size=1000))
    latents, norm = sae.encode_with_norm(x)
    assert torch.equal(stats.firing_rate, (latents > 0).sum(dim=0).double() / 300)
    torch.testing.assert_close(stats.latent_mean, latents.double().mean(dim=0), rtol=1e-2, atol=1e-3)
    error = ((x.double() - sae.decode(latents, norm).double()) ** 2).sum()
    variance = ((x.double() - x.double().mean(dim=0)) ** 2).sum()
    assert stats.fvu == pytest.approx(float(error / variance), rel=2e-2)


def test_outputs_have_the_seed_keys_and_values(project, sae_folder):
    layer_path = compute_steering(settings(project, sae_folder))
    ref = reference(sae_folder)
    pair_dir = layer_path / "on_stove"
    pos_x = torch.load(project / "data/residuals/on_vs_off_slices/layer12/turn on the stove.pt", weights_only=True).double().numpy()
    neg_x = torch.load(project / "data/residuals/on_vs_off_slices/layer12/turn off the stove.pt", weights_only=True).double().numpy()
    pos_mean, neg_mean = ref.encode(pos_x)[0].mean(axis=0), ref.encode(neg_x)[0].mean(axis=0)

    positive = torch.load(pair_dir / "positive_latent_mean.pt", weights_only=True)
    assert set(positive) == SEED_KEYS["latent_mean"]
    assert positive["concept"] == "turn on the stove" and positive["count"] == len(pos_x) and type(positive["count"]) is int
    assert positive["mean"].dtype == torch.float32 and positive["mean"].shape == (D_SAE,)
    np.testing.assert_allclose(positive["mean"].numpy(), pos_mean, rtol=1e-5, atol=1e-6)

    latent = torch.load(pair_dir / "latent_direction.pt", weights_only=True)
    assert set(latent) == SEED_KEYS["latent_direction"] | OUR_DIRECTION_KEYS
    assert (latent["pair"], latent["positive_concept"], latent["negative_concept"]) == (
        "on_stove", "turn on the stove", "turn off the stove")
    assert latent["counts"] == {"positive": len(pos_x), "negative": len(neg_x)}
    np.testing.assert_allclose(latent["latent_direction"].numpy(), pos_mean - neg_mean, rtol=1e-5, atol=1e-6)
    assert latent["latent_norm"] == pytest.approx(float(np.linalg.norm(pos_mean - neg_mean)), rel=1e-5)

    residual = torch.load(pair_dir / "residual_direction.pt", weights_only=True)
    assert set(residual) == SEED_KEYS["residual_direction"] | OUR_RESIDUAL_KEYS
    expected = (pos_mean - neg_mean) @ ref.W_dec  # no b_dec
    np.testing.assert_allclose(residual["residual_direction"].numpy(), expected, rtol=1e-5, atol=1e-5)
    assert residual["residual_norm"] == pytest.approx(float(np.linalg.norm(expected)), rel=1e-5)

    summary = json.loads((pair_dir / "directions.json").read_text())
    assert summary["mean_difference_norm"] == pytest.approx(float(np.linalg.norm(pos_x.mean(0) - neg_x.mean(0))), rel=1e-5)
    cos = expected @ (pos_x.mean(0) - neg_x.mean(0)) / np.linalg.norm(expected) / np.linalg.norm(pos_x.mean(0) - neg_x.mean(0))
    assert summary["decoded_vs_mean_difference_cosine"] == pytest.approx(cos, rel=1e-5)
    assert summary["method"] == "sae_decoder" and summary["sae"]["neuronpedia_id"] == "toy/12-res"

    for stem, key in [("positive_latent_mean", "mean"), ("latent_direction", "latent_direction"),
                      ("residual_direction", "residual_direction")]:
        payload = torch.load(pair_dir / f"{stem}.pt", weights_only=True)
        with safe_open(pair_dir / f"{stem}.safetensors", framework="pt") as handle:
            assert torch.equal(handle.get_tensor(key), payload[key])
            metadata = {name: json.loads(value) for name, value in handle.metadata().items()}
        assert metadata == {name: value for name, value in payload.items() if name != key}


def test_decoder_bias_option_reproduces_the_seed(project, sae_folder):
    layer_path = compute_steering(settings(project, sae_folder, include_decoder_bias=True))
    latent = torch.load(layer_path / "back_plate" / "latent_direction.pt", weights_only=True)["latent_direction"]
    residual = torch.load(layer_path / "back_plate" / "residual_direction.pt", weights_only=True)["residual_direction"]
    ref = reference(sae_folder)
    np.testing.assert_allclose(residual.numpy(), latent.double().numpy() @ ref.W_dec + ref.b_dec, rtol=1e-5, atol=1e-5)
    assert json.loads((layer_path / "back_plate" / "directions.json").read_text())["include_decoder_bias"] is True
    with safe_open(layer_path / "back_plate" / "residual_direction.safetensors", framework="pt") as handle:
        assert json.loads(handle.metadata()["include_decoder_bias"]) is True


def test_every_direction_records_the_mean_residual_norm_of_both_concepts_rows(project, sae_folder):
    layer_path = compute_steering(settings(project, sae_folder))
    slices = project / "data/residuals/on_vs_off_slices/layer12"
    rows = [torch.load(slices / f"turn {side} the stove.pt", weights_only=True).double() for side in ("on", "off")]
    expected = float(torch.cat(rows).norm(dim=-1).mean())
    pair_dir = layer_path / "on_stove"
    assert json.loads((pair_dir / "directions.json").read_text())["mean_residual_norm"] == pytest.approx(expected)
    for stem in ("residual_direction", "latent_direction"):
        with safe_open(pair_dir / f"{stem}.safetensors", framework="pt") as handle:
            assert json.loads(handle.metadata()["mean_residual_norm"]) == pytest.approx(expected)
        assert torch.load(pair_dir / f"{stem}.pt", weights_only=True)["mean_residual_norm"] == pytest.approx(expected)
    for name in ("sae", "mean_difference"):
        with safe_open(pair_dir / f"{name}_direction.safetensors", framework="pt") as handle:
            assert json.loads(handle.metadata()["mean_residual_norm"]) == pytest.approx(expected)


def test_statistics_without_the_row_norm_sum_are_recomputed(project, sae_folder):
    layer_path = compute_steering(settings(project, None))
    for stats in (layer_path / "concepts").glob("*.json"):
        meta = json.loads(stats.read_text())
        del meta["residual_norm_sum"]  # a statistics file written before the α unit was recorded
        stats.write_text(json.dumps(meta))
    compute_steering(settings(project, None))
    assert json.loads((layer_path / "on_stove" / "directions.json").read_text())["mean_residual_norm"] > 0


def test_pairwise_stats_by_hand(project, sae_folder):
    layer_path = compute_steering(settings(project, sae_folder))
    stats = torch.load(layer_path / "pairwise_stats.pt", weights_only=True)
    names = ["open_drawer_main", "on_stove", "open_drawer_subset", "back_plate"]
    assert list(stats) == [f"{a}__{b}" for i, a in enumerate(names) for b in names[i + 1:]]

    def load(pair, stem, key):
        return torch.load(layer_path / pair / f"{stem}.pt", weights_only=True)[key].double().numpy()

    a, b = "on_stove", "back_plate"
    entry = stats[f"{a}__{b}"]
    assert set(entry) == PAIRWISE_KEYS
    la, lb = load(a, "latent_direction", "latent_direction"), load(b, "latent_direction", "latent_direction")
    ra, rb = load(a, "residual_direction", "residual_direction"), load(b, "residual_direction", "residual_direction")
    assert entry["latent_cosine"] == pytest.approx(la @ lb / np.sqrt((la @ la) * (lb @ lb)), rel=1e-9)
    assert entry["residual_cosine"] == pytest.approx(ra @ rb / np.sqrt((ra @ ra) * (rb @ rb)), rel=1e-9)
    assert entry["latent_norm_b"] == pytest.approx(np.sqrt(lb @ lb), rel=1e-6)
    assert entry["residual_norm_a"] == pytest.approx(np.sqrt(ra @ ra), rel=1e-6)
    as_json = json.loads((layer_path / "pairwise_stats.json").read_text())
    assert as_json["pairs"] == names and as_json["sae_used"] is True
    assert as_json["entries"][f"{a}__{b}"]["residual_cosine"] == pytest.approx(entry["residual_cosine"])


def test_each_concept_is_encoded_once(project, sae_folder):
    config = json.loads((project / "layer12_pairs.json").read_text())
    config["pairs"].append({**config["pairs"][0], "name": "open_drawer_repeat"})  # shares both concept files
    (project / "layer12_pairs.json").write_text(json.dumps(config))
    sae = load_sae(sae_folder)
    encoded = []
    original = sae.encode_with_norm
    sae.encode_with_norm = lambda rows, out=None: (encoded.append(len(rows)), original(rows, out))[1]
    compute_steering(settings(project, None), sae=sae)
    rows = sum(len(torch.load(path, weights_only=True)) for path in (project / "data").rglob("*.pt"))
    assert sum(encoded) == rows


def test_a_pair_reversed_against_its_slices_manifest_is_refused(project, sae_folder):
    """The research group's files: the slices' index.json names the concept map, which names the manifest."""
    manifest, concept_map = project / "open_vs_close.json", project / "open_vs_close_concept_map.json"
    shutil.copy(FORMATS / "open_vs_close.json", manifest)
    payload = json.loads((FORMATS / "open_vs_close_concept_map.json").read_text())
    concept_map.write_text(json.dumps(payload | {"manifest": str(manifest)}))
    folder = project / "data/residuals/open_vs_close_slices/layer12"
    (folder / "index.json").write_text(json.dumps({"concept_map": str(concept_map), "concepts": {
        task: {"pt": f"{task}.pt", "safetensors": f"{task}.safetensors"}
        for task in ("open the top drawer of the cabinet", "close the top drawer of the cabinet")}}))
    compute_steering(settings(project, None))  # the order of the reference files is the manifest's
    config = json.loads(REFERENCE_PAIRS.read_text())
    spec = config["pairs"][0]
    for key in ("label", "path"):
        spec[f"positive_{key}"], spec[f"negative_{key}"] = spec[f"negative_{key}"], spec[f"positive_{key}"]
    (project / "layer12_pairs.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=r"^\S*layer12_pairs.json: pair 'open_drawer_main' has positive 'close the "
                                         r"top drawer of the cabinet' and negative 'open the top drawer of the "
                                         r"cabinet', but its manifest \S*open_vs_close.json lists positive 'open"):
        compute_steering(settings(project, None, output_root=project / "reversed"))
    assert not (project / "reversed").exists()


def test_current_statistics_are_reused_and_stale_ones_recomputed(project, sae_folder):
    sae = load_sae(sae_folder)
    compute_steering(settings(project, None), sae=sae)
    encoded = []
    original = sae.encode_with_norm
    sae.encode_with_norm = lambda rows, out=None: (encoded.append(len(rows)), original(rows, out))[1]
    compute_steering(settings(project, None), sae=sae)
    assert encoded == []
    changed = project / "data/residuals/on_vs_off_slices/layer12/turn on the stove.pt"
    torch.save(concept_tensor(5, seed=99), changed)
    compute_steering(settings(project, None), sae=sae)
    assert sum(encoded) == 5


def test_without_sae_directions_are_mean_differences(project):
    layer_path = compute_steering(settings(project, None))
    pair_dir = layer_path / "open_drawer_main"
    assert sorted(p.name for p in pair_dir.iterdir()) == [  # the seed's file and the residual-space methods
        "directions.json", "mean_difference_direction.safetensors", "probe_direction.safetensors",
        "residual_direction.pt", "residual_direction.safetensors"]
    residual = torch.load(pair_dir / "residual_direction.pt", weights_only=True)
    assert set(residual) == SEED_KEYS["residual_direction"] | OUR_RESIDUAL_KEYS
    pos = torch.load(project / "data/residuals/open_vs_close_slices/layer12/open the top drawer of the cabinet.pt", weights_only=True)
    neg = torch.load(project / "data/residuals/open_vs_close_slices/layer12/close the top drawer of the cabinet.pt", weights_only=True)
    np.testing.assert_allclose(residual["residual_direction"].numpy(), (pos.double().mean(0) - neg.double().mean(0)).numpy(),
                               rtol=1e-6, atol=1e-6)
    summary = json.loads((pair_dir / "directions.json").read_text())
    assert summary["sae"] is None and summary["method"] == "mean_difference"
    entry = torch.load(layer_path / "pairwise_stats.pt", weights_only=True)["open_drawer_main__on_stove"]
    assert set(entry) == {"residual_cosine", "residual_norm_a", "residual_norm_b"}
    assert "No SAE was used" in (layer_path / "summary.md").read_text()


def test_rerun_replaces_a_pair_folder_whole(project, sae_folder):
    compute_steering(settings(project, sae_folder))
    layer_path = compute_steering(settings(project, None))
    assert not (layer_path / "on_stove" / "latent_direction.pt").exists()


def test_paths_relative_to_config_folder(project, sae_folder, tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path.parent)
    with pytest.raises(FileNotFoundError):
        compute_steering(settings(project, sae_folder, paths_relative_to="cwd"))
    layer_path = compute_steering(settings(project, sae_folder, paths_relative_to="config"))
    assert (layer_path / "back_plate" / "residual_direction.pt").is_file()
    with caplog.at_level("INFO"):  # auto: not found from here, so the pairs file's folder, and it says so
        layer_path = compute_steering(settings(project, sae_folder, output_root=tmp_path / "auto"))
    assert (layer_path / "back_plate" / "residual_direction.pt").is_file()
    assert f"resolved against the pairs file's folder {project}" in caplog.text


def test_auto_paths_prefer_the_working_directory(project, tmp_path):
    """The seed's files are cwd-relative: a same-named file beside the pairs file must not win."""
    config = read_pairs_config(project / "layer12_pairs.json")
    nested = project / "nested"
    nested.mkdir()
    relative = config.pairs[0].positive_path
    (nested / relative).parent.mkdir(parents=True)
    (nested / relative).write_bytes(b"")
    _, pairs = concept_sources(config, nested / "pairs.json")
    assert pairs[config.pairs[0].name][0] == project / relative
    assert concept_sources(config, nested / "pairs.json", "config")[1][config.pairs[0].name][0] == nested / relative


def test_the_slices_reduction_is_recorded(project, sae_folder):
    slices = project / "data/residuals/on_vs_off_slices/layer12"
    (slices / "index.json").write_text(json.dumps({"settings": {"reduce": "frame", "token_type": "instructions"}}))
    pair_dir = compute_steering(settings(project, sae_folder)) / "on_stove"
    assert json.loads((pair_dir / "directions.json").read_text())["reduce"] == {"positive": "frame", "negative": "frame"}
    assert torch.load(pair_dir / "residual_direction.pt", weights_only=True)["reduce"] == {
        "positive": "frame", "negative": "frame"}
    other = torch.load(pair_dir.parent / "back_plate" / "latent_direction.pt", weights_only=True)
    assert other["reduce"] == {"positive": None, "negative": None}  # no index.json: unknown (e.g. the seed's slices)


def test_progress_reaches_the_total(project, sae_folder):
    calls = []
    compute_steering(settings(project, sae_folder), progress=lambda done, total: calls.append((done, total)))
    total = calls[0][1]
    assert calls[-1] == (total, total) and [done for done, _ in calls] == sorted(done for done, _ in calls)


def test_missing_concept_files_are_listed_with_their_pairs(project, sae_folder):
    (project / "data/residuals/on_vs_off_slices/layer12/turn off the stove.pt").unlink()
    (project / "data/residuals/back_vs_front_slices/layer12/put the black bowl at the back on the plate.pt").unlink()
    with pytest.raises(FileNotFoundError) as err:
        compute_steering(settings(project, sae_folder))
    message = str(err.value)
    assert "turn off the stove.pt (on_stove.negative_path): file not found" in message
    assert "(back_plate.positive_path): file not found" in message and "--paths-relative-to" in message


def test_dimension_mismatch_names_the_file_and_the_sae(project, tmp_path):
    sae = write_sae_folder(tmp_path / "wide_sae", d_in=D_IN + 4, d_sae=D_SAE)
    with pytest.raises(ValueError) as err:
        compute_steering(settings(project, sae))
    message = str(err.value)
    assert f"turn on the stove.pt (on_stove.positive_path): residuals are (37, {D_IN}) but SAE " in message
    assert f"expects (*, {D_IN + 4})" in message and message.count("residuals are") == 8


def test_empty_and_malformed_concepts(project, sae_folder):
    torch.save(torch.zeros(0, D_IN), project / "data/residuals/on_vs_off_slices/layer12/turn on the stove.pt")
    torch.save(torch.zeros(D_IN), project / "data/residuals/on_vs_off_slices/layer12/turn off the stove.pt")
    torch.save(torch.zeros(5, D_IN, dtype=torch.int64),
               project / "data/residuals/back_vs_front_slices/layer12/put the black bowl at the back on the plate.pt")
    torch.save({"rows": torch.zeros(5, D_IN)},
               project / "data/residuals/back_vs_front_slices/layer12/put the black bowl at the front on the plate.pt")
    with pytest.raises(ValueError) as err:
        compute_steering(settings(project, sae_folder))
    message = str(err.value)
    assert "(back_plate.positive_path): dtype is torch.int64, expected a floating-point tensor" in message
    assert "(back_plate.negative_path): " in message and "expected a (rows, d_in) tensor, found dict" in message
    assert "turn on the stove.pt (on_stove.positive_path): no rows; the concept is empty" in message
    assert f"turn off the stove.pt (on_stove.negative_path): tensor is ({D_IN},), expected (rows, {D_IN})" in message


def test_non_finite_rows_are_refused(project, sae_folder):
    x = concept_tensor(20, seed=1)
    x[13, 2] = float("nan")
    torch.save(x, project / "data/residuals/on_vs_off_slices/layer12/turn on the stove.pt")
    with pytest.raises(ValueError, match=r"turn on the stove.pt \(on_stove.positive_path\): tensor `residuals` holds "
                                         r"NaN or Inf \(nan at \(13, 2\)\)"):
        compute_steering(settings(project, sae_folder))
    assert not (settings(project, sae_folder).output_root / "layer12").exists()  # refused before any statistics


def test_sae_of_another_layer_is_refused(project, tmp_path):
    sae = write_sae_folder(tmp_path / "l6", d_in=D_IN, d_sae=D_SAE, hook_layer=6)
    with pytest.raises(ValueError, match="reads blocks.6.hook_resid_post \\(layer 6\\) but layer 12 was requested"):
        compute_steering(settings(project, sae))
    with pytest.raises(ValueError, match="but layer 12 was requested"):
        compute_steering(settings(project, None), sae=load_sae(sae))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda c: c["pairs"][1].pop("negative_path"), "pairs.1.negative_path: Field required"),
        (lambda c: c["pairs"][1].update(name="open_drawer_main"), "pair names must be unique; repeated: ['open_drawer_main']"),
        (lambda c: c["pairs"][0].update(name="../escape"), "one file or folder name without `..`"),
        (lambda c: c.update(pairs=[]), "pairs: List should have at least 1 item"),
        (lambda c: c["pairs"][0].update(weight=2), "pairs.0.weight: Extra inputs are not permitted"),
    ],
)
def test_bad_pairs_config(tmp_path, edit, message):
    config = json.loads(REFERENCE_PAIRS.read_text())
    edit(config)
    (tmp_path / "pairs.json").write_text(json.dumps(config))
    with pytest.raises(ValueError) as err:
        read_pairs_config(tmp_path / "pairs.json")
    assert str(err.value).startswith(f"{tmp_path / 'pairs.json'}: not a valid pairs config") and message in str(err.value)


def test_cli_steer(project, sae_folder):
    runner = CliRunner()
    args = ["steer", "--pairs-config", "layer12_pairs.json", "--output-root", "cli_out", "--layer", "12",
            "--device", "cpu", "--batch-size", "16", "--sae", str(sae_folder), "--top-k", "5"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "cli_out/layer12/summary.md" in result.output
    summary = json.loads((project / "cli_out/layer12/summary.json").read_text())
    assert len(summary["pairs"][0]["top_latents"]) == 5
    no_sae = runner.invoke(app, [*args[:-4], "--sae", "none", "--output-root", "plain"])
    assert no_sae.exit_code == 0 and not (project / "plain/layer12/on_stove/latent_direction.pt").exists()
    missing = runner.invoke(app, [*args[:-4], "--sae", "gemma-2b-it-res-jb", "--layer", "6"])
    assert missing.exit_code == 1 and "has no SAE id 'blocks.6.hook_resid_post'" in missing.output


def test_cli_steer_refuses_pickled_or_mislabelled_sae_files_in_one_line(project, tmp_path):
    import argparse
    import pickle

    pickled = tmp_path / "sae.pt"
    torch.save({"W_enc": torch.ones(2, 2), "cfg": argparse.Namespace(d_in=2)}, pickled)
    renamed = tmp_path / "sae.safetensors"
    renamed.write_bytes(pickle.dumps({"W_enc": [1.0]}))
    args = ["steer", "--pairs-config", "layer12_pairs.json", "--output-root", "out", "--layer", "12",
            "--device", "cpu"]
    for path, message in ((pickled, "holds pickled objects other than tensors"),
                          (renamed, "not a safetensors file")):
        result = CliRunner().invoke(app, [*args, "--sae", str(path)])
        assert result.exit_code == 1, result.output
        assert f"{path}: {message}" in result.output
        assert "Traceback" not in result.output and "weights_only=False" not in result.output


def test_a_second_run_waits_for_the_layer_another_process_writes_then_reuses_its_statistics(project, sae_folder):
    sae = load_sae(sae_folder)
    reference_root = project / "reference"
    compute_steering(settings(project, None, output_root=reference_root), sae=sae)
    encoded = []
    original = sae.encode_with_norm
    sae.encode_with_norm = lambda rows, out=None: (encoded.append(len(rows)), original(rows, out))[1]
    layer = project / "out" / "layer12"
    holder = hold_output_lock(layer)
    worker, outcome = start_waiting(lambda: compute_steering(settings(project, None), sae=sae))
    assert not layer.exists() and encoded == []  # waiting, nothing encoded
    shutil.copytree(reference_root / "layer12", layer)  # the other process finishes the layer
    holder.communicate("done\n", timeout=30)
    worker.join(timeout=60)
    assert outcome["result"] == layer and encoded == []  # the SAE pass was done once, by the other process
    for name in ("latent_direction.pt", "residual_direction.pt"):
        ours = torch.load(layer / "on_stove" / name, weights_only=True)
        theirs = torch.load(reference_root / "layer12" / "on_stove" / name, weights_only=True)
        assert torch.equal(ours[name.removesuffix(".pt")], theirs[name.removesuffix(".pt")])


def test_encoding_a_concept_another_process_is_encoding_waits_then_reuses_it(tmp_path, sae_folder):
    """The flow's per-concept step: the statistics file is locked while computed, then reused."""
    from steering_core.vectors.concept_stats import concept_stats_path

    path = tmp_path / "on.pt"
    torch.save(concept_tensor(20, seed=3, shift=1.0), path)
    source, sae = ConceptSource("on", path), load_sae(sae_folder)
    reference = encode_concept(source, tmp_path / "reference", sae, batch_size=8)
    encoded = []
    original = sae.encode_with_norm
    sae.encode_with_norm = lambda rows, out=None: (encoded.append(len(rows)), original(rows, out))[1]
    json_path = concept_stats_path(tmp_path / "layer12", source).with_suffix(".json")
    holder = hold_output_lock(json_path)
    worker, outcome = start_waiting(lambda: encode_concept(source, tmp_path / "layer12", sae, batch_size=8))
    assert not json_path.exists()  # waiting, nothing computed
    for suffix in (".safetensors", ".json"):  # the other process finishes the statistics
        shutil.copy(reference.with_suffix(suffix), json_path.with_suffix(suffix))
    holder.communicate("done\n", timeout=30)
    worker.join(timeout=60)
    assert outcome["result"] == json_path and encoded == []
    assert torch.equal(read_concept_stats(json_path).latent_mean, read_concept_stats(reference).latent_mean)
