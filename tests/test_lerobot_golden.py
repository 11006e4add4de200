"""lerobot's pi0.5 folder: our policy against lerobot 0.6.1's own PI05Policy and processors (golden fixture).

The fixture (tests/fixtures/lerobot_golden, README there) was written by lerobot itself on a tiny random model whose
`embed_tokens` differs from its `lm_head`; every number here is lerobot's, none is recomputed with our code.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_pi05 import golden_steering
from safetensors.torch import load_file, save_file

from steering_core.pi05 import Pi05Policy, PromptTokenizer
from steering_core.pi05.expert import euler_times
from steering_core.pi05.layouts import LEROBOT, LayoutName, resolve_checkpoint
from steering_core.synthetic.pi05 import tiny_arch

GOLDEN = Path(__file__).parent / "fixtures" / "lerobot_golden"
MODEL = GOLDEN / "model"
TOKENIZER_JSON = GOLDEN / "tokenizer" / "tokenizer.json"
SENTENCEPIECE = GOLDEN / "tokenizer" / "tokenizer.model"
ARCH = tiny_arch(512)
MAX_LEN = 96
PREFIX_LEN = 3 * ARCH.tokens_per_image + MAX_LEN
EMBED_TOKENS = "model.paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight"
LM_HEAD = "model.paligemma_with_expert.paligemma.lm_head.weight"


@pytest.fixture(scope="module")
def golden():
    return load_file(str(GOLDEN / "golden.safetensors"))


@pytest.fixture(scope="module")
def meta():
    return json.loads((GOLDEN / "golden_meta.json").read_text())


@pytest.fixture(scope="module")
def policy():
    return Pi05Policy.from_checkpoint(MODEL, ARCH, device="cpu", tokenizer_path=TOKENIZER_JSON)


def model_inputs(golden):
    images = [golden[f"preprocessed.images.{slot}"] for slot in range(3)]
    masks = [golden[f"preprocessed.image_masks.{slot}"] for slot in range(3)]
    return images, masks, golden["preprocessed.tokens"], golden["preprocessed.attention_mask"]


def folder_copy(tmp_path, name="model"):
    """Return a writable copy of the fixture's lerobot folder."""
    return Path(shutil.copytree(MODEL, tmp_path / name))


# ----------------------------------------------------------------------------- the folder


def test_lerobot_folder_is_detected_and_embeds_with_embed_tokens():
    checkpoint = resolve_checkpoint(MODEL)
    assert checkpoint.layout is LEROBOT and checkpoint.embedding == EMBED_TOKENS
    stored = load_file(str(MODEL / "model.safetensors"))
    assert (stored[EMBED_TOKENS] - stored[LM_HEAD]).abs().max() > 0.1  # the trap is in the fixture
    assert resolve_checkpoint(MODEL / "model.safetensors", "lerobot").layout is LEROBOT


def test_dimensions_come_from_the_tensors_not_the_variant_names(policy):
    config = json.loads((MODEL / "config.json").read_text())
    assert (config["paligemma_variant"], config["action_expert_variant"]) == ("gemma_2b", "gemma_300m")
    expert = policy.expert_arch
    assert (policy.arch.width, expert.width, expert.depth, expert.mlp_dim) == (64, 32, 4, 64)
    assert (policy.action_horizon, policy.tokenizer.max_len, policy.layout) == (10, MAX_LEN, "lerobot")


# ----------------------------------------------------------------------------- actions


@pytest.mark.parametrize("case", [None, "a_lm_one_layer", "b_lm_two_layers", "c_expert_layer"])
@pytest.mark.parametrize("attention", ["sdpa", "eager"])
def test_matches_lerobot_sample_actions(golden, policy, case, attention):
    policy.attention = attention
    try:
        steering = golden_steering(golden, case, PREFIX_LEN) if case else None
        actions = policy.sample_actions(*model_inputs(golden), noise=golden["inputs.noise"], steering=steering)
    finally:
        policy.attention = "sdpa"
    expected = golden[f"steer.{case}.actions" if case else "actions"]
    torch.testing.assert_close(actions, expected, rtol=0, atol=1e-4)
    if case:  # the case really steers
        assert (expected - golden["actions"]).abs().max() > 0.1


def test_last_lm_layer_is_a_no_op_in_lerobot_too_and_refused(golden, policy):
    case = "d_lm_last_layer_noop"
    assert torch.equal(golden[f"steer.{case}.actions"], golden["actions"])
    with pytest.raises(ValueError, match="the last language-model layer's output only feeds the final norm"):
        policy.sample_actions(*model_inputs(golden), noise=golden["inputs.noise"],
                              steering=golden_steering(golden, case, PREFIX_LEN))


def test_first_denoising_velocity_matches(golden, policy):
    # one Euler step from t = 1 with dt = -1: x = noise - v(noise, 1), lerobot's first velocity of the 10-step run
    noise = golden["inputs.noise"]
    one_step = policy.sample_actions(*model_inputs(golden), noise=noise, num_steps=1)
    torch.testing.assert_close(noise - one_step, golden["debug.v_t_step0"], rtol=0, atol=1e-4)


def test_flow_times_are_lerobots_not_openpis(golden, policy):
    _, times = euler_times(10, torch.device("cpu"), policy.accumulated_time)
    assert torch.equal(torch.stack(times), golden["debug.timesteps"])
    _, openpi = euler_times(10, torch.device("cpu"))
    assert not torch.equal(torch.stack(openpi), golden["debug.timesteps"])  # 0.79999995 against 0.8


def test_robot_actions_match_lerobots_postprocessor(golden, policy):
    robot = policy.robot_actions(golden["actions"])
    assert robot.shape == (2, 10, 7) and robot.dtype == np.float32
    np.testing.assert_allclose(robot, golden["robot_actions"].numpy(), rtol=0, atol=1e-5)


def test_raw_observation_to_robot_actions_end_to_end(golden, meta, policy):
    image, wrist = (golden[f"inputs.observation.images.{name}"] for name in ("image", "wrist_image"))
    assert image.shape[-2:] != (ARCH.image_size,) * 2  # lerobot's resize ran
    images, masks = policy.cameras.from_float(image, wrist, ARCH.image_size)
    tokens, token_mask = policy.tokenize(meta["tasks"], golden["inputs.observation.state"].numpy())
    actions = policy.sample_actions(images, masks, tokens, token_mask, noise=golden["inputs.noise"])
    np.testing.assert_allclose(policy.robot_actions(actions), golden["e2e.robot_actions"].numpy(), rtol=0, atol=1e-4)


# ----------------------------------------------------------------------------- preprocessing


def test_prompt_tokens_and_state_match_lerobots_preprocessor(golden, meta, policy):
    state = golden["inputs.observation.state"].numpy()
    normalized = policy.normalization.normalize_state(state)
    np.testing.assert_array_equal(normalized, golden["preprocessed.normalized_state"].numpy())  # float32, bit-exact
    assert [policy.tokenizer.prompt_text(task, s) for task, s in zip(meta["tasks"], normalized)] == meta["prompts"]
    tokens, mask = policy.tokenize(meta["tasks"], state)
    assert torch.equal(tokens, golden["preprocessed.tokens"]) and torch.equal(mask, golden["preprocessed.attention_mask"])


def test_camera_slots_match_lerobots_image_preprocessing(golden, policy):
    image, wrist = (golden[f"inputs.observation.images.{name}"] for name in ("image", "wrist_image"))
    images, masks = policy.cameras.from_float(image, wrist, ARCH.image_size)
    for slot in range(3):
        torch.testing.assert_close(images[slot], golden[f"preprocessed.images.{slot}"], rtol=0, atol=1e-6)
        assert torch.equal(masks[slot], golden[f"preprocessed.image_masks.{slot}"])
    assert masks[2].logical_not().all() and images[2].eq(-1).all()  # the empty camera


@pytest.mark.parametrize("prompt_index", [0, 1])
def test_sentencepiece_and_tokenizer_json_give_the_same_ids(meta, prompt_index):
    by_json = PromptTokenizer(TOKENIZER_JSON, MAX_LEN, "discrete_state")
    by_model = PromptTokenizer(SENTENCEPIECE, MAX_LEN, "discrete_state")
    assert by_json.vocab_size == by_model.vocab_size
    task = meta["tasks"][prompt_index]
    state = np.linspace(-1.2, 1.2, 8)
    one, other = by_json.tokenize(task, state), by_model.tokenize(task, state)
    assert np.array_equal(one.ids, other.ids) and one.instruction == other.instruction and one.n_valid == other.n_valid
    libero_json, libero_model = (PromptTokenizer(path, MAX_LEN, "libero") for path in (TOKENIZER_JSON, SENTENCEPIECE))
    for text in (task, "open the top drawer of the cabinet", "Ünïcode_and  double  spaces\n"):
        assert np.array_equal(libero_json.tokenize(text).ids, libero_model.tokenize(text).ids), text


def test_a_tokenizer_folder_reads_its_tokenizer_json(meta):
    folder, file = (PromptTokenizer(path, MAX_LEN, "discrete_state") for path in (TOKENIZER_JSON.parent, TOKENIZER_JSON))
    state = np.linspace(-1.0, 1.0, 8)
    assert np.array_equal(folder.tokenize(meta["tasks"][0], state).ids, file.tokenize(meta["tasks"][0], state).ids)
    with pytest.raises(FileNotFoundError, match="tokenizer.json: tokenizer not found"):
        PromptTokenizer(SENTENCEPIECE.parent.parent, MAX_LEN)  # a folder without one


# ----------------------------------------------------------------------------- the embedding table


def test_missing_embed_tokens_falls_back_to_lm_head_as_lerobot_does(golden, tmp_path, caplog):
    folder = folder_copy(tmp_path)
    tensors = load_file(str(folder / "model.safetensors"))
    del tensors[EMBED_TOKENS]
    save_file(tensors, str(folder / "model.safetensors"))
    with caplog.at_level(logging.WARNING, logger="steering_core.pi05.layouts"):
        fallback = Pi05Policy.from_checkpoint(folder, ARCH, device="cpu")
    assert f"no {EMBED_TOKENS}; embedding tokens with {LM_HEAD}" in caplog.text
    actions = fallback.sample_actions(*model_inputs(golden), noise=golden["inputs.noise"])
    torch.testing.assert_close(actions, golden["fallback.actions"], rtol=0, atol=1e-4)
    assert (golden["fallback.actions"] - golden["actions"]).abs().max() > 0.1  # the table matters


# ----------------------------------------------------------------------------- MEAN_STD statistics


def test_mean_std_statistics_follow_lerobots_formulas(golden, meta, tmp_path):
    folder = folder_copy(tmp_path)
    for path in (GOLDEN / "mean_std").iterdir():
        shutil.copy(path, folder / path.name)
    config = json.loads((folder / "config.json").read_text())
    config["normalization_mapping"] |= {"STATE": "MEAN_STD", "ACTION": "MEAN_STD"}
    (folder / "config.json").write_text(json.dumps(config))
    policy = Pi05Policy.from_checkpoint(folder, ARCH, device="cpu", tokenizer_path=TOKENIZER_JSON)
    state = golden["inputs.observation.state"].numpy()
    np.testing.assert_array_equal(policy.normalization.normalize_state(state), golden["mean_std.normalized_state"].numpy())
    tokens, mask = policy.tokenize(meta["tasks"], state)
    assert torch.equal(tokens, golden["mean_std.tokens"]) and torch.equal(mask, golden["mean_std.attention_mask"])
    np.testing.assert_allclose(policy.robot_actions(golden["actions"]), golden["mean_std.robot_actions"].numpy(),
                               rtol=0, atol=1e-5)
    assert not np.allclose(golden["mean_std.robot_actions"].numpy(), golden["robot_actions"].numpy(), atol=1e-3)


# ----------------------------------------------------------------------------- bad folders, one line each


def rewrite_json(path: Path, **changes) -> None:
    payload = json.loads(path.read_text())
    for dotted, value in changes.items():
        target = payload
        *parents, last = dotted.split("__")
        for key in parents:
            target = target[key]
        target[last] = value
    path.write_text(json.dumps(payload))


def bad_both_layouts(folder):
    (folder / "assets" / "physical-intelligence" / "libero").mkdir(parents=True)
    (folder / "assets" / "physical-intelligence" / "libero" / "norm_stats.json").write_text("{}")
    return "the folder mixes two layouts"


def bad_stats_width(folder):
    payload = json.loads((folder / "config.json").read_text())
    payload["input_features"]["observation.state"]["shape"] = [9]
    (folder / "config.json").write_text(json.dumps(payload))
    return r"`observation.state.\w+` is \(8,\) float32, expected \(9,\)"


def bad_type(kind):
    def make(folder):
        rewrite_json(folder / "config.json", type=kind)
        return f"type '{kind}' is not pi0.5; expected 'pi05'"
    return make


def bad_mixed_keys(folder):
    tensors = load_file(str(folder / "model.safetensors"))
    tensors["action_in_proj.weight"] = tensors.pop("model.action_in_proj.weight")
    save_file(tensors, str(folder / "model.safetensors"))
    return "the file mixes two layouts"


def bad_mode_disagrees(folder):
    rewrite_json(folder / "config.json", normalization_mapping__ACTION="MEAN_STD")
    return "normalises action with 'QUANTILES', config.json's normalization_mapping says 'MEAN_STD'"


def bad_stats_scale(folder):
    path = folder / "policy_postprocessor_step_0_unnormalizer_processor.safetensors"
    stats = load_file(str(path))
    stats["action.q99"][2] = 1e38
    save_file(stats, str(path))
    return r"unnormalizer_processor.safetensors: `action.q99` holds 1e\+38, expected magnitudes up to 1e\+06"


def bad_missing_processor(folder):
    (folder / "policy_postprocessor.json").unlink()
    return "policy_postprocessor.json: not found"


@pytest.mark.parametrize("make", [bad_both_layouts, bad_stats_width, bad_type("pi0"), bad_type("smolvla"),
                                  bad_mixed_keys, bad_mode_disagrees, bad_missing_processor, bad_stats_scale],
                         ids=["both_layouts", "stats_width", "type_pi0", "type_smolvla", "mixed_keys",
                              "mode_disagrees", "missing_processor", "stats_scale"])
def test_bad_lerobot_folders_are_refused_in_one_line(tmp_path, make):
    folder = folder_copy(tmp_path)
    expected = make(folder)
    with pytest.raises((ValueError, FileNotFoundError), match=expected) as err:
        Pi05Policy.from_checkpoint(folder, ARCH, device="cpu")
    message = str(err.value)
    assert "\n" not in message and str(folder) in message


def test_a_forced_layout_the_folder_contradicts_is_refused():
    with pytest.raises(ValueError, match="the layout was set to openpi, but the file is lerobot's"):
        resolve_checkpoint(MODEL, LayoutName.OPENPI)


def test_arguments_that_contradict_the_lerobot_folder_are_refused():
    with pytest.raises(ValueError, match="lerobot's pi0.5 always reads the discretised state in its prompt"):
        Pi05Policy.from_checkpoint(MODEL, ARCH, device="cpu", prompt_format="libero")
    with pytest.raises(ValueError, match="chunk_size 10, but an action horizon of 50 was asked for"):
        Pi05Policy.from_checkpoint(MODEL, ARCH, device="cpu", action_horizon=50)
