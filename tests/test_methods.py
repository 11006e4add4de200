"""Direction methods through phase 3: the registry, `sae`, `mean_difference`, `sae_top_k`, `file`, the unit files
with their clamp levels, and the refusals (one line naming the pair, layer and setting, nothing written)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from steering_core.sae.model import load_sae
from steering_core.synthetic.sae import write_sae_folder
from steering_core.vectors.directions import SteeringSettings, compute_steering
from steering_core.vectors.methods import METHODS, method
from steering_core.vectors.methods.direction_file import read_method_direction
from steering_core.vectors.methods.registry import register_method

D_IN, D_SAE = 12, 40


def write_pair(folder: Path, shift: float = 1.0) -> Path:
    """Write two concept slices (.pt + .safetensors with episodes, three episodes each) and a pairs config."""
    generator = torch.Generator().manual_seed(0)
    offset = torch.randn(D_IN, generator=generator)
    paths = {}
    for side, sign, first in (("positive", 1.0, 0), ("negative", -1.0, 10)):
        rows = (torch.randn(30, D_IN, generator=generator) + sign * shift * offset + 0.2).float()
        path = folder / "slices" / f"{side}.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(rows, path)
        save_file({"residuals": rows, "episode_index": torch.arange(first, first + 3).repeat_interleave(10)},
                  path.with_suffix(".safetensors"))
        paths[side] = path
    config = {"pairs": [{"name": "p", "positive_label": "pos", "positive_path": str(paths["positive"]),
                         "negative_label": "neg", "negative_path": str(paths["negative"])}]}
    (folder / "pairs.json").write_text(json.dumps(config))
    return folder / "pairs.json"


def rows(folder: Path, side: str) -> torch.Tensor:
    return torch.load(folder / "slices" / f"{side}.pt", weights_only=True).double()


def settings(folder: Path, **overrides) -> SteeringSettings:
    sae = write_sae_folder(folder / "sae", d_in=D_IN, d_sae=D_SAE, dtype="float64") if not (folder / "sae").exists() \
        else folder / "sae"
    values = dict(pairs_config=write_pair(folder), output_root=folder / "out", sae=str(sae), layer=12,
                  batch_size=8, device="cpu", top_k=5)
    return SteeringSettings(**(values | overrides))


def test_each_method_writes_a_unit_direction_with_the_concepts_mean_levels(tmp_path):
    layer = compute_steering(settings(tmp_path, methods=("sae", "mean_difference", "sae_top_k")))
    summary = json.loads((layer / "p" / "directions.json").read_text())
    assert list(summary["methods"]) == ["sae", "mean_difference", "sae_top_k"]
    positive, negative = rows(tmp_path, "positive"), rows(tmp_path, "negative")
    sae = load_sae(tmp_path / "sae")
    latent = sae.encode(positive).mean(0) - sae.encode(negative).mean(0)  # naive: every row encoded at once
    top = latent.abs().topk(5).indices
    kept = torch.zeros_like(latent).index_copy_(0, top, latent[top])
    expected = {"mean_difference": positive.mean(0) - negative.mean(0), "sae": latent @ sae.W_dec.double(),
                "sae_top_k": kept @ sae.W_dec.double()}
    for name, vector in expected.items():
        stored = read_method_direction(layer / "p" / summary["methods"][name]["file"])
        assert stored.method == name and stored.pair == "p" and stored.layer == 12
        assert float(stored.direction.norm()) == pytest.approx(1.0, abs=1e-6)
        torch.testing.assert_close(stored.direction.double(), vector / vector.norm(), rtol=0, atol=1e-5)
        assert stored.norm == pytest.approx(float(vector.norm()), rel=1e-5)
        # the levels: each concept's rows projected on the unit direction, averaged
        unit = stored.direction.double()
        assert stored.levels == pytest.approx((float((negative @ unit).mean()), float((positive @ unit).mean())),
                                              rel=1e-5)
        assert stored.levels[1] > stored.levels[0]  # every direction points to the positive concept
        assert summary["methods"][name]["positive_level"] == stored.levels[1]
    assert summary["methods"]["sae_top_k"]["record"]["latents"] == top.tolist()


def test_without_an_sae_the_defaults_are_the_residual_space_methods(tmp_path):
    from steering_core.vectors.directions import DEFAULT_METHODS

    chosen = settings(tmp_path, sae=None)
    assert chosen.method_list(False) == tuple(name for name in DEFAULT_METHODS if not METHODS[name].needs_sae)
    with pytest.raises(ValueError, match=r"layer 12: steering.methods \['sae'\]: \['sae'\] need an SAE"):
        settings(tmp_path, sae=None, methods=("sae",)).method_list(False)


def test_the_registry_refuses_unknown_and_repeated_names():
    with pytest.raises(ValueError, match=r"unknown direction method 'diffmean'; registered: \["):
        method("diffmean")
    with pytest.raises(ValueError, match="'sae' is already registered"):
        register_method("sae", "again")(lambda data: None)
    with pytest.raises(ValueError, match=r"\['nope'\] not registered"):
        SteeringSettings(pairs_config=Path("x"), methods=("sae", "nope"))
    with pytest.raises(ValueError, match="each once"):
        SteeringSettings(pairs_config=Path("x"), methods=("sae", "sae"))
    with pytest.raises(ValueError, match="direction_file is not set"):
        SteeringSettings(pairs_config=Path("x"), methods=("file",))


def test_a_supplied_file_is_evaluated_as_it_is_and_its_source_recorded(tmp_path):
    vector = torch.randn(D_IN, generator=torch.Generator().manual_seed(3))
    save_file({"v": vector}, tmp_path / "p_12.safetensors")
    layer = compute_steering(settings(tmp_path, methods=("file",),
                                      direction_file=str(tmp_path / "{pair}_{layer}.safetensors")))
    summary = json.loads((layer / "p" / "directions.json").read_text())
    stored = read_method_direction(layer / "p" / summary["methods"]["file"]["file"])
    torch.testing.assert_close(stored.direction, vector / vector.norm())
    assert summary["methods"]["file"]["record"]["source"] == str((tmp_path / "p_12.safetensors").resolve())


@pytest.mark.parametrize(("tensors", "found"), [
    ({"v": torch.ones(D_IN + 1)}, r"`v` is \(13,\) float32, expected \(12,\) float"),
    ({"v": torch.full((D_IN,), math.nan)}, "tensor `direction` holds NaN or Inf"),
    ({"v": torch.zeros(D_IN)}, "the direction's length is 0, below float32's smallest normal number"),
    ({"v": torch.full((D_IN,), 1e-45)}, r"the direction's length is 4.85e-45, below float32's smallest normal"),
    ({"v": torch.ones(D_IN, dtype=torch.int32)}, r"`v` is \(12,\) int32"),
    ({"a": torch.ones(D_IN), "b": torch.ones(D_IN)}, r"holds 2 tensors \['a', 'b'\], expected one direction"),
    (None, "file not found"),
    (b"not a safetensors file", "not a readable safetensors file"),
])
def test_a_bad_supplied_file_is_one_line_naming_the_pair_layer_and_setting_and_nothing_is_written(
        tmp_path, tensors, found):
    path = tmp_path / "p_12.safetensors"
    if isinstance(tensors, dict):
        save_file(tensors, path)
    elif tensors is not None:
        path.write_bytes(tensors)
    chosen = settings(tmp_path, methods=("mean_difference", "file"),
                      direction_file=str(tmp_path / "{pair}_{layer}.safetensors"))
    with pytest.raises(ValueError, match=f"pair 'p', layer 12, steering.direction_file {path}: {found}") as err:
        compute_steering(chosen)
    assert "\n" not in str(err.value)
    assert not (tmp_path / "out").exists()  # refused before the SAE pass


def test_a_template_with_other_fields_is_refused(tmp_path):
    chosen = settings(tmp_path, methods=("file",), direction_file=str(tmp_path / "{pair}_{run}.safetensors"))
    with pytest.raises(ValueError, match=r"only \{pair\} and \{layer\} may be filled in"):
        compute_steering(chosen)


def test_the_directions_identity_covers_every_method_setting_and_the_rows_they_read(tmp_path):
    """Mutate each input a method reads: the pair-directions task's cache key must change with it."""
    from tasks.sae import direction_inputs, stats_files

    vector = torch.randn(D_IN, generator=torch.Generator().manual_seed(3))
    save_file({"v": vector}, tmp_path / "p_12.safetensors")
    base = settings(tmp_path, methods=("mean_difference", "file"),
                    direction_file=str(tmp_path / "{pair}_{layer}.safetensors"))
    key = direction_inputs(base)
    for field, value in (("methods", ("file",)), ("top_k", 6), ("probe_folds", 3), ("probe_c", 0.5),
                         ("effect_min_episodes", 3), ("include_decoder_bias", True),
                         ("direction_file", str(tmp_path / "{pair}_{layer}_b.safetensors"))):
        assert direction_inputs(base.model_copy(update={field: value})) != key, field
    save_file({"v": vector * 2}, tmp_path / "p_12.safetensors")  # the supplied file's content
    assert direction_inputs(base) != key
    layer = compute_steering(base)
    stats = next((layer / "concepts").glob("pos-*.json"))
    before = stats_files(str(stats))
    slices = tmp_path / "slices" / "positive.safetensors"  # the rows and episodes the probe and sae_effect read
    episodes = torch.arange(3).repeat_interleave(10).flip(0)
    save_file({"residuals": rows(tmp_path, "positive").float(), "episode_index": episodes}, slices)
    assert stats_files(str(stats)) != before
