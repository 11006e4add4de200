"""The bad-input table, area "finite": NaN or Inf in any tensor a step reads, shapes that disagree with their
bytes, and an SAE of another width, each refused in one line naming the file and the tensor or key.

Every case poisons a copy of one input of the finished tiny run (`helpers_attack`) under its own tmp_path.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import pytest
import torch
import yaml
from helpers_attack import Attack, Case, World, assert_refused, registrar
from safetensors import safe_open
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.pi05.checkpoint import EMBEDDING_KEY, LM_PREFIX, VISION_PREFIX
from steering_core.synthetic.sae import write_sae_folder

VALUES = {"nan": math.nan, "inf": math.inf, "neg_inf": -math.inf}
CASES: list[Attack] = []
case = registrar(CASES)


def poison_safetensors(path: Path, name: str, value: float, at: int = 0) -> Path:
    """Set element `at` (flattened) of tensor `name` in a safetensors file to `value` (metadata kept); return the path."""
    tensors = load_file(path)
    with safe_open(path, "pt") as handle:
        metadata = handle.metadata()
    tensors[name].view(-1)[at] = value
    save_file(tensors, path, metadata=metadata)
    return path


def misshape(path: Path, name: str) -> Path:
    """Rewrite a safetensors header so that tensor `name` claims one more row than its bytes hold."""
    data = path.read_bytes()
    length = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + length])
    header[name]["shape"][0] += 1
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 8)
    path.write_bytes(len(text).to_bytes(8, "little") + text + data[8 + length :])
    return path


# ----------------------------------------------------------------------------- demos: convert and filter

DEMO_KEYS = ("actions", "states", "robot_states", "obs/ee_pos", "obs/ee_ori", "obs/ee_states", "obs/gripper_states",
             "obs/joint_states")


def poisoned_demos(world: World, tmp_path: Path, key: str, value: float, demo: str = "demo_1") -> tuple[Path, Path]:
    """Copy the run's demo folder and put `value` into one step of `data/<demo>/<key>` of its first file."""
    folder = tmp_path / "demos"
    shutil.copytree(world.inputs / "inputs" / "demos", folder)
    target = sorted(folder.glob("*.hdf5"))[0]
    with h5py.File(target, "r+") as handle:
        handle[f"data/{demo}/{key}"][1, 0] = value
    return folder, target


def convert_argv(folder: Path, tmp_path: Path) -> list:
    return ["convert", "--input-dir", folder, "--repo-id", "poisoned", "--output-dir", tmp_path / "out",
            "--image-size", "32"]


def demo_case(key: str, value_name: str) -> None:
    @case(f"convert_demo_{key.replace('/', '_')}_{value_name}")
    def attack(world: World, tmp_path: Path) -> Case:
        folder, target = poisoned_demos(world, tmp_path, key, VALUES[value_name])
        return Case(convert_argv(folder, tmp_path), (target.name, f"data/demo_1/{key}", "NaN or Inf"))


for _key in DEMO_KEYS:
    for _value in VALUES:
        demo_case(_key, _value)


@case("convert_demo_all_nan_actions")
def _all_nan_actions(world: World, tmp_path: Path) -> Case:
    folder, target = poisoned_demos(world, tmp_path, "actions", 0.0)
    with h5py.File(target, "r+") as handle:
        actions = handle["data/demo_0/actions"]
        actions[...] = math.nan
    return Case(convert_argv(folder, tmp_path), (target.name, "data/demo_0/actions", "NaN or Inf"))


def filter_case(key: str, value_name: str) -> None:
    @case(f"filter_demo_{key.replace('/', '_')}_{value_name}")
    def attack(world: World, tmp_path: Path) -> Case:
        folder, target = poisoned_demos(world, tmp_path, key, VALUES[value_name], demo="demo_0")
        from steering_core.data.libero import read_instruction

        return Case(["filter", "--input-dir", folder, "--output-dir", tmp_path / "filtered", "--task",
                     read_instruction(target)], (target.name, f"data/demo_0/{key}", "NaN or Inf"))


for _key, _value in (("actions", "nan"), ("states", "inf"), ("obs/joint_states", "neg_inf")):
    filter_case(_key, _value)


# ----------------------------------------------------------------------------- SAEs, slices and headers: steer

def steer_argv(world: World, tmp_path: Path, sae: Path, layer: int = 1, pairs: Path | None = None) -> list:
    return ["steer", "--pairs-config", pairs or world.data / f"layer{layer}_pairs.json", "--output-root",
            tmp_path / "steering", "--layer", str(layer), "--device", "cpu", "--sae", sae]


def sae_copy(world: World, tmp_path: Path, layer: int = 1) -> Path:
    folder = tmp_path / f"sae_layer{layer:02d}"
    shutil.copytree(world.sae(layer), folder)
    return folder


def sae_case(tensor: str, value_name: str) -> None:
    @case(f"steer_sae_{tensor}_{value_name}")
    def attack(world: World, tmp_path: Path) -> Case:
        weights = poison_safetensors(sae_copy(world, tmp_path) / "sae_weights.safetensors", tensor,
                                     VALUES[value_name], at=3)
        return Case(steer_argv(world, tmp_path, weights.parent), (str(weights), f"`{tensor}`", "NaN or Inf"))


for _tensor in ("W_enc", "W_dec", "b_enc", "b_dec"):
    for _value in ("nan", "inf"):
        sae_case(_tensor, _value)


def state_dict_case(suffix: str, tensor: str, value_name: str) -> None:
    @case(f"steer_sae_state_dict{suffix.replace('.', '_')}_{tensor}_{value_name}")
    def attack(world: World, tmp_path: Path) -> Case:
        weights = load_file(world.sae(1) / "sae_weights.safetensors")
        weights[tensor].view(-1)[0] = VALUES[value_name]
        path = tmp_path / f"sae{suffix}"
        if suffix == ".pt":
            torch.save({"state_dict": weights}, path)
        else:
            save_file(weights, path)
        return Case(steer_argv(world, tmp_path, path), (str(path), f"`{tensor}`", "NaN or Inf"))


for _suffix, _tensor, _value in ((".pt", "W_enc", "nan"), (".pt", "b_enc", "inf"), (".safetensors", "W_dec", "neg_inf"),
                                 (".safetensors", "b_dec", "nan")):
    state_dict_case(_suffix, _tensor, _value)


def slice_copy(world: World, tmp_path: Path, layer: int, pair: str = "open_vs_close") -> tuple[Path, Path]:
    """Copy one pair's slices of `layer` and a pairs config reading them; return (pairs config, slice folder)."""
    folder = tmp_path / f"{pair}_slices" / f"layer{layer:02d}"
    shutil.copytree(world.data / "residuals" / f"{pair}_slices" / f"layer{layer:02d}", folder)
    config = json.loads((world.data / f"layer{layer}_pairs.json").read_text())
    config["pairs"] = [entry for entry in config["pairs"] if entry["name"] == pair]
    for entry in config["pairs"]:
        for side in ("positive", "negative"):
            entry[f"{side}_path"] = str(folder / Path(entry[f"{side}_path"]).name)
    path = tmp_path / "pairs.json"
    path.write_text(json.dumps(config))
    return path, folder


def slice_case(layer: int, concept: str, suffix: str, value_name: str) -> None:
    @case(f"steer_slice_layer{layer}_{concept.split()[0]}{suffix.replace('.', '_')}_{value_name}")
    def attack(world: World, tmp_path: Path) -> Case:
        pairs, folder = slice_copy(world, tmp_path, layer)
        config = json.loads(pairs.read_text())
        target = folder / f"{concept}{suffix}"
        if suffix == ".pt":
            rows = torch.load(target, weights_only=True)
            rows[-1, 2] = VALUES[value_name]
            torch.save(rows, target)
        else:
            poison_safetensors(target, "residuals", VALUES[value_name], at=5)
            for entry in config["pairs"]:
                for side in ("positive", "negative"):
                    entry[f"{side}_path"] = str(Path(entry[f"{side}_path"]).with_suffix(".safetensors"))
            pairs.write_text(json.dumps(config))
        return Case(steer_argv(world, tmp_path, world.sae(layer), layer, pairs), (str(target), "NaN or Inf"))


for _layer, _concept, _suffix, _value in (
        (1, "open the top drawer of the cabinet", ".pt", "nan"),
        (1, "close the top drawer of the cabinet", ".pt", "inf"),
        (2, "open the top drawer of the cabinet", ".safetensors", "neg_inf"),
        (2, "close the top drawer of the cabinet", ".safetensors", "nan")):
    slice_case(_layer, _concept, _suffix, _value)


@case("steer_sae_weights_header_disagrees_with_offsets")
def _sae_header(world: World, tmp_path: Path) -> Case:
    weights = misshape(sae_copy(world, tmp_path) / "sae_weights.safetensors", "W_dec")
    return Case(steer_argv(world, tmp_path, weights.parent), (str(weights), "`W_dec`", "disagrees with its data_offsets"))


@case("steer_sae_sparsity_header_disagrees_with_offsets")
def _sparsity_header(world: World, tmp_path: Path) -> Case:
    sparsity = misshape(sae_copy(world, tmp_path) / "sparsity.safetensors", "sparsity")
    return Case(steer_argv(world, tmp_path, sparsity.parent),
                (str(sparsity), "`sparsity`", "disagrees with its data_offsets"))


@case("steer_state_dict_header_disagrees_with_offsets")
def _state_dict_header(world: World, tmp_path: Path) -> Case:
    path = tmp_path / "sae.safetensors"
    shutil.copy(world.sae(1) / "sae_weights.safetensors", path)
    misshape(path, "b_enc")
    return Case(steer_argv(world, tmp_path, path), (str(path), "`b_enc`", "disagrees with its data_offsets"))


@case("steer_slice_header_disagrees_with_offsets")
def _slice_header(world: World, tmp_path: Path) -> Case:
    pairs, folder = slice_copy(world, tmp_path, 1)
    config = json.loads(pairs.read_text())
    entry = config["pairs"][0]
    entry["positive_path"] = str(Path(entry["positive_path"]).with_suffix(".safetensors"))
    pairs.write_text(json.dumps(config))
    target = misshape(Path(entry["positive_path"]), "residuals")
    return Case(steer_argv(world, tmp_path, world.sae(1), 1, pairs),
                (str(target), "`residuals`", "disagrees with its data_offsets"))


# ----------------------------------------------------------------------------- run: preflight before any step

def run_case(name: str, change: Callable[[dict, World, Path], tuple[str, ...]]) -> None:
    """A `run --config` whose config, written under tmp_path with its output root there, is changed by `change`
    (which returns the names the error must hold); preflight must refuse it before any step."""
    @case(f"run_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        config = yaml.safe_load(world.config.read_text())
        config["output_root"] = str(tmp_path / "out")
        names = change(config, world, tmp_path)
        path = tmp_path / "run.yaml"
        path.write_text(yaml.safe_dump(config))
        return Case(["run", "--config", path], ("before the run started", *names))


def checkpoint_copy(config: dict, world: World, tmp_path: Path) -> Path:
    folder = tmp_path / "checkpoint"
    shutil.copytree(world.checkpoint, folder)
    config["model"]["checkpoint"] = str(folder)
    return folder / "model.safetensors"


def poisoned_checkpoint(tensor: str, value_name: str) -> Callable[[dict, World, Path], tuple[str, ...]]:
    def change(config: dict, world: World, tmp_path: Path) -> tuple[str, ...]:
        model = poison_safetensors(checkpoint_copy(config, world, tmp_path), tensor, VALUES[value_name], at=7)
        return str(model), f"`{tensor}`", "NaN or Inf"
    return change


for _name, _tensor, _value in (
        ("embedding_nan", EMBEDDING_KEY, "nan"),
        ("q_proj_layer0_inf", f"{LM_PREFIX}layers.0.self_attn.q_proj.weight", "inf"),
        ("patch_embedding_neg_inf", f"{VISION_PREFIX}embeddings.patch_embedding.weight", "neg_inf"),
        ("action_expert_head_nan", "action_out_proj.weight", "nan")):  # read by the decision capture only
    run_case(f"checkpoint_{_name}", poisoned_checkpoint(_tensor, _value))


def _checkpoint_header(config: dict, world: World, tmp_path: Path) -> tuple[str, ...]:
    tensor = f"{LM_PREFIX}layers.1.mlp.up_proj.weight"
    return str(misshape(checkpoint_copy(config, world, tmp_path), tensor)), tensor, "disagrees with its data_offsets"


run_case("checkpoint_header_disagrees_with_offsets", _checkpoint_header)


def _sae_of_another_width(config: dict, world: World, tmp_path: Path) -> tuple[str, ...]:
    width = config["model"]["arch"]["width"]
    folder = write_sae_folder(tmp_path / "sae_narrow", d_in=width // 2, d_sae=64, hook_layer=2)
    config["sae"]["2"]["path"] = str(folder)
    return str(folder), "layer 2", f"d_in {width // 2}", f"width (model.arch.width) is {width}"


run_case("sae_of_another_width", _sae_of_another_width)


def poisoned_run_sae(tensor: str, value_name: str, layer: int) -> Callable[[dict, World, Path], tuple[str, ...]]:
    def change(config: dict, world: World, tmp_path: Path) -> tuple[str, ...]:
        weights = poison_safetensors(sae_copy(world, tmp_path, layer) / "sae_weights.safetensors", tensor,
                                     VALUES[value_name])
        config["sae"][str(layer)]["path"] = str(weights.parent)
        return str(weights), f"`{tensor}`", "NaN or Inf"
    return change


run_case("sae_w_dec_nan", poisoned_run_sae("W_dec", "nan", 1))
run_case("sae_b_enc_inf", poisoned_run_sae("b_enc", "inf", 2))


def poisoned_run_demo(key: str, value_name: str) -> Callable[[dict, World, Path], tuple[str, ...]]:
    def change(config: dict, world: World, tmp_path: Path) -> tuple[str, ...]:
        folder, target = poisoned_demos(world, tmp_path, key, VALUES[value_name])
        config["sources"]["folders"] = [str(folder)]
        return target.name, f"data/demo_1/{key}", "NaN or Inf"
    return change


run_case("demo_states_nan", poisoned_run_demo("states", "nan"))
run_case("demo_actions_inf", poisoned_run_demo("actions", "inf"))


@pytest.fixture
def no_pipeline(monkeypatch):
    """Fail the test if the pipeline flow starts; keep `run`'s Prefect settings out of the other tests."""
    import flows.pipeline

    monkeypatch.setattr(flows.pipeline, "latent_steering", lambda *a, **k: pytest.fail("the pipeline started"))
    before = dict(os.environ)
    yield
    for key in set(os.environ) - set(before):
        del os.environ[key]


@pytest.mark.parametrize("attack", CASES, ids=lambda f: f.__name__)
def test_refused(attack_world, tmp_path, attack, no_pipeline):
    assert_refused(attack_world, tmp_path, attack)



# ----------------------------------------------------------------------------- where a table case does not fit

def test_capture_refuses_a_nan_checkpoint_before_any_shard(attack_world, tmp_path):
    """capture writes its run spec before loading the model; the tensor is refused as it is read: no shard."""
    folder = tmp_path / "checkpoint"
    shutil.copytree(attack_world.checkpoint, folder)
    tensor = f"{LM_PREFIX}layers.1.mlp.down_proj.weight"
    model = poison_safetensors(folder / "model.safetensors", tensor, math.nan, at=11)
    run_dir = tmp_path / "run"
    result = CliRunner().invoke(app, [
        "capture", "--checkpoint-path", str(folder), "--tokenizer-path", str(attack_world.tokenizer),
        "--lerobot-root", str(attack_world.dataset), "--repo-id", attack_world.dataset.name, "--output-dir",
        str(run_dir), "--layers", "1,2", "--device", "cpu", "--num-workers", "0",
        "--arch-file", str(attack_world.data / "arch.json")])
    assert result.exit_code == 1, result.output
    assert result.output.strip().splitlines() == [result.output.strip()]
    assert f"error: {model}: tensor `{tensor}` holds NaN or Inf (nan at (0, 11))" in result.output
    assert not list(run_dir.rglob("shard-*"))


def test_slice_refuses_a_nan_shard_naming_it(attack_world, tmp_path):
    """A shard holding NaN (read without checksums) stops slicing, naming the shard; no slice folder is written."""
    run_dir = tmp_path / "run"
    shutil.copytree(attack_world.data / "residuals" / "demo", run_dir)
    shard = sorted((run_dir / "instructions" / "layer01").glob("shard-*.safetensors"))[1]
    tensors = load_file(shard)
    with safe_open(shard, "pt") as handle:
        metadata = handle.metadata()
    save_file({**tensors, "residuals": torch.full_like(tensors["residuals"], math.inf)}, shard, metadata=metadata)
    output = tmp_path / "slices"
    manifests = attack_world.data / "manifests"
    result = CliRunner().invoke(app, [
        "slice", "--run-dir", str(run_dir), "--concept-map-path", str(manifests / "open_vs_close_concept_map.json"),
        "--output-dir", str(output), "--layers", "1", "--split", str(manifests / "open_vs_close_split.json"),
        "--no-verify-checksums"])
    assert result.exit_code == 1, result.output
    line = result.output.strip()
    assert line.startswith(f"error: {shard}: tensor `residuals` holds NaN or Inf (inf at ("), line
    assert line.endswith("); expected finite values; the shard is damaged; re-run capture to rewrite it"), line
    assert not (output / "layer01").exists()


def test_json_writer_refuses_nan_naming_the_key(tmp_path):
    from steering_core.storage.fileio import write_json

    path = tmp_path / "manifest.json"
    with pytest.raises(ValueError, match=r"manifest.json: `episodes.1.axis_range` is NaN or Inf"):
        write_json(path, {"episodes": [{"axis_range": 0.5}, {"axis_range": math.nan}]})
    assert list(tmp_path.iterdir()) == []
    write_json(path, {"episodes": [{"axis_range": None}]})
    assert json.loads(path.read_text()) == {"episodes": [{"axis_range": None}]}


def test_served_and_evaluated_vectors_are_checked_finite(attack_world, tmp_path):
    """A NaN direction file is refused by the server's catalog and by evaluation's reader, naming file and tensor."""
    from steering_core.evaluate.directions import pair_directions
    from steering_core.serve.catalog import VectorCatalog

    root = tmp_path / "latent_steering"
    shutil.copytree(attack_world.data / "latent_steering", root)
    direction = poison_safetensors(root / "layer02" / "on_vs_off" / "mean_difference_direction.safetensors",
                                   "direction", math.nan, at=4)
    expected = f"{direction}: tensor `direction` holds NaN or Inf (nan at 4)"
    with pytest.raises(ValueError, match=re.escape(expected)):
        VectorCatalog.scan(root)
    with pytest.raises(ValueError, match=re.escape(expected)):
        pair_directions(direction.parent)
    assert len(VectorCatalog.scan(attack_world.data / "latent_steering")) > 0
