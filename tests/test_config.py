"""Run config: YAML loading, path resolution, each step's settings, and errors naming file and key path."""

import json
import textwrap
from pathlib import Path

import pytest

from steering_core.capture import CaptureSettings
from steering_core.capture.slicing import SliceSettings
from steering_core.config import RunConfig, load_run_config, write_run_config
from steering_core.vectors.directions import PairsConfig, SteeringSettings

VALID = """\
name: drawer_stove
sources:
  folders: [demos, /abs/more_demos]
dataset: {repo_id: libero_ds, image_size: 64}
pairs:
  - name: open_vs_close
    positive: open the top drawer of the cabinet
    negative: close the top drawer of the cabinet
  - name: on_vs_off
    positive: turn on the stove
    negative: turn off the stove
    rename: {turn on the stove: stove_on}
    manifest: {pad: 3}
layers: [2, 1]
model: {checkpoint: ckpt, tokenizer: tok/tokenizer.model, arch: {width: 64, depth: 4}}
capture: {batch_size: 8, storage_dtype: bfloat16}
slicing: {reduce: frame}
sae:
  2: {release: gemma-2b-it-res-jb, sae_id: blocks.12.hook_resid_post}
  1: {path: saes/one}
steering: {top_k: 7, include_decoder_bias: true}
"""


def write_yaml(tmp_path: Path, text: str, name: str = "run.yaml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


def load_error(tmp_path: Path, text: str) -> list[str]:
    path = write_yaml(tmp_path, text)
    with pytest.raises(ValueError) as err:
        load_run_config(path)
    prefix = f"{path}: "
    lines = str(err.value).splitlines()
    assert all(line.startswith(prefix) for line in lines), lines
    return [line.removeprefix(prefix) for line in lines]


def test_valid_config_resolves_paths_against_its_file(tmp_path):
    config = load_run_config(write_yaml(tmp_path, VALID))
    assert config.sources.folders == (tmp_path / "demos", Path("/abs/more_demos"))
    assert config.output_root == tmp_path / "data"  # default `data`, next to the file
    assert config.model.checkpoint == tmp_path / "ckpt"
    assert config.sae[1].path == tmp_path / "saes/one"
    assert config.layers == (1, 2)
    # the seed's layout under output_root
    assert config.dataset_root == tmp_path / "data/libero_lerobot/libero_ds"
    assert config.filtered_dir == tmp_path / "data/libero_filtered/demos"
    assert config.manifest_path(config.pairs[1]) == tmp_path / "data/manifests/on_vs_off.json"
    assert config.concept_map_path(config.pairs[0]) == tmp_path / "data/manifests/open_vs_close_concept_map.json"
    assert config.run_dir == tmp_path / "data/residuals/drawer_stove"
    assert config.slices_dir(config.pairs[0]) == tmp_path / "data/residuals/open_vs_close_slices"
    assert config.pairs_config_path(2) == tmp_path / "data/latent_steering/layer02_pairs.json"


def test_each_step_gets_its_own_full_settings(tmp_path):
    config = load_run_config(write_yaml(tmp_path, VALID))
    capture = config.capture_settings()
    assert isinstance(capture, CaptureSettings)
    assert (capture.model.checkpoint, capture.model.tokenizer) == (tmp_path / "ckpt", tmp_path / "tok/tokenizer.model")
    assert capture.layers == (1, 2) and capture.batch_size == 8 and capture.storage_dtype == "bfloat16"
    assert capture.arch.width == 64

    sliced = config.slice_settings(2)
    assert isinstance(sliced, SliceSettings)
    assert (sliced.layers, sliced.token_type, sliced.reduce) == ((2,), "instructions", "frame")

    with_release, with_path = config.steering_settings(2), config.steering_settings(1)
    assert isinstance(with_release, SteeringSettings)
    assert (with_release.sae, with_release.sae_id, with_release.layer) == (
        "gemma-2b-it-res-jb", "blocks.12.hook_resid_post", 2)
    assert with_path.sae == str(tmp_path / "saes/one")
    assert with_path.output_root == tmp_path / "data/latent_steering"
    assert with_path.pairs_config == tmp_path / "data/latent_steering/layer01_pairs.json"
    assert (with_path.top_k, with_path.include_decoder_bias) == (7, True)

    convert = config.convert_settings()
    assert (convert.repo_id, convert.image_size, convert.orientation) == ("libero_ds", 64, "rotate180")
    # no tasks and no globs: the pairs' four task texts are selected
    assert config.filter_settings().tasks == (
        "open the top drawer of the cabinet", "close the top drawer of the cabinet",
        "turn on the stove", "turn off the stove")


def test_layer_without_sae_gets_residual_directions_only(tmp_path):
    text = VALID.replace("  1: {path: saes/one}\n", "")
    config = load_run_config(write_yaml(tmp_path, text))
    assert config.sae_for(1) is None and config.steering_settings(1).sae is None


def test_write_and_reload_round_trip(tmp_path):
    config = load_run_config(write_yaml(tmp_path, VALID))
    moved = tmp_path / "elsewhere" / "copy.yaml"
    moved.parent.mkdir()
    write_run_config(config, moved)
    again = load_run_config(moved)
    assert again == config
    assert again.fingerprint() == config.fingerprint()


def test_missing_field_names_file_and_key_path(tmp_path):
    text = VALID.replace("    positive: turn on the stove\n", "")
    assert load_error(tmp_path, text) == ["pairs[1].positive: field required"]


def test_every_problem_is_reported_at_once(tmp_path):
    text = (VALID.replace("manifest: {pad: 3}", "manifest: {pad: -1, padding: 4}")
            .replace("batch_size: 8", "batch_size: 0, layers: [3]")
            .replace("reduce: frame", "reduce: frame, token_type: prompt"))
    assert load_error(tmp_path, text) == [
        "pairs[1].manifest.pad: input should be greater than or equal to 0",
        "pairs[1].manifest.padding: unknown key (check its spelling and section)",
        "capture.batch_size: input should be greater than or equal to 1",
        "capture.layers: set by the run config: use `layers`",
        "slicing.token_type: set by the run config: use `capture.token_type`",
    ]


def test_cross_section_errors(tmp_path):
    text = VALID.replace("layers: [2, 1]", "layers: [1, 4]").replace("  2: {release", "  3: {release")
    assert load_error(tmp_path, text) == [(
        "layers [4] out of range: model.arch has 4 decoder layers (0..3); "
        "sae has entries for layers [3] that are not in layers [1, 4]"
    )]
    duplicate = VALID.replace("name: on_vs_off", "name: open_vs_close")
    assert load_error(tmp_path, duplicate) == [
        "pairs: pairs[0] and pairs[1] are both named 'open_vs_close'; names must be unique"
    ]
    same_task = VALID.replace("negative: turn off the stove", "negative: Turn on the stove")
    assert load_error(tmp_path, same_task) == [
        "pairs[1]: positive and negative are both 'turn on the stove'; a pair needs two different tasks"
    ]


def test_sae_section_needs_exactly_one_source(tmp_path):
    text = VALID.replace("1: {path: saes/one}", "1: {path: saes/one, release: gemma-2b-res-jb}")
    assert load_error(tmp_path, text) == [
        "sae.1: give one of `release` (with optional `sae_id`) or `path`, not both"
    ]
    assert load_error(tmp_path, VALID.replace("1: {path: saes/one}", "1: {local_dir: saes}")) == [
        "sae.1: give `release` (with optional `sae_id`), `path`, or `train`"
    ]


def test_unsafe_pair_name_and_bad_yaml(tmp_path):
    assert load_error(tmp_path, VALID.replace("name: on_vs_off", "name: on/off"))[0].startswith(
        "pairs[1].name: string should match pattern")
    broken = write_yaml(tmp_path, "pairs: [\n  - {name: x\n", "broken.yaml")
    with pytest.raises(ValueError, match=r"broken\.yaml: not valid YAML \(line \d+, column \d+: "):
        load_run_config(broken)
    listing = write_yaml(tmp_path, "- just\n- a list\n", "list.yaml")
    with pytest.raises(ValueError, match=r"list\.yaml: expected a mapping of sections .* found list"):
        load_run_config(listing)
    with pytest.raises(FileNotFoundError, match=r"nope\.yaml: run config not found"):
        load_run_config(tmp_path / "nope.yaml")


def test_pairs_config_uses_dataset_texts_renames_and_relative_paths(tmp_path):
    config = load_run_config(write_yaml(tmp_path, VALID))
    slices = tmp_path / "data/residuals"
    concepts = {
        "open_vs_close": {"open the top drawer of the cabinet": str(slices / "a/open.pt"),
                          "close the top drawer of the cabinet": str(slices / "a/close.pt")},
        "on_vs_off": {"stove_on": str(slices / "b/on.pt"), "turn off the stove": str(slices / "b/off.pt")},
    }
    tasks = {"open_vs_close": ("open the top drawer of the cabinet", "close the top drawer of the cabinet"),
             "on_vs_off": ("turn on the stove", "turn off the stove")}
    pairs = config.pairs_config(1, tasks, concepts)
    assert isinstance(pairs, PairsConfig)
    on = pairs.pairs[1]
    assert (on.positive_label, on.positive_path) == ("stove_on", "../residuals/b/on.pt")
    # the written file is the seed's format and its paths resolve against its own folder
    written = config.pairs_config_path(1)
    written.parent.mkdir(parents=True)
    written.write_text(json.dumps(pairs.model_dump()))
    assert (written.parent / json.loads(written.read_text())["pairs"][0]["negative_path"]).resolve() == (
        slices / "a/close.pt")

    del concepts["on_vs_off"]["stove_on"]
    with pytest.raises(ValueError, match=r"pair 'on_vs_off': no slice for concept\(s\) \['stove_on'\]"):
        config.pairs_config(1, tasks, concepts)


def test_python_construction_keeps_paths_as_given():
    config = RunConfig.model_validate({
        "sources": {"folders": ["demos"]}, "dataset": {"repo_id": "r"},
        "pairs": [{"name": "p", "positive": "a", "negative": "b"}],
        "model": {"checkpoint": "ckpt", "tokenizer": "tok"},
    })
    assert config.sources.folders == (Path("demos"),) and config.output_root == Path("data")


def test_documented_example_is_valid(tmp_path):
    import steering_core.config as module

    example = module.__doc__.split("```yaml\n")[1].split("```")[0]
    config = load_run_config(write_yaml(tmp_path, example))
    assert [p.name for p in config.pairs] == ["open_vs_close", "on_vs_off"]
    assert config.steering_settings(12).sae == "gemma-2b-it-res-jb"
    assert config.pairs[1].concept("turn on the stove") == "stove_on"


def test_evaluate_section_holds_out_episodes_and_names_methods_and_modes(tmp_path):
    config = load_run_config(write_yaml(tmp_path, VALID + "evaluate: {holdout_fraction: 0.25, max_frames: 6, alphas: "
                                        "[0, 2, -2], methods: [probe, sae], modes: [clamp]}\n"))
    settings = config.evaluate_settings()
    assert (settings.holdout_fraction, settings.max_frames, settings.alphas) == (0.25, 6, (-2.0, 0.0, 2.0))
    assert (settings.methods, settings.modes) == (("probe", "sae"), ("clamp",))
    assert load_error(tmp_path, VALID + "evaluate: {modes: [add, add]}\n") == [
        "evaluate.modes: ['add', 'add']: give at least one, each once"]
    assert config.holdout_fraction == 0.25
    assert config.slice_settings(2, (5, 3)).holdout_episodes == (3, 5)
    assert config.slice_settings(2).holdout_episodes == ()
    assert config.split_path(config.pairs[0]) == tmp_path / "data/manifests/open_vs_close_split.json"
    assert config.eval_layer_path(2) == tmp_path / "data/steering_eval/layer02"
    off = load_run_config(write_yaml(tmp_path, VALID + "evaluate: null\n", name="off.yaml"))
    assert off.holdout_fraction == 0.0
    with pytest.raises(ValueError, match="evaluate: null"):
        off.evaluate_settings()
    assert load_error(tmp_path, VALID + "evaluate: {top_k: 3}\n") == ["evaluate.top_k: set by the run config: use `steering.top_k`"]
    assert load_error(tmp_path, VALID + "evaluate: {alphas: [1, 2]}\n")[0].startswith("evaluate.alphas: alphas [1.0, 2.0] must include 0")
    assert load_error(tmp_path, VALID.replace("slicing: {reduce: frame}", "slicing: {holdout_episodes: [1]}")) == [
        "slicing.holdout_episodes: set by the run config: use `evaluate.holdout_fraction`"]


def test_expert_layers_add_a_decision_capture_and_are_checked_against_the_expert_depth(tmp_path):
    config = load_run_config(write_yaml(tmp_path, VALID + "evaluate: {expert_layers: [3, 0, 3]}\n"))
    assert config.expert_layers == (0, 3)
    assert "expert_layers" not in config.evaluate_settings().model_dump()  # a run-level choice, not per evaluation
    decision = config.decision_capture_settings()
    main = config.capture_settings()
    assert (decision.token_type, decision.layers) == ("decision", (0, 3))
    assert decision.model_dump(exclude={"token_type", "layers"}) == main.model_dump(exclude={"token_type", "layers"})
    assert config.decision_run_dir == tmp_path / "data/residuals/drawer_stove_decision"
    pair = config.pairs[0]
    assert config.decision_slices_dir(pair) == tmp_path / "data/residuals/open_vs_close_decision_slices"
    expert_slices = config.slice_settings(3, (4,), "expert")
    assert (expert_slices.token_type, expert_slices.layers, expert_slices.holdout_episodes) == ("decision", (3,), (4,))
    assert expert_slices.reduce == "frame"  # the slicing section applies to both streams
    assert config.eval_layer_path(3, "expert") == tmp_path / "data/steering_eval/expert_layer03"
    assert config.eval_layers() == [(1, "lm"), (2, "lm"), (0, "expert"), (3, "expert")]
    assert load_run_config(write_yaml(tmp_path, VALID, name="none.yaml")).expert_layers == ()
    with pytest.raises(ValueError, match="captures no decision rows"):
        load_run_config(write_yaml(tmp_path, VALID, name="none.yaml")).decision_capture_settings()
    assert load_error(tmp_path, VALID + "evaluate: {expert_layers: [1, 4]}\n") == [
        "evaluate.expert_layers [4] out of range: the action expert has 4 decoder layers (0..3), as many as "
        "model.arch.depth"]
    assert load_error(tmp_path, VALID + "evaluate: {expert_layers: [-1]}\n") == [
        "evaluate.expert_layers: expert_layers [-1] include a negative index; expert layers count from 0"]
    assert load_error(tmp_path, VALID.replace("storage_dtype: bfloat16}", "num_steps: 5}")
                      + "evaluate: {expert_layers: [1]}\n") == [
        "evaluate.num_steps 10 differs from capture.num_steps 5: the expert direction comes from the decision rows "
        "of the sampler the evaluation steers; set both to the same value"]



def test_the_last_decoder_layer_is_refused_when_the_run_evaluates(tmp_path):
    last = VALID.replace("layers: [2, 1]", "layers: [1, 3]").replace("  2: {release", "  3: {release")
    assert load_error(tmp_path, last) == [
        "layers include 3, the last decoder layer: its output only feeds the final norm the actions never read, "
        "so steering it cannot move them; evaluate earlier layers or set `evaluate: null`"]
    config = load_run_config(write_yaml(tmp_path, last + "evaluate: null\n", name="off.yaml"))
    assert config.layers == (1, 3)  # capturing and steering vectors at the last layer stay possible

EXISTING = VALID.replace("sources:\n  folders: [demos, /abs/more_demos]\n", "").replace(
    "dataset: {repo_id: libero_ds, image_size: 64}", "dataset: {existing: hf/physical-intelligence/libero}")


def test_existing_dataset_is_read_in_place(tmp_path):
    config = load_run_config(write_yaml(tmp_path, EXISTING))
    assert config.sources is None and not config.converts
    assert config.dataset_root == tmp_path / "hf/physical-intelligence/libero"  # the folder itself, not under data/
    assert config.repo_id == "libero"  # the folder's name unless repo_id is given
    named = load_run_config(write_yaml(tmp_path, EXISTING.replace("libero}", "libero, repo_id: pi/libero}")))
    assert named.repo_id == "pi/libero" and named.dataset_root == config.dataset_root
    with pytest.raises(ValueError, match=r"reads the existing dataset .*libero in place: it has no hdf5 `sources`"):
        config.convert_settings()
    with pytest.raises(ValueError, match=r"no hdf5 `sources`"):
        config.filtered_dir  # noqa: B018 (a property that must refuse)
    again = tmp_path / "again.yaml"
    write_run_config(config, again)
    assert load_run_config(again) == config


def test_existing_dataset_and_sources_are_exclusive(tmp_path):
    both = VALID.replace("dataset: {repo_id: libero_ds, image_size: 64}", "dataset: {existing: ds}")
    assert load_error(tmp_path, both) == [
        "give exactly one of `sources` (hdf5 demo folders to filter and convert) and `dataset.existing` "
        "(a LeRobot dataset to read in place); found both"]
    neither = VALID.replace("sources:\n  folders: [demos, /abs/more_demos]\n", "")
    assert load_error(tmp_path, neither)[0].endswith("found neither")
    convert_keys = EXISTING.replace("{existing: hf/physical-intelligence/libero}",
                                    "{existing: ds, image_size: 64, codebase_version: v2.1}")
    assert load_error(tmp_path, convert_keys) == [
        "dataset: ['codebase_version', 'image_size'] apply only when converting hdf5 `sources`; "
        "an `existing` dataset is read as it is: remove them"]
    no_repo = VALID.replace("{repo_id: libero_ds, image_size: 64}", "{image_size: 64}")
    assert load_error(tmp_path, no_repo) == [
        "dataset: give `repo_id` (the name of the dataset converted from `sources`), "
        "or `existing` with the path of a LeRobot dataset to read in place"]


def test_merged_keys_may_be_overridden_but_a_key_written_twice_is_refused(tmp_path):
    merged = VALID.replace("steering: {top_k: 7, include_decoder_bias: true}",
                           "steering: {<<: {top_k: 3, batch_size: 64}, top_k: 7, include_decoder_bias: true}")
    config = load_run_config(write_yaml(tmp_path, merged))
    assert (config.steering.top_k, config.steering.batch_size) == (7, 64)
    twice = VALID.replace("steering: {top_k: 7,", "steering: {top_k: 3, top_k: 7,")
    assert load_error(tmp_path, twice) == ["not valid YAML (line 21, column 22: key 'top_k' appears twice; keep one)"]


def test_a_trained_layer_steers_through_its_trained_sae_and_is_judged_against_the_named_one(tmp_path):
    text = VALID.replace("1: {path: saes/one}", "1: {path: saes/one, train: {d_sae: 128, k: 4, seed: 3}}")
    config = load_run_config(write_yaml(tmp_path, text))
    assert config.trained_layers == (1,)
    trained = tmp_path / "data" / "saes" / config.name / "layer01" / "sae"
    assert config.trained_sae_dir(1) == trained and config.steering_settings(1).sae == str(trained)
    assert config.steering_settings(1, borrowed=True).sae == str(tmp_path / "saes/one")
    assert (config.train_settings(1).d_sae, config.train_settings(1).k, config.train_settings(1).seed) == (128, 4, 3)
    alone = load_run_config(write_yaml(tmp_path, VALID.replace("1: {path: saes/one}", "1: {train: {d_sae: 128, k: 4}}")))
    assert alone.steering_settings(1).sae == str(trained) and alone.steering_settings(1, borrowed=True).sae is None
    with pytest.raises(ValueError, match="sae.4 has no `train` section"):
        config.train_settings(4)


def test_a_shared_run_config_is_the_one_parse_of_its_run(tmp_path, monkeypatch):
    import contextvars
    import threading

    from tasks.run_configs import run_config, sharing

    path = write_yaml(tmp_path, VALID)
    parsed = load_run_config(path)
    monkeypatch.chdir(tmp_path)
    with sharing(parsed, path, "s3://bucket/run.yaml"):
        assert run_config(path) is parsed and run_config("run.yaml") is parsed  # by the file, however named
        assert run_config("s3://bucket/run.yaml") is parsed
        seen = []
        context = contextvars.copy_context()  # what Prefect's task threads run in
        worker = threading.Thread(target=context.run, args=(lambda: seen.append(run_config(path)),))
        worker.start()
        worker.join()
        assert seen == [parsed] and seen[0] is parsed
        other = write_yaml(tmp_path, VALID.replace("drawer_stove", "another"), "other.yaml")
        assert run_config(other).name == "another"  # another file is read
    fresh = run_config(path)
    assert fresh is not parsed and fresh == parsed  # outside the run: read again
