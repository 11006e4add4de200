"""The bad-input table, area "overwrite": an output never overwrites an input. Every command with an output option,
and a run config's `output_root`, given an output that is, contains or lies inside one of its own inputs (spelled
through `..` or a symlink too), is refused before anything is written, in one line naming both
(`steering_core.storage.overwrites`; `helpers_attack.assert_refused`).

The inputs a case could harm are copies under its own tmp_path, so even a command that wrote would leave the finished
run alone.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml
from helpers_attack import Attack, Case, World, assert_refused, config_case, config_text, dataset_copy, good, registrar

from steering_core.storage.overwrites import overwrite_problem

CASES: list[Attack] = []
case = registrar(CASES)
MANIFEST = "open_vs_close.json"
REFUSED = "an input is read, never written"


def command(world: World, tmp_path: Path, name: str, **options: object) -> list:
    """`name`'s working command line with `options` (`--flag`: value) set."""
    argv = [str(word) for word in good(world, tmp_path)[name]]
    for flag, value in options.items():
        argv[argv.index(flag) + 1] = str(value)
    return [name, *argv]


def copied(source: Path, tmp_path: Path, *parts: str) -> Path:
    """A copy of the file or folder `source` at `tmp_path/parts`."""
    target = tmp_path.joinpath(*parts)
    target.parent.mkdir(parents=True, exist_ok=True)
    if source.is_dir():
        return Path(shutil.copytree(source, target, symlinks=True))
    return Path(shutil.copy(source, target))


def manifest_copy(world: World, tmp_path: Path) -> Path:
    return copied(world.data / "manifests" / MANIFEST, tmp_path, "manifests", MANIFEST)


# ----------------------------------------------------------------------------- JSON outputs over their inputs


@case("manifest_output_is_the_datasets_info_json")
def _manifest_over_info(world: World, tmp_path: Path) -> Case:
    dataset = dataset_copy(world, tmp_path)
    info = dataset / "meta" / "info.json"
    argv = command(world, tmp_path, "manifest", **{"--lerobot-root": dataset, "--output": info})
    return Case(argv, (f"--output {info} lies inside --lerobot-root {dataset}", REFUSED))


@case("manifest_output_inside_the_dataset_through_dotdot")
def _manifest_dotdot(world: World, tmp_path: Path) -> Case:
    dataset = dataset_copy(world, tmp_path)
    output = dataset / "meta" / ".." / "manifest.json"
    argv = command(world, tmp_path, "manifest", **{"--lerobot-root": dataset, "--output": output})
    return Case(argv, (f"--output {output} lies inside --lerobot-root {dataset}",))


@case("split_output_is_its_manifest")
def _split_over_manifest(world: World, tmp_path: Path) -> Case:
    manifest = manifest_copy(world, tmp_path)
    argv = command(world, tmp_path, "split", **{"--manifest": manifest, "--output": manifest})
    return Case(argv, (f"--output {manifest} is --manifest {manifest}", REFUSED))


@case("split_output_a_symlink_to_its_manifest")
def _split_through_link(world: World, tmp_path: Path) -> Case:
    manifest = manifest_copy(world, tmp_path)
    link = tmp_path / "split.json"
    link.symlink_to(manifest)
    argv = command(world, tmp_path, "split", **{"--manifest": manifest, "--output": link})
    return Case(argv, (f"--output {link} is --manifest {manifest}",))


@case("concept_map_output_is_its_manifest")
def _concept_map_over_manifest(world: World, tmp_path: Path) -> Case:
    manifest = manifest_copy(world, tmp_path)
    argv = command(world, tmp_path, "concept-map", **{"--manifest-path": manifest, "--output-path": manifest})
    return Case(argv, (f"--output-path {manifest} is --manifest-path {manifest}",))


@case("concept_map_output_is_its_rename_map")
def _concept_map_over_rename(world: World, tmp_path: Path) -> Case:
    rename = tmp_path / "rename.json"
    rename.write_text(json.dumps({}))
    argv = [*command(world, tmp_path, "concept-map", **{"--output-path": rename}), "--concept-map", rename]
    return Case(argv, (f"--output-path {rename} is --concept-map {rename}",))


# ----------------------------------------------------------------------------- folders over their inputs


@case("filter_output_contains_its_input")
def _filter_around_input(world: World, tmp_path: Path) -> Case:
    demos = copied(world.inputs / "inputs" / "demos", tmp_path, "work", "demos")
    argv = command(world, tmp_path, "filter", **{"--input-dir": demos, "--output-dir": demos.parent})
    return Case(argv, (f"--output-dir {demos.parent} contains --input-dir {demos}",))


@case("convert_output_is_its_input")
def _convert_over_input(world: World, tmp_path: Path) -> Case:
    filtered = copied(world.data / "filtered", tmp_path, "filtered")
    argv = command(world, tmp_path, "convert", **{"--input-dir": filtered, "--output-dir": filtered})
    return Case(argv, (f"--output-dir {filtered} is --input-dir {filtered}",))


@case("capture_output_inside_the_dataset")
def _capture_into_dataset(world: World, tmp_path: Path) -> Case:
    dataset = dataset_copy(world, tmp_path)
    argv = command(world, tmp_path, "capture", **{"--lerobot-root": dataset, "--output-dir": dataset / "run"})
    return Case(argv, (f"--output-dir {dataset / 'run'} lies inside --lerobot-root {dataset}",))


@case("capture_output_is_the_checkpoint")
def _capture_over_checkpoint(world: World, tmp_path: Path) -> Case:
    checkpoint = copied(world.checkpoint, tmp_path, "pi05_tiny")
    argv = command(world, tmp_path, "capture", **{"--checkpoint-path": checkpoint, "--output-dir": checkpoint})
    return Case(argv, (f"--output-dir {checkpoint} is --checkpoint-path {checkpoint}",))


@case("slice_output_contains_its_concept_map")
def _slice_around_concept_map(world: World, tmp_path: Path) -> Case:
    concept_map = copied(world.data / "manifests" / "open_vs_close_concept_map.json", tmp_path, "slices", "map.json")
    argv = command(world, tmp_path, "slice", **{"--concept-map-path": concept_map, "--output-dir": concept_map.parent})
    return Case(argv, (f"--output-dir {concept_map.parent} contains --concept-map-path {concept_map}",))


@case("train_sae_output_inside_its_run")
def _train_into_run(world: World, tmp_path: Path) -> Case:
    run = copied(world.data / "residuals" / "demo", tmp_path, "run")
    argv = command(world, tmp_path, "train-sae", **{"--run-dir": run, "--output-dir": run / "sae"})
    return Case(argv, (f"--output-dir {run / 'sae'} lies inside --run-dir {run}",))


@case("steer_layer_folder_is_the_slices_folder")
def _steer_over_slices(world: World, tmp_path: Path) -> Case:
    slices = copied(world.data / "residuals" / "open_vs_close_slices", tmp_path, "slices")
    pairs = json.loads((world.data / "layer1_pairs.json").read_text())
    for pair in pairs["pairs"]:
        for side in ("positive_path", "negative_path"):
            pair[side] = str(slices / "layer01" / Path(pair[side]).name)
    pairs["pairs"] = pairs["pairs"][:1]
    config = tmp_path / "pairs.json"
    config.write_text(json.dumps(pairs))
    argv = command(world, tmp_path, "steer", **{"--pairs-config": config, "--output-root": slices})
    return Case(argv, (f"output_root's layer01 {slices / 'layer01'} contains pair 'open_vs_close'",))


@case("evaluate_output_contains_its_pairs_config")
def _evaluate_around_pairs(world: World, tmp_path: Path) -> Case:
    pairs = copied(world.data / "layer1_pairs.json", tmp_path, "eval", "pairs.json")
    argv = command(world, tmp_path, "evaluate", **{"--pairs-config": pairs, "--output-root": pairs.parent})
    return Case(argv, (f"--output-root {pairs.parent} contains --pairs-config {pairs}",))


@case("serve_episodes_file_is_its_api_key_file")
def _serve_over_key(world: World, tmp_path: Path) -> Case:
    key = tmp_path / "key.txt"
    key.write_text("secret-key\n")
    argv = [*command(world, tmp_path, "serve", **{"--vectors": tmp_path / "no_vectors"}), "--api-key-file", key,
            "--episodes-file", key]
    return Case(argv, (f"--episodes-file {key} is --api-key-file {key}",))


# ----------------------------------------------------------------------------- a run config's output_root


def run_config(name: str, where: str, relation: str, key: str) -> None:
    """`capture --config` of a run whose input `key` is a copy under tmp_path and whose output_root `where` is
    relative to it ("." the input itself, ".." its folder, "out" inside it)."""
    @case(f"config_output_root_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        data = yaml.safe_load(world.config.read_text(encoding="utf-8"))
        section, field = key.split(".", 1)
        holder = data[section]
        if section == "sae":
            layer, field = field.split(".")
            holder = holder[layer]
        original = holder[field][0] if field == "folders" else holder[field]
        source = copied(Path(original), tmp_path, "inputs", Path(original).name)
        holder[field] = [str(source)] if field == "folders" else str(source)
        root = (source / where).resolve() if where != "out" else source / "out"
        text = config_text(world, tmp_path, lambda config: config.update({**data, "output_root": str(root)}))
        return config_case(tmp_path, text, f"output_root {root} {relation} {key}", "an input of the run")


run_config("is_the_demo_sources", ".", "is", "sources.folders")
run_config("inside_the_demo_sources", "out", "lies inside", "sources.folders")
run_config("is_the_checkpoint", ".", "is", "model.checkpoint")
run_config("contains_the_checkpoint", "..", "contains", "model.checkpoint")
run_config("contains_the_tokenizer", "..", "contains", "model.tokenizer")
run_config("is_an_sae", ".", "is", "sae.1.path")


@pytest.mark.parametrize("attack", CASES, ids=lambda f: f.__name__)
def test_refused(attack_world, tmp_path, attack):
    assert_refused(attack_world, tmp_path, attack)


def test_the_table_holds_every_case_once():
    assert len({attack.__name__ for attack in CASES}) == len(CASES) >= 20


def test_outputs_apart_from_inputs_pass(tmp_path):
    """Siblings, a common parent and a name that merely starts like the input's are apart."""
    inputs = {"--input": tmp_path / "data" / "in", "--list": [tmp_path / "a.json", None], "--none": None}
    for output in (tmp_path / "data" / "out", tmp_path / "data" / "in2", tmp_path / "b.json"):
        assert overwrite_problem({"--output": output}, inputs) is None
    assert overwrite_problem({"--output": None}, inputs) is None
