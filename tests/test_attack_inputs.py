"""The bad-input table, inputs: names that would leave the output root, URLs given as paths, binary or
ambiguous (a key given twice) JSON and YAML, pickled slices, sizes beyond what a step can hold, and files
derived from one dataset combined with another. Each case is refused in one line naming the file and key
or option (`helpers_attack.assert_refused`)."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from helpers_attack import Attack, Case, World, assert_refused, config_case, config_text

from steering_core.layout import check_name

BINARY = bytes(range(128, 256)) * 4  # no UTF-8 text starts with these
PAIR = "open_vs_close"
POSITIVE = "open the top drawer of the cabinet"


def named(name: str, attack: Attack) -> Attack:
    """Return `attack` under `name` (the table's test id)."""
    attack.__name__ = name
    return attack


# ----------------------------------------------------------------------------- run configs (capture --config)


def config_value(name: str, key: str, value: object, shown: str | None = None) -> Attack:
    """A run config whose `key` (dotted; list positions as digits; a missing section is added) is set to `value`;
    its error names `shown` (default the key)."""
    def attack(world: World, tmp_path: Path) -> Case:
        def edit(data: dict) -> None:
            *parents, last = key.split(".")
            node = data
            for part in parents:
                node = node[int(part)] if isinstance(node, list) else node.setdefault(part, {})
            node[int(last) if isinstance(node, list) else last] = value
        return config_case(tmp_path, config_text(world, tmp_path, edit), shown or key.replace(".0.", "[0]."))
    return named(name, attack)


def config_twice(name: str, anchor: str, line: str, key: str) -> Attack:
    """A run config with `line` added after the line `anchor`: a key the mapping already has, given again."""
    def attack(world: World, tmp_path: Path) -> Case:
        text = config_text(world, tmp_path)
        assert anchor in text, anchor
        return config_case(tmp_path, text.replace(anchor, f"{anchor}\n{line}", 1), f"key {key!r} appears twice")
    return named(name, attack)


ESCAPES = {"parent": "../../..", "absolute": "/tmp/elsewhere", "inner_parent": "a/../../b", "empty_part": "a//b",
           "home": "~/x", "backslash": "a\\..\\b", "dot": ".", "trailing_parent": "libero/..", "blank": " "}
# URLs of stores that are not object storage (s3://, gs:// and file:// roots are accepted: test_object_storage)
URLS = {"http": "http://host/x", "https": "https://host/x", "hf": "hf://datasets/x", "ftp": "ftp://host/x",
        "s3_no_bucket": "s3://", "gs_parent": "gs://bucket/../x"}

CONFIG_ATTACKS = [
    *(config_value(f"repo_id_{kind}", "dataset.repo_id", value) for kind, value in ESCAPES.items()),
    config_value("run_name_parent", "name", "../x"),
    config_value("run_name_absolute", "name", "/tmp/x"),
    config_value("pair_name_parent", "pairs.0.name", "../../evil"),
    config_value("pair_name_nested", "pairs.0.name", "a/b"),
    config_value("suite_parent", "sources.suite", "../../x"),
    *(config_value(f"output_root_{scheme}", "output_root", url) for scheme, url in URLS.items()),
    config_value("checkpoint_url", "model.checkpoint", "http://host/pi05"),
    config_value("tokenizer_url", "model.tokenizer", "https://host/tokenizer.model"),
    config_value("sources_folder_url", "sources.folders", ["ftp://host/demos"]),
    config_value("dataset_root_url", "dataset.root", "s3://bucket//dataset"),
    config_value("sae_path_url", "sae.1.path", "hf://org/sae"),
    config_value("sae_train_k_over_latents", "sae.1.train.k", 999, "sae.1.train: k is 999"),
    config_value("sae_train_architecture", "sae.1.train.architecture", "gated"),
    config_value("sae_train_heldout_fraction", "sae.1.train.heldout_fraction", 1.5),
    config_value("image_size_huge", "dataset.image_size", 20000),
    config_value("image_size_over_limit", "dataset.image_size", 513),
    config_value("run_name_300_characters", "name", "r" * 300, "at most 100 characters"),
    config_value("pair_name_300_characters", "pairs.0.name", "p" * 300, "at most 100 characters"),
    config_value("evaluate_permutations", "evaluate.permutations", 10**9, "less than or equal to 10000"),
    config_value("evaluate_num_steps", "evaluate.num_steps", 10**9, "less than or equal to 1000"),
    config_value("evaluate_entries_per_call", "evaluate.entries_per_call", 10**9, "less than or equal to 1024"),
    config_value("evaluate_alphas_100k", "evaluate.alphas", [0.0, *range(1, 100_001)], "100001 values"),
    config_value("rollout_max_steps", "rollout.max_steps", 10**9, "less than or equal to 10000"),
    config_value("rollout_alphas_100k", "rollout.alphas", [0.0, *range(1, 100_001)], "100001 values"),
    config_value("rollout_episodes", "rollout.episodes", 10**9, "less than or equal to 1000"),
    config_value("sae_train_buffer_rows", "sae.1.train.buffer_rows", 10**12, "less than or equal to 2097152"),
    config_value("sae_train_d_sae", "sae.1.train.d_sae", 10**9, "less than or equal to 1048576"),
    config_value("shards_per_capture_run", "orchestration.shards_per_capture_run", 10**12,
                 "less than or equal to 100000"),
    config_value("capture_num_steps", "capture.num_steps", 10**9, "less than or equal to 1000"),
    config_twice("twice_name", "name: demo", "name: other", "name"),
    config_twice("twice_repo_id", "  repo_id: libero_demo_lerobot", "  repo_id: other", "repo_id"),
    config_twice("twice_layers", "layers:\n- 1\n- 2", "layers: [1]", "layers"),
    config_twice("twice_pair_key", "- name: open_vs_close", "  name: again", "name"),
    config_twice("twice_checkpoint", "model:", "  checkpoint: /y", "checkpoint"),
    config_twice("twice_capture_key", "capture:", "  batch_size: 2", "batch_size"),
    config_twice("twice_sae_layer", "sae:", "  '1': {path: /x}", "1"),
]


def binary_config(world: World, tmp_path: Path) -> Case:
    return config_case(tmp_path, BINARY, "not a text file")


def utf16_config(world: World, tmp_path: Path) -> Case:
    return config_case(tmp_path, config_text(world, tmp_path).encode("utf-16"), "not a text file")


def binary_config_with_run(world: World, tmp_path: Path) -> Case:
    path = tmp_path / "run.yaml"
    path.write_bytes(b"name: demo\n" + BINARY)
    return Case(["run", "--config", path], (str(path), "not UTF-8"))


# ----------------------------------------------------------------------------- URLs given to CLI path options


def cli_url(name: str, flag: str, argv: Callable[[World, Path], list], url: str = "http://host/x") -> Attack:
    """A command whose path option `flag` is given `url`, a URL of no object storage (the other options sound)."""
    def attack(world: World, tmp_path: Path) -> Case:
        words = [str(word) for word in argv(world, tmp_path)]
        if f"{flag}=" in words:  # the `--flag=value` spelling
            words[words.index(f"{flag}=")] = f"{flag}={url}"
        else:
            words += [flag, url]
        return Case(words, (flag, url, "unsupported storage URL"))
    return named(name, attack)


def _convert(world: World, tmp_path: Path) -> list:
    return ["convert", "--input-dir", world.data / "filtered", "--repo-id", "x", "--image-size", "16"]


def _manifest(world: World, tmp_path: Path) -> list:
    return ["manifest", "--task-a-index", "0", "--task-b-index", "1", "--lerobot-root", world.dataset]


def _concept_map(world: World, tmp_path: Path) -> list:
    return ["concept-map", "--lerobot-root", world.dataset, "--manifest-path", world.data / "manifests" / f"{PAIR}.json"]


def _capture(world: World, tmp_path: Path) -> list:
    return ["capture", "--checkpoint-path", world.checkpoint, "--tokenizer-path", world.tokenizer,
            "--lerobot-root", world.dataset, "--layers", "1", "--device", "cpu"]


def _slice(world: World, tmp_path: Path) -> list:
    return ["slice", "--run-dir", world.data / "residuals" / "demo", "--layers", "1",
            "--concept-map-path", world.data / "manifests" / f"{PAIR}_concept_map.json"]


def _steer(world: World, tmp_path: Path) -> list:
    return ["steer", "--pairs-config", world.data / "layer1_pairs.json", "--layer", "1", "--sae", "none"]


def _evaluate(world: World, tmp_path: Path) -> list:
    return ["evaluate", "--pairs-config", world.data / "layer2_pairs.json", "--layer", "2",
            "--checkpoint-path", world.checkpoint, "--tokenizer-path", world.tokenizer,
            "--arch-file", world.data / "arch.json", "--device", "cpu"]


URL_ATTACKS = [
    cli_url("convert_output_dir", "--output-dir", _convert),
    cli_url("convert_output_dir_equals", "--output-dir", lambda w, t: [*_convert(w, t), "--output-dir="]),
    cli_url("convert_input_dir", "--input-dir", lambda w, t: [*_convert(w, t), "--output-dir", t / "ds"], "gs://b/../demos"),
    cli_url("filter_output_dir", "--output-dir", lambda w, t: ["filter", "--input-dir", w.inputs / "inputs" / "demos"]),
    cli_url("make_demos_output_dir", "--output-dir", lambda w, t: ["make-demos", "--image-size", "16"], "http://h/x"),
    cli_url("manifest_lerobot_root", "--lerobot-root",
            lambda w, t: ["manifest", "--task-a-index", "0", "--task-b-index", "1", "--output", t / "m.json"]),
    cli_url("manifest_output", "--output", _manifest, "https://host/m.json"),
    cli_url("concept_map_output", "--output-path", _concept_map),
    cli_url("concept_map_manifest", "--manifest-path",
            lambda w, t: ["concept-map", "--lerobot-root", w.dataset, "--output-path", t / "c.json"]),
    cli_url("capture_output_dir", "--output-dir", _capture),
    cli_url("capture_checkpoint", "--checkpoint-path",
            lambda w, t: ["capture", "--tokenizer-path", w.tokenizer, "--lerobot-root", w.dataset,
                          "--output-dir", t / "run"], "hf://org/pi05"),
    cli_url("capture_config", "--config", lambda w, t: ["capture"]),
    cli_url("slice_output_dir", "--output-dir", _slice),
    cli_url("slice_split", "--split", lambda w, t: [*_slice(w, t), "--output-dir", t / "slices"], "ftp://b/split.json"),
    cli_url("split_output", "--output", lambda w, t: ["split", "--manifest", w.data / "manifests" / f"{PAIR}.json"]),
    cli_url("steer_output_root", "--output-root", _steer),
    cli_url("steer_pairs_config", "--pairs-config", lambda w, t: ["steer", "--layer", "1", "--sae", "none"]),
    cli_url("evaluate_lerobot_root", "--lerobot-root", lambda w, t: [*_evaluate(w, t), "--data-root", w.data]),
    cli_url("evaluate_data_root", "--data-root", lambda w, t: [*_evaluate(w, t), "--lerobot-root", w.dataset]),
    cli_url("run_config", "--config", lambda w, t: ["run"], "https://host/run.yaml"),
]


# ----------------------------------------------------------------------------- names that become path components


def convert_repo_id(name: str, repo_id: str) -> Attack:
    def attack(world: World, tmp_path: Path) -> Case:
        return Case([*_convert(world, tmp_path), "--output-dir", tmp_path / "ds", "--repo-id", repo_id],
                    ("--repo-id", repr(repo_id)))
    return named(name, attack)


def evaluate_pair_parent(world: World, tmp_path: Path) -> Case:
    return Case([*_evaluate(world, tmp_path), "--data-root", world.data, "--lerobot-root", world.dataset,
                 "--output-root", tmp_path / "eval", "--pair", "../../evil"], ("--pair", "'../../evil'"))


def steer_pair_name_parent(world: World, tmp_path: Path) -> Case:
    pairs = json.loads((world.data / "layer1_pairs.json").read_text())
    pairs["pairs"][0]["name"] = "../../evil"
    path = tmp_path / "pairs.json"
    path.write_text(json.dumps(pairs))
    return Case(["steer", "--pairs-config", path, "--layer", "1", "--sae", "none", "--output-root", tmp_path / "st"],
                (str(path), "'../../evil'"))


NAME_ATTACKS = [
    *(convert_repo_id(f"convert_repo_id_{kind}", value) for kind, value in ESCAPES.items()),
    named("evaluate_pair_parent", evaluate_pair_parent),
    named("steer_pair_name_parent", steer_pair_name_parent),
]


# ----------------------------------------------------------------------------- binary or ambiguous JSON inputs


def json_input(name: str, build: Callable[[World, Path, Path], list], source: Callable[[World], Path],
               spoil: Callable[[bytes], bytes], expect: str) -> Attack:
    """A command reading a copy of one of the world's JSON files spoiled by `spoil`; its error names the copy."""
    def attack(world: World, tmp_path: Path) -> Case:
        original = source(world)
        path = tmp_path / original.name
        path.write_bytes(spoil(original.read_bytes()))
        return Case(build(world, tmp_path, path), (str(path), expect))
    return named(name, attack)


def _binary(data: bytes) -> bytes:
    return BINARY + data


def _utf16(data: bytes) -> bytes:
    return data.decode("utf-8").encode("utf-16")


def _first_key_twice(data: bytes) -> bytes:
    """Return the JSON object with its first key given again (same value) at the end of the top level."""
    payload = json.loads(data)
    key = next(iter(payload))
    return (json.dumps(payload)[:-1] + f", {json.dumps(key)}: {json.dumps(payload[key])}}}").encode("utf-8")


def _manifest_of(world: World) -> Path:
    return world.data / "manifests" / f"{PAIR}.json"


def _concept_map_of(world: World) -> Path:
    return world.data / "manifests" / f"{PAIR}_concept_map.json"


def _split_of(world: World) -> Path:
    return world.data / "manifests" / f"{PAIR}_split.json"


def _pairs_of(world: World) -> Path:
    return world.data / "layer1_pairs.json"


def _arch_of(world: World) -> Path:
    return world.data / "arch.json"


def _use_manifest(world: World, tmp_path: Path, path: Path) -> list:
    return ["concept-map", "--manifest-path", path, "--lerobot-root", world.dataset, "--output-path", tmp_path / "c.json"]


def _use_manifest_in_split(world: World, tmp_path: Path, path: Path) -> list:
    return ["split", "--manifest", path, "--output", tmp_path / "split.json"]


def _use_concept_map(world: World, tmp_path: Path, path: Path) -> list:
    return [*_slice(world, tmp_path)[:-2], "--concept-map-path", path, "--output-dir", tmp_path / "slices"]


def _use_split(world: World, tmp_path: Path, path: Path) -> list:
    return [*_slice(world, tmp_path), "--output-dir", tmp_path / "slices", "--split", path]


def _use_pairs(world: World, tmp_path: Path, path: Path) -> list:
    return ["steer", "--pairs-config", path, "--layer", "1", "--sae", "none", "--output-root", tmp_path / "st"]


def _use_arch(world: World, tmp_path: Path, path: Path) -> list:
    return [*_capture(world, tmp_path), "--output-dir", tmp_path / "run", "--arch-file", path]


def _use_rename(world: World, tmp_path: Path, path: Path) -> list:
    return [*_concept_map(world, tmp_path), "--output-path", tmp_path / "c.json", "--concept-map", path]


def _rename_map(world: World) -> Path:
    path = world.inputs.parent / "rename.json"  # beside the world, written once: the renames of the pair
    if not path.is_file():
        path.write_text(json.dumps({POSITIVE: "open", "close the top drawer of the cabinet": "close"}))
    return path


JSON_INPUTS = {
    "manifest": (_use_manifest, _manifest_of),
    "manifest_split": (_use_manifest_in_split, _manifest_of),
    "concept_map": (_use_concept_map, _concept_map_of),
    "split": (_use_split, _split_of),
    "pairs_config": (_use_pairs, _pairs_of),
    "arch_file": (_use_arch, _arch_of),
    "rename_map": (_use_rename, _rename_map),
}
SPOILS = {"binary": (_binary, "not a text file"), "utf16": (_utf16, "not a text file"),
          "key_twice": (_first_key_twice, "appears twice")}
JSON_ATTACKS = [json_input(f"{what}_{how}", build, source, spoil, expect)
                for what, (build, source) in JSON_INPUTS.items() for how, (spoil, expect) in SPOILS.items()]


def dataset_info(name: str, spoil: Callable[[bytes], bytes], expect: str) -> Attack:
    """`manifest` on a copy of the world's dataset whose meta/info.json is spoiled."""
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = tmp_path / "dataset"
        shutil.copytree(world.dataset, dataset)
        info = dataset / "meta" / "info.json"
        info.write_bytes(spoil(info.read_bytes()))
        return Case(["manifest", "--lerobot-root", dataset, "--task-a-index", "0", "--task-b-index", "1",
                     "--output", tmp_path / "m.json"], (str(info), expect))
    return named(name, attack)


DATASET_ATTACKS = [dataset_info(f"dataset_info_{how}", spoil, expect) for how, (spoil, expect) in SPOILS.items()]


# ----------------------------------------------------------------------------- pickled and unreadable slices


class Payload:
    """Unpickling this runs `touch` (the file shows whether it ran)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def steer_slice(name: str, side: str, write: Callable[[Path, Path], None]) -> Attack:
    """`steer` whose pair's `side` slice is replaced by a file `write` makes (the world's other paths kept)."""
    def attack(world: World, tmp_path: Path) -> Case:
        pairs = json.loads(_pairs_of(world).read_text())
        path = tmp_path / f"{side}.pt"
        write(path, tmp_path / "PWNED")
        pairs["pairs"][0][f"{side}_path"] = str(path)
        config = tmp_path / "pairs.json"
        config.write_text(json.dumps(pairs))
        return Case(_use_pairs(world, tmp_path, config), (str(path), f"{PAIR}.{side}_path"))
    return named(name, attack)


def _pickled_payload(path: Path, marker: Path) -> None:
    torch.save({"rows": Payload(marker)}, path)


def _pickled_object(path: Path, marker: Path) -> None:
    torch.save(Payload(marker), path)


def _garbage(path: Path, marker: Path) -> None:
    path.write_bytes(BINARY)


def _dict_of_tensors(path: Path, marker: Path) -> None:
    torch.save({"rows": torch.zeros(4, 64)}, path)


PICKLE_ATTACKS = [steer_slice(f"{side}_slice_{kind}", side, write) for side in ("positive", "negative")
                  for kind, write in (("pickle_payload", _pickled_payload), ("pickle_object", _pickled_object),
                                      ("garbage", _garbage), ("not_a_tensor", _dict_of_tensors))]


# ----------------------------------------------------------------------------- sizes beyond what a step can hold


def sized(name: str, argv: Callable[[World, Path], list], flag: str, value: str, limit: str) -> Attack:
    def attack(world: World, tmp_path: Path) -> Case:
        return Case([*argv(world, tmp_path), flag, value], (flag, value, limit))
    return named(name, attack)


def _convert_to(world: World, tmp_path: Path) -> list:
    return [*_convert(world, tmp_path), "--output-dir", tmp_path / "ds"]


def _make_demos(world: World, tmp_path: Path) -> list:
    return ["make-demos", "--output-dir", tmp_path / "demos"]


BOUND_ATTACKS = [
    sized("convert_image_size_huge", _convert_to, "--image-size", "20000", "512"),
    sized("convert_image_size_over", _convert_to, "--image-size", "513", "512"),
    sized("make_demos_image_size_huge", _make_demos, "--image-size", "4000", "512"),
    sized("make_demos_steps_huge", _make_demos, "--num-steps", "1000000", "5000"),
    sized("capture_batch_huge", lambda w, t: [*_capture(w, t), "--output-dir", t / "run"], "--batch-size", "100000",
          "1024"),
    *(sized(f"evaluate_{flag[2:].replace('-', '_')}_huge",
            lambda w, t: [*_evaluate(w, t), "--data-root", w.data, "--lerobot-root", w.dataset,
                          "--output-root", t / "eval"], flag, value, limit)
      for flag, value, limit in (("--batch-size", "5000", "1024"), ("--noise-seeds", "1000", "256"),
                                 ("--random-directions", "100000", "4096"), ("--max-frames", "1000000", "10000"))),
    config_value("config_capture_batch_huge", "capture.batch_size", 100000),
    config_value("config_evaluate_bootstrap_huge", "evaluate.bootstrap", 10**9),
]


# ----------------------------------------------------------------------------- inputs of different datasets


def other_dataset(world: World, tmp_path: Path) -> Path:
    """Return a copy of the world's dataset with other content (its info.json reformatted): another fingerprint."""
    dataset = tmp_path / "other"
    shutil.copytree(world.dataset, dataset)
    info = dataset / "meta" / "info.json"
    info.write_text(json.dumps(json.loads(info.read_text()), indent=1))
    return dataset


def evaluate_other_dataset(world: World, tmp_path: Path) -> Case:
    dataset = other_dataset(world, tmp_path)
    return Case([*_evaluate(world, tmp_path), "--data-root", world.data, "--lerobot-root", dataset,
                 "--output-root", tmp_path / "eval"], (str(_manifest_of(world)), str(dataset), "fingerprint"))


def evaluate_other_dataset_one_pair(world: World, tmp_path: Path) -> Case:
    case = evaluate_other_dataset(world, tmp_path)
    return Case([*case.argv, "--pair", "on_vs_off"], (str(world.data / "manifests" / "on_vs_off.json"), "fingerprint"))


def concept_map_other_dataset(world: World, tmp_path: Path) -> Case:
    dataset = other_dataset(world, tmp_path)
    return Case(["concept-map", "--manifest-path", _manifest_of(world), "--lerobot-root", dataset,
                 "--output-path", tmp_path / "c.json"], (str(_manifest_of(world)), "fingerprint"))


def evaluate_missing_dataset(world: World, tmp_path: Path) -> Case:
    return Case([*_evaluate(world, tmp_path), "--data-root", world.data, "--lerobot-root", tmp_path / "none",
                 "--output-root", tmp_path / "eval"], (str(tmp_path / "none"),))


DATASET_PAIRING_ATTACKS = [evaluate_other_dataset, evaluate_other_dataset_one_pair, concept_map_other_dataset,
                           evaluate_missing_dataset]

ATTACKS = [binary_config, utf16_config, binary_config_with_run, *CONFIG_ATTACKS, *URL_ATTACKS, *NAME_ATTACKS,
           *JSON_ATTACKS, *DATASET_ATTACKS, *PICKLE_ATTACKS, *BOUND_ATTACKS, *DATASET_PAIRING_ATTACKS]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda f: f.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)  # what a URL taken for a relative path would create (`s3:/...`) is seen too
    assert_refused(attack_world, tmp_path, attack)


def test_names_that_stay_under_their_root_are_accepted():
    for name in ("libero_demo_lerobot", "physical-intelligence/libero", "v2.1", "open the top drawer"):
        assert check_name(name, "repo_id", nested=True) == name
    for name in ("open_vs_close", "turn on the stove", "a..b"):
        assert check_name(name, "pair") == name


def test_the_table_holds_eighty_cases_or_more():
    assert len({attack.__name__ for attack in ATTACKS}) == len(ATTACKS) >= 80


def test_no_pickled_slice_ran_its_payload(attack_world, tmp_path):
    """The payload cases refuse the file without running it: the marker it would touch never appears."""
    for attack in PICKLE_ATTACKS[:2]:
        (tmp_path / attack.__name__).mkdir()
        assert_refused(attack_world, tmp_path / attack.__name__, attack)
        assert not (tmp_path / attack.__name__ / "PWNED").exists()
