"""SAE loading and maths against the independent numpy reference, registry resolution, and error texts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from reference_sae import ReferenceSae
from safetensors.torch import load_file, save_file

from steering_core.sae.formats import CFG_FILE, WEIGHTS_FILE, is_legacy_cfg, parse_cfg, upgrade_legacy_cfg
from steering_core.sae.model import Sae, StandardSae, load_sae, register_architecture, sae_class
from steering_core.sae.registry import hub_cache_dir, resolve_release
from steering_core.synthetic.sae import write_release_to_hub_cache, write_sae_folder, write_sae_state_dict

D_IN, D_SAE, ROWS, K = 16, 64, 40, 8
ARCHITECTURES = ("standard", "jumprelu", "topk")
NORMALISATIONS = ("none", "constant_norm_rescale", "layer_norm", "expected_average_only_in")
GEMMA_L12_FACTOR = 0.21381938399317255  # SAELens registry: gemma-2b-res-jb blocks.12


@pytest.fixture
def hub_cache(tmp_path, monkeypatch) -> Path:
    cache = tmp_path / "hub"
    monkeypatch.setenv("HF_HUB_CACHE", str(cache))
    return cache


def residuals(rows: int = ROWS, d_in: int = D_IN, seed: int = 1) -> torch.Tensor:
    """(rows, d_in) float64 residuals with an offset and uneven scale, like real activations."""
    gen = torch.Generator().manual_seed(seed)
    return 3 * torch.randn(rows, d_in, generator=gen, dtype=torch.float64) + 0.5


def reference_for(folder: Path, **settings) -> ReferenceSae:
    return ReferenceSae.from_weights_file(folder / WEIGHTS_FILE, **settings)


@pytest.mark.parametrize("layout", ["current", "legacy"])
@pytest.mark.parametrize("normalize", NORMALISATIONS)
@pytest.mark.parametrize("architecture", ARCHITECTURES)
def test_encode_decode_match_reference(tmp_path, architecture, normalize, layout):
    folder = write_sae_folder(
        tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, architecture=architecture, normalize_activations=normalize,
        layout=layout, k=K, dtype="float64", apply_b_dec_to_input=normalize != "layer_norm",
    )
    sae = load_sae(folder)
    ref = reference_for(
        folder, architecture=architecture, normalize=normalize, k=K,
        apply_b_dec_to_input=normalize != "layer_norm",
    )
    x = residuals()
    f, norm = sae.encode_with_norm(x)
    ref_f, stats = ref.encode(x.numpy())
    assert sae.cfg.architecture == architecture and f.shape == (ROWS, D_SAE)
    assert 0 < (f > 0).sum() < f.numel()  # the comparison is not between two all-zero tensors
    np.testing.assert_allclose(f.numpy(), ref_f, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sae.decode(f, norm).numpy(), ref.decode(ref_f, stats), rtol=1e-10, atol=1e-10)
    d = torch.randn(3, D_SAE, dtype=torch.float64)
    np.testing.assert_allclose(sae.decode_direction(d).numpy(), d.numpy() @ ref.W_dec, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("normalize", ["none", "layer_norm"])
@pytest.mark.parametrize("architecture", ARCHITECTURES)
def test_reconstruct_into_reused_buffers_matches_reference(tmp_path, architecture, normalize):
    """Batches computed into the same two buffers (a full one, then a shorter one) each match the reference."""
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, architecture=architecture, k=K,
                              normalize_activations=normalize, dtype="float64")
    sae = load_sae(folder)
    ref = reference_for(folder, architecture=architecture, normalize=normalize, k=K)
    buffers = torch.full((ROWS, D_IN), 7.0, dtype=torch.float64), torch.full((ROWS, D_SAE), 7.0, dtype=torch.float64)
    for rows, seed in ((ROWS, 2), (ROWS // 3, 3)):
        x = residuals(rows, seed=seed)
        decoded, latents = sae.reconstruct(x, tuple(buffer[:rows] for buffer in buffers))
        ref_f, stats = ref.encode(x.numpy())
        np.testing.assert_allclose(latents.numpy(), ref_f, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(decoded.numpy(), ref.decode(ref_f, stats), rtol=1e-10, atol=1e-10)


def test_topk_rescaled_by_decoder_norm_matches_reference(tmp_path):
    folder = write_sae_folder(
        tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, architecture="topk", k=K, rescale_acts_by_decoder_norm=True,
        dtype="float64", layout="current",
    )
    sae = load_sae(folder)
    ref = reference_for(folder, architecture="topk", k=K, rescale_by_decoder_norm=True)
    x = residuals()
    ref_f, stats = ref.encode(x.numpy())
    np.testing.assert_allclose(sae.encode(x).numpy(), ref_f, rtol=1e-10, atol=1e-10)
    assert ((sae.encode(x) > 0).sum(dim=-1) <= K).all()
    np.testing.assert_allclose(sae.decode(sae.encode(x)).numpy(), ref.decode(ref_f, stats), rtol=1e-10, atol=1e-10)
    d = torch.randn(D_SAE, dtype=torch.float64)
    np.testing.assert_allclose(sae.decode_direction(d).numpy(), ref.direction(d.numpy()), rtol=1e-12, atol=1e-12)


def test_float32_sae_casts_inputs_and_matches_reference(tmp_path):
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE)
    sae = load_sae(folder)
    x = residuals().to(torch.bfloat16)
    f = sae.encode(x)
    assert f.dtype == torch.float32 and sae.W_enc.dtype == torch.float32
    ref_f, _ = reference_for(folder).encode(x.double().numpy())
    np.testing.assert_allclose(f.numpy(), ref_f, rtol=1e-4, atol=1e-4)


def test_legacy_cfg_upgrade_rules():
    legacy = {
        "d_in": 8, "d_sae": 32, "hook_point": "blocks.6.hook_resid_post", "hook_point_layer": 6,
        "hook_point_head_index": None, "activation_fn_str": "relu", "normalize_activations": True,
    }
    upgraded = upgrade_legacy_cfg(legacy)
    assert upgraded["hook_name"] == "blocks.6.hook_resid_post" and "hook_point" not in upgraded
    assert upgraded["hook_head_index"] is None and upgraded["activation_fn"] == "relu"
    assert upgraded["architecture"] == "standard" and upgraded["apply_b_dec_to_input"] is True
    assert upgraded["normalize_activations"] == "expected_average_only_in"
    assert upgrade_legacy_cfg({**legacy, "normalize_activations": False})["normalize_activations"] == "none"
    assert upgrade_legacy_cfg({**legacy, "normalize_activations": None})["normalize_activations"] == "none"
    # flags present in the old file win over the defaults
    assert upgrade_legacy_cfg({**legacy, "apply_b_dec_to_input": False})["apply_b_dec_to_input"] is False
    topk = upgrade_legacy_cfg({**legacy, "activation_fn_str": "topk", "activation_fn_kwargs": {"k": 4}})
    assert topk["architecture"] == "topk" and topk["k"] == 4
    cfg = parse_cfg(legacy, source="cfg.json")
    assert (cfg.hook_name, cfg.hook_layer, cfg.d_in, cfg.d_sae) == ("blocks.6.hook_resid_post", 6, 8, 32)


@pytest.mark.parametrize(
    ("raw", "legacy"),
    [
        ({}, True),
        ({"sae_lens_version": "5.9.1"}, True),
        ({"sae_lens_version": "6.0.0-rc.0"}, False),
        ({"metadata": {"sae_lens_version": "6.18.0"}}, False),
        ({"meta": {"sae_lens_version": "6.1.0"}}, False),
    ],
)
def test_cfg_version_detection(raw, legacy):
    assert is_legacy_cfg(raw) is legacy


def test_current_cfg_reads_metadata_and_hook_layer(tmp_path):
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, hook_layer=7, neuronpedia_id="x/7-res")
    cfg = load_sae(folder).cfg
    assert (cfg.hook_name, cfg.hook_layer, cfg.neuronpedia_id) == ("blocks.7.hook_resid_post", 7, "x/7-res")
    assert cfg.source == str(folder / WEIGHTS_FILE) and cfg.apply_b_dec_to_input is True


def test_sparsity_file_is_loaded(tmp_path):
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE)
    assert load_sae(folder).log_sparsity.shape == (D_SAE,)
    assert load_sae(write_sae_folder(tmp_path / "b", d_in=D_IN, d_sae=D_SAE, with_sparsity=False)).log_sparsity is None


def test_unknown_architecture_lists_allowed_values(tmp_path):
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE)
    cfg = json.loads((folder / CFG_FILE).read_text())
    (folder / CFG_FILE).write_text(json.dumps({**cfg, "architecture": "gated"}))
    with pytest.raises(ValueError, match=r"unknown SAE architecture 'gated'; allowed values: \['jumprelu', 'standard', 'topk'\]"):
        load_sae(folder)
    assert sae_class("topk").architecture == "topk"


def test_registering_an_architecture_twice_is_refused():
    class Duplicate(StandardSae):
        architecture = "standard"

    with pytest.raises(ValueError, match="SAE architecture 'standard' is already registered to StandardSae"):
        register_architecture(Duplicate)


def test_bad_cfg_values_are_reported_together(tmp_path):
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE)
    cfg = json.loads((folder / CFG_FILE).read_text())
    (folder / CFG_FILE).write_text(json.dumps({**cfg, "dtype": "int8", "normalize_activations": "whiten", "d_sae": 0}))
    with pytest.raises(ValueError) as err:
        load_sae(folder)
    message = str(err.value)
    assert "`dtype` is 'int8'" in message and "`normalize_activations` is 'whiten'" in message
    assert "`d_sae` is 0, expected a positive integer" in message


def test_weights_that_disagree_with_cfg_are_listed(tmp_path):
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, architecture="jumprelu")
    weights = load_file(folder / WEIGHTS_FILE)
    weights.pop("threshold")
    weights["W_enc"] = weights["W_enc"][:, :10].contiguous()
    weights["extra"] = torch.zeros(2)
    save_file(weights, folder / WEIGHTS_FILE)
    with pytest.raises(ValueError) as err:
        load_sae(folder)
    message = str(err.value)
    assert f"missing `threshold` ({D_SAE},)" in message and "unexpected `extra`" in message
    assert f"`W_enc` is ({D_IN}, 10), expected ({D_IN}, {D_SAE})" in message


def test_topk_k_out_of_range(tmp_path):
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, architecture="topk", k=D_SAE + 1)
    with pytest.raises(ValueError, match=f"topk SAE has k = {D_SAE + 1}, expected 1 <= k <= d_sae"):
        load_sae(folder)


def test_dimension_mismatch_names_both(tmp_path):
    sae = load_sae(write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE))
    with pytest.raises(ValueError, match=rf"input is \(4, 12\), SAE .*sae_weights.safetensors expects \(\.\.\., {D_IN}\)"):
        sae.encode(torch.zeros(4, 12))


def test_decode_needs_input_statistics_under_input_dependent_norms(tmp_path):
    sae = load_sae(write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, normalize_activations="layer_norm"))
    f = sae.encode(residuals())
    with pytest.raises(ValueError, match="decoding needs the InputNorm returned by encode_with_norm"):
        sae.decode(f)


def test_scaling_factor_all_ones_is_dropped(tmp_path):
    folder = write_sae_folder(
        tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, layout="legacy", scaling_factor=torch.ones(D_SAE), dtype="float64"
    )
    sae = load_sae(folder)
    assert not sae.cfg.finetuning_scaling_factor
    np.testing.assert_allclose(sae.W_dec.numpy(), load_file(folder / WEIGHTS_FILE)["W_dec"].numpy())


def test_scaling_factor_needs_finetuning_flag(tmp_path):
    scale = 1 + torch.rand(D_SAE)
    folder = write_sae_folder(tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, layout="legacy", scaling_factor=scale)
    with pytest.raises(ValueError, match="`scaling_factor` is not all ones but `finetuning_scaling_factor` is false"):
        load_sae(folder)


def test_finetuning_scaling_factor_scales_decoder_rows(tmp_path):
    scale = 1 + torch.rand(D_SAE, dtype=torch.float64)
    folder = write_sae_folder(
        tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, layout="legacy", scaling_factor=scale,
        finetuning_scaling_factor=True, dtype="float64",
    )
    sae, ref = load_sae(folder), reference_for(folder)
    x = residuals()
    ref_f, stats = ref.encode(x.numpy())
    np.testing.assert_allclose(sae.decode(sae.encode(x)).numpy(), ref.decode(ref_f, stats), rtol=1e-10, atol=1e-10)
    raw = load_file(folder / WEIGHTS_FILE)
    np.testing.assert_allclose(sae.W_dec.numpy(), (raw["W_dec"] * scale[:, None]).numpy(), rtol=1e-12)


@pytest.mark.parametrize(("name", "nested"), [("sae.pt", False), ("sae.pt", True), ("sae.safetensors", False)])
def test_seed_state_dict_file(tmp_path, name, nested):
    path = write_sae_state_dict(tmp_path / name, d_in=D_IN, d_sae=D_SAE, nested=nested)
    sae = load_sae(path, sae_id="blocks.12.hook_resid_post")
    assert (sae.cfg.d_in, sae.cfg.d_sae, sae.cfg.architecture, sae.cfg.hook_layer) == (D_IN, D_SAE, "standard", 12)
    weights = torch.load(path, weights_only=True) if name.endswith(".pt") else load_file(path)
    weights = weights.get("state_dict", weights)
    ref = ReferenceSae(**{key: value.double().numpy() for key, value in weights.items()})
    x = residuals()
    np.testing.assert_allclose(sae.encode(x).numpy(), ref.encode(x.numpy())[0], rtol=1e-4, atol=1e-4)


def test_state_dict_with_threshold_is_jumprelu(tmp_path):
    path = write_sae_state_dict(tmp_path / "sae.pt", d_in=D_IN, d_sae=D_SAE, architecture="jumprelu")
    assert load_sae(path).cfg.architecture == "jumprelu"


def test_state_dict_takes_settings_from_cfg_folder(tmp_path):
    folder = write_sae_folder(tmp_path / "base", d_in=D_IN, d_sae=D_SAE, apply_b_dec_to_input=False, hook_layer=12)
    path = write_sae_state_dict(tmp_path / "finetuned.pt", d_in=D_IN, d_sae=D_SAE, seed=5)
    sae = load_sae(path, cfg_from=folder)
    assert sae.cfg.apply_b_dec_to_input is False and sae.cfg.source == str(path)
    weights = torch.load(path, weights_only=True)
    assert torch.equal(sae.W_enc, weights["W_enc"])
    ref = ReferenceSae(**{k: v.double().numpy() for k, v in weights.items()}, apply_b_dec_to_input=False)
    x = residuals()
    np.testing.assert_allclose(sae.encode(x).numpy(), ref.encode(x.numpy())[0], rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="cfg_from applies to state-dict files only"):
        load_sae(folder, cfg_from=folder)


class _NotATensor:
    pass


def test_state_dict_is_never_unpickled(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"W_enc": torch.zeros(2, 2), "payload": _NotATensor()}, path)
    with pytest.raises(ValueError, match=f"{path}: holds pickled objects other than tensors, .*_NotATensor"):
        load_sae(path)


def test_state_dict_without_sae_keys(tmp_path):
    torch.save({"weights": torch.zeros(2)}, tmp_path / "x.pt")
    with pytest.raises(ValueError, match=r"not an SAE state dict; expected tensors W_enc, W_dec, b_enc, b_dec .* found \['weights'\]"):
        load_sae(tmp_path / "x.pt")


def test_release_resolves_from_hub_cache(hub_cache):
    write_release_to_hub_cache(hub_cache, "gemma-2b-it-res-jb", d_in=D_IN, d_sae=D_SAE, layout="legacy")
    sae = load_sae("gemma-2b-it-res-jb", "blocks.12.hook_resid_post")
    assert sae.cfg.neuronpedia_id == "gemma-2b-it/12-res-jb"
    assert (sae.cfg.release, sae.cfg.sae_id, sae.cfg.hook_layer) == ("gemma-2b-it-res-jb", "blocks.12.hook_resid_post", 12)
    assert "models--jbloom--Gemma-2b-IT-Residual-Stream-SAEs/snapshots" in sae.cfg.source
    assert sae.name == "gemma-2b-it-res-jb/blocks.12.hook_resid_post"
    # the release's only SAE needs no id
    assert load_sae("gemma-2b-it-res-jb").cfg.sae_id == "blocks.12.hook_resid_post"


def test_release_prefers_the_main_snapshot(hub_cache):
    folder = write_release_to_hub_cache(hub_cache, "gemma-2b-it-res-jb", d_in=D_IN, d_sae=D_SAE)
    older = folder.parents[1] / "aaaa" / folder.name  # sorts before the main revision
    write_sae_folder(older, d_in=D_IN, d_sae=D_SAE * 2)
    assert resolve_release("gemma-2b-it-res-jb", None) == folder


def test_base_release_folds_norm_scaling_factor(hub_cache):
    folder = write_release_to_hub_cache(
        hub_cache, "gemma-2b-res-jb", "blocks.12.hook_resid_post", d_in=D_IN, d_sae=D_SAE, layout="legacy",
        normalize_activations="expected_average_only_in", dtype="float64",
    )
    sae = load_sae("gemma-2b-res-jb", "blocks.12.hook_resid_post")
    assert sae.cfg.normalize_activations == "none" and sae.cfg.norm_scaling_factor == GEMMA_L12_FACTOR
    assert sae.cfg.neuronpedia_id == "gemma-2b/12-res-jb"
    ref = reference_for(folder, input_scale=GEMMA_L12_FACTOR)
    x = residuals()
    ref_f, stats = ref.encode(x.numpy())
    np.testing.assert_allclose(sae.encode(x).numpy(), ref_f, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sae.decode(sae.encode(x)).numpy(), ref.decode(ref_f, stats), rtol=1e-10, atol=1e-10)


def test_expected_average_without_factor_leaves_inputs_unscaled(tmp_path, caplog):
    folder = write_sae_folder(
        tmp_path / "sae", d_in=D_IN, d_sae=D_SAE, layout="legacy", normalize_activations="expected_average_only_in",
        dtype="float64",
    )
    sae = load_sae(folder)
    assert sae.cfg.normalize_activations == "expected_average_only_in"
    assert "no norm_scaling_factor is known" in caplog.text
    np.testing.assert_allclose(sae.encode(residuals()).numpy(), reference_for(folder).encode(residuals().numpy())[0])


def test_folder_named_like_a_release_gets_its_registry_facts(tmp_path):
    folder = write_sae_folder(tmp_path / "gemma_2b_it_blocks.12.hook_resid_post_16384", d_in=D_IN, d_sae=D_SAE)
    cfg = load_sae(folder).cfg
    assert (cfg.release, cfg.neuronpedia_id) == ("gemma-2b-it-res-jb", "gemma-2b-it/12-res-jb")


def test_release_in_user_folder(tmp_path, hub_cache):
    write_sae_folder(tmp_path / "downloads" / "gemma_2b_it_blocks.12.hook_resid_post_16384", d_in=D_IN, d_sae=D_SAE)
    sae = load_sae("gemma-2b-it-res-jb", local_dir=tmp_path / "downloads")
    assert sae.cfg.source.startswith(str(tmp_path / "downloads"))


def test_missing_release_says_what_to_obtain_and_where(hub_cache, tmp_path):
    with pytest.raises(FileNotFoundError) as err:
        load_sae("gemma-2b-res-jb", "blocks.6.hook_resid_post", local_dir=tmp_path / "dl")
    message = str(err.value)
    assert "Hugging Face repo `jbloom/Gemma-2b-Residual-Stream-SAEs`" in message
    assert "folder `gemma_2b_blocks.6.hook_resid_post_16384_anthropic_fast_lr/`" in message
    assert "cfg.json, sae_weights.safetensors (optional sparsity.safetensors)" in message
    assert str(hub_cache / "models--jbloom--Gemma-2b-Residual-Stream-SAEs") in message
    assert str(tmp_path / "dl" / "gemma_2b_blocks.6.hook_resid_post_16384_anthropic_fast_lr") in message
    assert "--local-dir" in message and "no network access is attempted" in message


def test_unknown_release_and_sae_id(hub_cache):
    with pytest.raises(ValueError, match=r"'gemma-7b' is neither an SAE folder or file nor a known release; known releases: \['gemma-2b-it-res-jb', 'gemma-2b-res-jb'\]"):
        load_sae("gemma-7b")
    with pytest.raises(ValueError, match=r"has no SAE id 'blocks.5.hook_resid_post'; valid ids: \['blocks.0.hook_resid_post'"):
        load_sae("gemma-2b-res-jb", "blocks.5.hook_resid_post")
    with pytest.raises(ValueError, match="holds several SAEs; pass an SAE id"):
        load_sae("gemma-2b-res-jb")
    with pytest.raises(FileNotFoundError, match="no such SAE folder or state-dict file"):
        load_sae("missing/sae.pt")


def test_missing_folder_files(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="not a SAELens SAE folder, missing cfg.json, sae_weights.safetensors"):
        load_sae(tmp_path / "empty")


def test_hub_cache_dir_follows_environment(monkeypatch, tmp_path):
    for variable in ("HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE", "HF_HOME", "XDG_CACHE_HOME"):
        monkeypatch.delenv(variable, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert hub_cache_dir() == tmp_path / ".cache" / "huggingface" / "hub"
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    assert hub_cache_dir() == tmp_path / "hf" / "hub"
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "c"))
    assert hub_cache_dir() == tmp_path / "c"


def test_fingerprint_changes_with_weights(tmp_path):
    a = load_sae(write_sae_folder(tmp_path / "a", d_in=D_IN, d_sae=D_SAE, seed=0))
    b = load_sae(write_sae_folder(tmp_path / "b", d_in=D_IN, d_sae=D_SAE, seed=1))
    assert a.fingerprint() != b.fingerprint()
    assert isinstance(a, Sae) and a.describe()["weights_sha256"] is not None
