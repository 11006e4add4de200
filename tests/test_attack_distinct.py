"""The bad-input table, area "distinct": inputs that must differ (a pair's two sides, its slices and layer, two
keys of one setting) and one spelling per thing (a scalar of its own type, no converted values, no second name
for a key), each refused in one line naming the file and the key (`helpers_attack.assert_refused`).

Every case changes a copy of one input of the finished tiny run under its own tmp_path. The unit tests at the end
hold the settings' strictness where no command line is natural, and that good inputs stay accepted.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from helpers_attack import Attack, Case, World, assert_refused, config_case, config_text, good, registrar
from pydantic import ValidationError
from safetensors.torch import load_file, save_file

from steering_core.config import CONFIG_FILE, claim_config_file, load_run_config, write_run_config
from steering_core.config.sections import OrchestrationSection, PairSection
from steering_core.demo import PLANTED_DIR, demo_config
from steering_core.rollout.settings import RolloutPair
from steering_core.sae.formats import CFG_FILE, SPARSITY_FILE, WEIGHTS_FILE
from steering_core.vectors.directions import SteeringSettings

PAIR, OTHER = "open_vs_close", "on_vs_off"
OPEN, CLOSE, STOVE_ON = "open the top drawer of the cabinet", "close the top drawer of the cabinet", "turn on the stove"
CASES: list[Attack] = []
case = registrar(CASES)


# ----------------------------------------------------------------------------- a pair's two sides: steer, evaluate


def slices(world: World, pair: str = PAIR, layer: int = 1) -> Path:
    """Return a pair's slices folder of one layer in the finished run."""
    return world.data / "residuals" / f"{pair}_slices" / f"layer{layer:02d}"


def edited_pairs(world: World, tmp_path: Path, edit: Callable[[dict], None], layer: int = 1) -> Path:
    """Return a copy of the run's pairs config of `layer` after `edit` of its first pair."""
    pairs = json.loads((world.data / f"layer{layer}_pairs.json").read_text())
    edit(pairs["pairs"][0])
    path = tmp_path / "pairs.json"
    path.write_text(json.dumps(pairs))
    return path


def steer(world: World, tmp_path: Path, pairs: Path, layer: int = 1, sae: Path | str = "none") -> list:
    return ["steer", "--pairs-config", pairs, "--layer", str(layer), "--sae", sae, "--device", "cpu",
            "--output-root", tmp_path / "steering"]


def pair_case(name: str, edit: Callable[[dict, World, Path], None], *names: str, layer: int = 1) -> None:
    """`steer --layer layer` on the run's pairs config of `layer` whose first pair `edit` changed."""
    @case(f"steer_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        path = edited_pairs(world, tmp_path, lambda pair: edit(pair, world, tmp_path), layer)
        return Case(steer(world, tmp_path, path, layer), (str(path), f"pair {PAIR!r}", *names))


def _same_label(pair: dict, world: World, tmp_path: Path) -> None:
    pair["negative_label"] = pair["positive_label"]


def _same_label_other_case(pair: dict, world: World, tmp_path: Path) -> None:
    pair["negative_label"] = f" {pair['positive_label'].upper()}"


def _same_file(pair: dict, world: World, tmp_path: Path) -> None:
    pair["negative_path"] = pair["positive_path"]


def _same_file_other_spelling(pair: dict, world: World, tmp_path: Path) -> None:
    positive = Path(pair["positive_path"])
    pair["negative_path"] = str(positive.parent / ".." / positive.parent.name / positive.name)


def _other_pairs_slice(layer: int = 1) -> Callable[[dict, World, Path], None]:
    def edit(pair: dict, world: World, tmp_path: Path) -> None:
        pair["positive_path"] = str(slices(world, OTHER, layer) / f"{STOVE_ON}.pt")
    return edit


def _labels_swapped(pair: dict, world: World, tmp_path: Path) -> None:
    pair["positive_label"], pair["negative_label"] = pair["negative_label"], pair["positive_label"]


def _not_in_index(pair: dict, world: World, tmp_path: Path) -> None:
    copy = shutil.copytree(slices(world), tmp_path / "slices" / "layer01")
    shutil.copy(copy / f"{OPEN}.pt", copy / "extra.pt")
    pair["positive_path"], pair["negative_path"] = str(copy / "extra.pt"), str(copy / f"{CLOSE}.pt")


def _two_concept_maps(pair: dict, world: World, tmp_path: Path) -> None:
    copy = shutil.copytree(slices(world), tmp_path / "slices" / "layer01")
    index = json.loads((copy / "index.json").read_text())
    index["concept_map"] = str(world.data / "manifests" / f"{OTHER}_concept_map.json")
    (copy / "index.json").write_text(json.dumps(index))
    pair["negative_path"] = str(copy / f"{CLOSE}.pt")


pair_case("same_label", _same_label, "positive_label and negative_label are both")
pair_case("same_label_other_case", _same_label_other_case, "positive_label and negative_label are both")
pair_case("same_file", _same_file, "positive_path and negative_path are both")
pair_case("same_file_other_spelling", _same_file_other_spelling, "positive_path and negative_path are both")
pair_case("other_pairs_slice", _other_pairs_slice(), f"holds concept {STOVE_ON!r}", f"positive_label {OPEN!r}")
pair_case("labels_swapped_files_kept", _labels_swapped, f"holds concept {OPEN!r}", f"positive_label {CLOSE!r}")
pair_case("file_not_in_index", _not_in_index, "extra.pt is not a slice its index.json lists")
pair_case("sides_from_two_concept_maps", _two_concept_maps, "different concept maps")


def evaluate(world: World, tmp_path: Path, pairs: Path, layer: int) -> list:
    """`evaluate` of the run's pairs config `pairs` at `layer` (the rest of its working command line)."""
    argv = [str(word) for word in good(world, tmp_path)["evaluate"]]
    argv[argv.index("--pairs-config") + 1], argv[argv.index("--layer") + 1] = str(pairs), str(layer)
    return ["evaluate", *argv]


def wrong_layer(name: str, argv: Callable[[World, Path, Path, int], list], given: int, asked: int) -> None:
    """A command asked for layer `asked` with the run's pairs config of layer `given`."""
    @case(name)
    def attack(world: World, tmp_path: Path) -> Case:
        pairs = world.data / f"layer{given}_pairs.json"
        return Case(argv(world, tmp_path, pairs, asked), (str(pairs), f"holds layer {given} slices",
                                                          f"expected layer {asked}"))


wrong_layer("steer_layer2_slices_under_layer1", steer, 2, 1)
wrong_layer("steer_layer1_slices_under_layer2_with_its_sae",
            lambda world, tmp_path, pairs, layer: steer(world, tmp_path, pairs, layer, world.sae(layer)), 1, 2)
wrong_layer("evaluate_layer1_slices_under_layer2", evaluate, 1, 2)


@case("evaluate_other_pairs_slice")
def _evaluate_other_slice(world: World, tmp_path: Path) -> Case:
    pairs = edited_pairs(world, tmp_path, lambda pair: _other_pairs_slice(2)(pair, world, tmp_path), 2)
    return Case(evaluate(world, tmp_path, pairs, 2), (str(pairs), f"holds concept {STOVE_ON!r}"))


# ----------------------------------------------------------------------------- SAE files: steer --sae


def sae_case(name: str, spoil: Callable[[Path], Path], *names: str) -> None:
    """`steer --sae` with a copy of layer 1's SAE folder that `spoil` changed; its error names the file `spoil`
    returns and `names`."""
    @case(f"steer_sae_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        folder = shutil.copytree(world.sae(1), tmp_path / "sae_layer01")
        return Case(steer(world, tmp_path, world.data / "layer1_pairs.json", 1, folder), (str(spoil(folder)), *names))


def cfg_edit(edit: Callable[[dict], None]) -> Callable[[Path], Path]:
    def spoil(folder: Path) -> Path:
        cfg = json.loads((folder / CFG_FILE).read_text())
        edit(cfg)
        (folder / CFG_FILE).write_text(json.dumps(cfg))
        return folder / CFG_FILE
    return spoil


def tensor_edit(file: str, name: str, value: Callable[[torch.Tensor], torch.Tensor]) -> Callable[[Path], Path]:
    def spoil(folder: Path) -> Path:
        tensors = load_file(folder / file)
        tensors[name] = value(tensors[name]).contiguous()
        save_file(tensors, folder / file)
        return folder / file
    return spoil


def _topk(k: object = None, **extra: object) -> Callable[[dict], None]:
    def edit(cfg: dict) -> None:
        cfg.update({"architecture": "topk", **extra})
        if k is not None:
            cfg["k"] = k
    return edit


def _legacy_with_both_hook_names(cfg: dict) -> None:
    metadata = cfg.pop("metadata")
    cfg.update({key: value for key, value in metadata.items() if key != "sae_lens_version"})
    cfg["hook_point"] = cfg["hook_name"]


sae_case("topk_without_k", cfg_edit(_topk()), "unusable SAE config", "`k` is missing, expected a positive integer")
sae_case("topk_k_as_string", cfg_edit(_topk("4")), "`k` is '4', expected a positive integer")
sae_case("topk_k_as_float", cfg_edit(_topk(4.0)), "`k` is 4.0, expected a positive integer")
sae_case("topk_k_as_bool", cfg_edit(_topk(True)), "`k` is True, expected a positive integer")
sae_case("topk_with_relu", cfg_edit(_topk(4, activation_fn="relu")), "`activation_fn` is 'relu'")
sae_case("d_in_as_bool", cfg_edit(lambda cfg: cfg.update(d_in=True)), "`d_in` is True, expected a positive integer")
sae_case("flag_as_string", cfg_edit(lambda cfg: cfg.update(apply_b_dec_to_input="false")),
         "`apply_b_dec_to_input` is 'false', expected true or false")
sae_case("flag_as_int", cfg_edit(lambda cfg: cfg.update(rescale_acts_by_decoder_norm=0)),
         "`rescale_acts_by_decoder_norm` is 0, expected true or false")
sae_case("hook_name_twice", cfg_edit(lambda cfg: cfg.update(hook_name="blocks.2.hook_resid_post")),
         "`hook_name` is given at the top level and in `metadata`")
sae_case("meta_and_metadata", cfg_edit(lambda cfg: cfg.update(meta=cfg["metadata"])), "`metadata` and `meta`")
sae_case("legacy_and_current_hook_name", cfg_edit(_legacy_with_both_hook_names), "`hook_point` and `hook_name`")
sae_case("sparsity_short", tensor_edit(SPARSITY_FILE, "sparsity", lambda t: t[:-1]),
         "`sparsity` is (255,)", "expected (256,) floats")
sae_case("sparsity_per_input", tensor_edit(SPARSITY_FILE, "sparsity", lambda t: t[:64]), "expected (256,) floats")
sae_case("sparsity_integers", tensor_edit(SPARSITY_FILE, "sparsity", lambda t: t.long()), "torch.int64")
sae_case("w_dec_all_zero", tensor_edit(WEIGHTS_FILE, "W_dec", torch.zeros_like), "`W_dec` is all zeros")
sae_case("w_enc_all_zero", tensor_edit(WEIGHTS_FILE, "W_enc", torch.zeros_like), "`W_enc` is all zeros")


# ----------------------------------------------------------------------------- run configs: capture --config


def config(name: str, edit: Callable[[dict, World, Path], None], *names: str) -> None:
    """`capture --config` of the run's config after `edit`; its error names the file and `names`."""
    @case(f"config_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        return config_case(tmp_path, config_text(world, tmp_path, lambda data: edit(data, world, tmp_path)), *names)


def setting(name: str, section: str, key: str, value: object, expected: str) -> None:
    """A run config whose `section.key` holds `value`, a value of another type that pydantic would convert."""
    def edit(data: dict, world: World, tmp_path: Path) -> None:
        data.setdefault(section, {})[key] = value
    config(name, edit, f"{section}.{key}: input should be a valid {expected}", f"found {value!r}")


setting("int_as_string", "orchestration", "resubmits", "2", "integer")
setting("int_as_float", "rollout", "episodes", 2.0, "integer")
setting("int_as_bool", "evaluate", "noise_seeds", True, "integer")
setting("bool_as_int", "rollout", "videos", 1, "boolean")
setting("bool_as_float", "steering", "include_decoder_bias", 1.0, "boolean")
setting("bool_as_string", "slicing", "verify_checksums", "yes", "boolean")
setting("float_as_string", "orchestration", "poll_seconds", "5", "number")
setting("float_as_bool", "evaluate", "holdout_fraction", True, "number")
setting("string_as_int", "capture", "device", 0, "string")


def _layer_as_string(data: dict, world: World, tmp_path: Path) -> None:
    data["layers"] = ["1", 2]


def _mode_and_former_name(data: dict, world: World, tmp_path: Path) -> None:
    data["orchestration"] = {"mode": "local", "capture": "deployment"}


def _sae_layer_twice(data: dict, world: World, tmp_path: Path) -> None:
    data["sae"][1] = {"path": str(world.sae(2))}  # beside the key '1' written as a string


def _sae_layer_padded(data: dict, world: World, tmp_path: Path) -> None:
    data["sae"]["01"] = data["sae"].pop("1")


def _existing(where: Callable[[World], Path]) -> Callable[[dict, World, Path], None]:
    def edit(data: dict, world: World, tmp_path: Path) -> None:
        del data["sources"]
        data["dataset"] = {"existing": str(world.dataset)}
        data["output_root"] = str(where(world))
    return edit


def _rename(mapping: Callable[[dict], dict]) -> Callable[[dict, World, Path], None]:
    def edit(data: dict, world: World, tmp_path: Path) -> None:
        data["pairs"][0]["rename"] = mapping(data["pairs"][0])
    return edit


def _rollout_negative(task: object) -> Callable[[dict, World, Path], None]:
    def edit(data: dict, world: World, tmp_path: Path) -> None:
        sides = data["rollout"]["pairs"][PAIR]
        sides["negative"] = dict(sides["positive"]) if task is None else {"suite": "libero_90", "task": task}
        if task is not None:
            sides["positive"] = {"suite": "libero_90", "task": "open the top drawer of the cabinet"}
    return edit


config("layer_as_string", _layer_as_string, "layers[0]: input should be a valid integer", "found '1'")
config("mode_and_former_name", _mode_and_former_name, "orchestration.capture", "the former name of `mode`")
config("sae_layer_twice", _sae_layer_twice, "sae: keys", "both name layer 1")
config("sae_layer_zero_padded", _sae_layer_padded, "sae: key '01'", "e.g. 1")
config("output_root_is_existing_dataset", _existing(lambda world: world.dataset),
       "output_root", "is dataset.existing", "never written")
config("output_root_inside_existing_dataset", _existing(lambda world: world.dataset / "out"),
       "output_root", "inside dataset.existing")
config("rename_both_tasks_to_one_concept", _rename(lambda pair: {pair["positive"]: "drawer", pair["negative"]: "drawer"}),
       "pairs[0]", "one concept 'drawer'")
config("rename_positive_to_negative_task", _rename(lambda pair: {pair["positive"]: pair["negative"]}),
       "pairs[0]", "one concept")
config("rollout_same_task_index", _rollout_negative(None), f"rollout.pairs.{PAIR}", "both libero_90[7]")
config("rollout_same_instruction", _rollout_negative(" Open the top drawer of the cabinet"),
       f"rollout.pairs.{PAIR}", "two different LIBERO tasks")


# ----------------------------------------------------------------------------- demo --output-dir


def demo_case(name: str, *folder: str) -> None:
    """`demo --output-dir DIR` where `DIR/<folder>/run.yaml` holds another run's config."""
    @case(f"demo_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        path = tmp_path.joinpath("out", *folder, CONFIG_FILE)
        path.parent.mkdir(parents=True)
        shutil.copy(world.config, path)  # the attacked run's own config, not this folder's demo
        return Case(["demo", "--output-dir", tmp_path / "out", "--demos-per-task", "2"],
                    (str(path), "already holds another run config"))


demo_case("over_another_run_yaml")
demo_case("over_another_planted_run_yaml", PLANTED_DIR)


@pytest.mark.parametrize("attack", CASES, ids=lambda f: f.__name__)
def test_refused(attack_world, tmp_path, attack):
    assert_refused(attack_world, tmp_path, attack)


def test_the_table_holds_every_case_once():
    assert len({attack.__name__ for attack in CASES}) == len(CASES) >= 45


# ----------------------------------------------------------------------------- settings: unit tests


@pytest.mark.parametrize(("values", "problem"), [
    ({"resubmits": "2"}, "int_type"), ({"resubmits": 2.0}, "int_type"), ({"resubmits": False}, "int_type"),
    ({"poll_seconds": "5"}, "float_type"), ({"poll_seconds": True}, "float_type"),
])
def test_a_value_that_merely_converts_is_refused(values, problem):
    with pytest.raises(ValidationError) as err:
        OrchestrationSection.model_validate(values)
    assert [error["type"] for error in err.value.errors()] == [problem]


def test_native_yaml_and_json_values_pass():
    """An int where a float is wanted, lists for tuples and strings for paths are what YAML and JSON give."""
    section = OrchestrationSection.model_validate({"poll_seconds": 5, "resubmits": 0})
    assert (section.poll_seconds, section.resubmits) == (5.0, 0)
    settings = SteeringSettings.model_validate({"pairs_config": "p.json", "include_decoder_bias": True, "layer": 3})
    assert (settings.pairs_config, settings.include_decoder_bias, settings.layer) == (Path("p.json"), True, 3)


def test_a_run_config_written_and_read_again_is_the_same(tmp_path):
    """Layer keys come back from YAML as the strings "1", "2": mapping keys keep their conversion."""
    config = demo_config(tmp_path)
    path = write_run_config(config, tmp_path / CONFIG_FILE)
    assert "'1':" in path.read_text()
    assert load_run_config(path) == config
    claim_config_file(path, config)  # the demo's own run.yaml is its to rewrite
    with pytest.raises(ValueError, match="already holds another run config"):
        claim_config_file(path, config.model_copy(update={"name": "other"}))


def test_pairs_and_rollout_pairs_with_two_sides_pass():
    pair = PairSection(name="p", positive=OPEN, negative=CLOSE, rename={OPEN: "open", CLOSE: "close"})
    assert (pair.concept(OPEN), pair.concept(CLOSE)) == ("open", "close")
    tasks = RolloutPair.model_validate({"positive": {"suite": "libero_90", "task": 7},
                                        "negative": {"suite": "libero_10", "task": 7}})
    assert tasks.positive.suite != tasks.negative.suite


def test_the_former_name_alone_is_still_read():
    assert OrchestrationSection.model_validate({"capture": "local"}).mode == "local"
