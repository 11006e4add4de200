"""pi0.5 policy: openpi's own sample_actions (golden fixture), a naive float64 reference, steering semantics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_pi05 import golden_steering, make_batch
from reference_policy import reference_actions
from safetensors.torch import load_file, save_file

from steering_core.pi05 import Pi05Policy, PromptTokenizer, Steering
from steering_core.pi05.checkpoint import MODEL_FILE
from steering_core.pi05.preprocess import resize_with_pad, to_model_range
from steering_core.synthetic.pi05 import tiny_arch, tiny_expert_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

GOLDEN = Path(__file__).parent / "fixtures" / "openpi_golden"
SLOTS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
ARCH = tiny_arch()
EXPERT = tiny_expert_arch(ARCH)
MAX_LEN = 24
PREFIX_LEN = 3 * ARCH.tokens_per_image + MAX_LEN


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def golden():
    return load_file(str(GOLDEN / "golden.safetensors"))


@pytest.fixture(scope="module")
def golden_policy(golden, tmp_path_factory):
    # the golden's output transform used 7-dim action quantiles; mean/std are not read by it
    q01, q99 = golden["transforms.q01_actions"].double(), golden["transforms.q99_actions"].double()
    stats = {"actions": {"mean": [0.0] * 7, "std": [1.0] * 7, "q01": q01.tolist(), "q99": q99.tolist()}}
    stats_file = tmp_path_factory.mktemp("golden") / "norm_stats.json"
    stats_file.write_text(json.dumps({"norm_stats": stats}))
    return Pi05Policy.from_checkpoint(GOLDEN, tiny_arch(512), device="cpu", norm_stats_path=stats_file)


def golden_inputs(golden):
    images = [golden[f"inputs.image.{slot}"] for slot in SLOTS]
    masks = [golden[f"inputs.image_mask.{slot}"] for slot in SLOTS]
    return images, masks, golden["inputs.tokenized_prompt"], golden["inputs.tokenized_prompt_mask"]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_pi05_checkpoint(tmp_path_factory.mktemp("pi05") / "ckpt", ARCH, seed=3)


@pytest.fixture(scope="module")
def tokenizer_path(tmp_path_factory):
    return write_tokenizer(tmp_path_factory.mktemp("tok") / "tokenizer.model")


@pytest.fixture(scope="module")
def policy(checkpoint, tokenizer_path):
    return Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu", tokenizer_path=tokenizer_path)


@pytest.fixture(scope="module")
def batch(tokenizer_path):
    return make_batch(ARCH, PromptTokenizer(tokenizer_path, max_len=MAX_LEN))


@pytest.fixture(scope="module")
def noise():
    return torch.randn(3, 10, 32, generator=torch.Generator().manual_seed(5))


def vector(width, seed):
    return torch.randn(width, generator=torch.Generator().manual_seed(seed))


def prompt_columns(token_mask):
    """Return (B, P) bool: the prompt positions of `token_mask` in the full prefix."""
    return torch.cat([torch.zeros(token_mask.shape[0], 3 * ARCH.tokens_per_image, dtype=torch.bool), token_mask], 1)


# ----------------------------------------------------------------------------- openpi golden


@pytest.mark.parametrize("case", [None, "a_lm_one_layer", "b_lm_two_layers", "c_expert_layer"])
@pytest.mark.parametrize("attention", ["sdpa", "eager"])
def test_matches_openpi_sample_actions(golden, golden_policy, case, attention):
    golden_policy.attention = attention
    try:
        steering = golden_steering(golden, case, 28) if case else None
        actions = golden_policy.sample_actions(*golden_inputs(golden), noise=golden["inputs.noise"], steering=steering)
    finally:
        golden_policy.attention = "sdpa"
    expected = golden[f"steer.{case}.actions" if case else "actions"]
    assert actions.dtype == torch.float32 and actions.shape == (2, 10, 32)
    torch.testing.assert_close(actions, expected, rtol=0, atol=1e-4)
    if case:  # the case really steers
        assert (expected - golden["actions"]).abs().max() > 0.1


def test_last_lm_layer_is_refused_as_openpi_shows_it_changes_nothing(golden, golden_policy):
    case = "d_lm_last_layer_noop"
    assert torch.equal(golden[f"steer.{case}.actions"], golden["actions"])  # openpi's own policy: a no-op
    with pytest.raises(ValueError, match="the last language-model layer's output only feeds the final norm"):
        golden_policy.sample_actions(*golden_inputs(golden), noise=golden["inputs.noise"],
                                     steering=golden_steering(golden, case, 28))


def test_robot_actions_match_openpi_output_transform(golden, golden_policy):
    robot = golden_policy.robot_actions(golden["actions"])
    assert robot.shape == (2, 10, 7) and robot.dtype == np.float32
    np.testing.assert_allclose(robot, golden["transforms.libero_actions"].numpy(), rtol=1e-6, atol=1e-6)


def test_bfloat16_policy_is_within_rounding_of_openpi_bfloat16(golden):
    # openpi's own bf16 policy (run on CPU) differs from its float32 result by its rounding; ours must be as
    # close to it as that (not bit-exact: kernels and summation orders differ)
    half = Pi05Policy.from_checkpoint(GOLDEN, tiny_arch(512), device="cpu", dtype="bfloat16")
    actions = half.sample_actions(*golden_inputs(golden), noise=golden["inputs.noise"])
    openpi = golden["extra.actions_bf16_policy_cpu"]
    rounding = (openpi - golden["actions"]).abs().max()
    assert 0 < (actions - openpi).abs().max() < 1.5 * rounding


def test_golden_expert_dimensions_are_read_from_the_checkpoint(golden_policy):
    expert = golden_policy.expert_arch
    assert (expert.width, expert.depth, expert.mlp_dim, expert.head_dim) == (32, 4, 64, 16)


# ----------------------------------------------------------------------------- float64 reference


def steering_forms(batch):
    """Return name -> (Steering list, the reference's description of it) for every steering form."""
    lm_v, lm_w, ex_v = vector(ARCH.width, 1), vector(ARCH.width, 2), vector(EXPERT.width, 3)
    instruction = batch.token_mask.clone()
    instruction[:, 0] = False  # not BOS
    some = torch.zeros(3, PREFIX_LEN, dtype=torch.bool)
    some[:, [0, 3, 5, 13, 14, 20]] = True  # images of cameras 0 and 1 and the first prompt tokens
    forms = {
        "lm_default": ([Steering(1, lm_v, 2.0)], [("lm", 1, lm_v, 2.0, prompt_columns(batch.token_mask))]),
        "lm_token_mask": ([Steering(0, lm_v, -3.0, token_mask=instruction)],
                          [("lm", 0, lm_v, -3.0, prompt_columns(instruction))]),
        "lm_prefix_mask": ([Steering(2, lm_w, 4.0, prefix_mask=some)], [("lm", 2, lm_w, 4.0, some)]),
        "lm_two_layers": ([Steering(0, lm_v, 1.5, prefix_mask=some), Steering(2, lm_w, -2.0)],
                          [("lm", 0, lm_v, 1.5, some), ("lm", 2, lm_w, -2.0, prompt_columns(batch.token_mask))]),
        "expert": ([Steering(1, ex_v, 3.0, stream="expert")], [("expert", 1, ex_v, 3.0, None)]),
        "lm_and_expert": ([Steering(1, lm_v, 2.0), Steering(3, ex_v, -1.0, stream="expert")],
                          [("lm", 1, lm_v, 2.0, prompt_columns(batch.token_mask)), ("expert", 3, ex_v, -1.0, None)]),
    }
    return {
        name: (items, [dict(zip(("stream", "layer", "vector", "alpha", "columns"), spec)) for spec in specs])
        for name, (items, specs) in forms.items()
    }


@pytest.mark.parametrize(
    "form", [None, "lm_default", "lm_token_mask", "lm_prefix_mask", "lm_two_layers", "expert", "lm_and_expert"]
)
def test_matches_float64_reference(policy, checkpoint, batch, noise, form):
    steering, spec = steering_forms(batch)[form] if form else (None, ())
    actions = policy.sample_actions(*batch.args(), noise=noise, num_steps=4, steering=steering)
    expected = reference_actions(checkpoint / MODEL_FILE, ARCH, *batch.args(), noise, num_steps=4, steering=spec)
    torch.testing.assert_close(actions.double(), expected, rtol=1e-5, atol=1e-5)
    if form:
        unsteered = policy.sample_actions(*batch.args(), noise=noise, num_steps=4)
        assert (actions - unsteered).abs().max() > 1e-2


def test_ten_steps_and_generator_noise(policy, checkpoint, batch):
    drawn = policy.sample_actions(*batch.args(), generator=torch.Generator().manual_seed(9))
    noise = torch.randn(3, 10, 32, generator=torch.Generator().manual_seed(9))
    expected = reference_actions(checkpoint / MODEL_FILE, ARCH, *batch.args(), noise, num_steps=10)
    torch.testing.assert_close(drawn.double(), expected, rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- steering semantics


def test_alpha_zero_is_bit_identical(policy, batch, noise):
    plain = policy.sample_actions(*batch.args(), noise=noise, num_steps=3)
    zero = [Steering(1, vector(ARCH.width, 1), 0.0), Steering(2, vector(EXPERT.width, 2), 0.0, stream="expert")]
    assert torch.equal(policy.sample_actions(*batch.args(), noise=noise, num_steps=3, steering=zero), plain)


def test_last_lm_layer_is_refused_in_one_line(policy, batch, noise):
    last = [Steering(1, vector(ARCH.width, 1), 1.0), Steering(ARCH.depth - 1, vector(ARCH.width, 1), 50.0)]
    message = (rf"^steering\[1\] \(lm layer {ARCH.depth - 1}\): the last language-model layer's output only feeds the "
               rf"final norm, which no action reads, so steering it cannot change the actions; steer a layer below "
               rf"{ARCH.depth - 1}$")
    with pytest.raises(ValueError, match=message):
        policy.sample_actions(*batch.args(), noise=noise, num_steps=3, steering=last)
    with pytest.raises(ValueError, match=message):
        policy.sample_actions_sweep(*batch.args(), [None, last], noise=noise, num_steps=3)


def test_steering_invalid_positions_changes_nothing(policy, batch, noise):
    # the masked right wrist (every row), the partly masked cameras' masked rows, and prompt padding
    invalid = ~batch.valid(ARCH)
    assert invalid[:, 2 * ARCH.tokens_per_image : 3 * ARCH.tokens_per_image].all() and invalid[:, -1].all()
    assert (invalid[:, : 2 * ARCH.tokens_per_image].any(dim=1) == torch.tensor([False, True, True])).all()
    plain = policy.sample_actions(*batch.args(), noise=noise, num_steps=3)
    steering = [Steering(0, vector(ARCH.width, 1), 100.0, prefix_mask=invalid),
                Steering(1, vector(ARCH.width, 2), 100.0, token_mask=~batch.token_mask)]
    assert torch.equal(policy.sample_actions(*batch.args(), noise=noise, num_steps=3, steering=steering), plain)


def test_sweep_equals_separate_calls(policy, batch, noise):
    lm_v, ex_v = vector(ARCH.width, 1), vector(EXPERT.width, 2)
    entries = [
        None,
        Steering(2, lm_v, 1.0),
        [Steering(1, lm_v, -2.0), Steering(0, lm_v, 5.0)],
        Steering(0, ex_v, 2.0, stream="expert"),
        [Steering(2, lm_v, 3.0), Steering(1, ex_v, -1.0, stream="expert")],
    ]
    swept = policy.sample_actions_sweep(*batch.args(), entries, noise=noise, num_steps=3)
    assert swept.shape == (5, 3, 10, 32)
    for index, entry in enumerate(entries):
        alone = policy.sample_actions(*batch.args(), noise=noise, num_steps=3, steering=entry)
        torch.testing.assert_close(swept[index], alone, rtol=1e-5, atol=1e-5)
    only_expert = policy.sample_actions_sweep(*batch.args(), [entries[3], None], noise=noise, num_steps=3)
    torch.testing.assert_close(only_expert[1], swept[0], rtol=1e-5, atol=1e-5)


def test_alpha_sweep_shares_noise_drawn_once(policy, batch):
    """Two equal entries of one sweep get the same actions: one noise draw for all. Equal within float32 rounding,
    not bitwise: a CPU kernel may round a row differently at another position of the batch (AVX-512 ones do);
    another draw moves the actions by O(1)."""
    lm_v = vector(ARCH.width, 1)
    swept = policy.sample_actions_sweep(*batch.args(), [Steering(1, lm_v, a) for a in (0.0, 0.0)], num_steps=2,
                                        generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(swept[0], swept[1], rtol=1e-5, atol=1e-5)
    redrawn = policy.sample_actions(*batch.args(), num_steps=2, generator=torch.Generator().manual_seed(2))
    assert (redrawn - swept[0]).abs().max() > 0.1


# ----------------------------------------------------------------------------- robot side


def test_infer_runs_openpi_libero_preprocessing(policy, tokenizer_path):
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (40, 30, 3), dtype=np.uint8)
    wrist = rng.integers(0, 256, (28, 28, 3), dtype=np.uint8)
    prompt = "open the top drawer of the cabinet"
    noise = torch.randn(10, 32, generator=torch.Generator().manual_seed(2))
    observation = {"observation/image": base, "observation/wrist_image": wrist,
                   "observation/state": np.zeros(8), "prompt": prompt}
    result = policy.infer(observation, noise=noise)
    assert result["actions"].shape == (10, 7) and result["policy_timing"]["infer_ms"] > 0
    # by hand: HWC -> CHW, resize-with-pad to 28, [-1, 1], an all -1 masked third camera, BOS + text + "\n"
    chw = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None]  # noqa: E731
    images = [to_model_range(resize_with_pad(chw(base), 28)), to_model_range(chw(wrist)), -torch.ones(1, 3, 28, 28)]
    masks = [torch.tensor([True]), torch.tensor([True]), torch.tensor([False])]
    encoded = PromptTokenizer(tokenizer_path).tokenize(prompt)
    tokens, mask = torch.from_numpy(encoded.ids)[None], torch.from_numpy(encoded.mask)[None]
    assert tokens.shape == (1, 200) and tokens[0, 0] == 2
    model = policy.sample_actions(images, masks, tokens, mask, noise=noise[None])
    stats = policy.normalization.stats["actions"]
    by_hand = (model[0, :, :7].double().numpy() + 1) / 2 * (stats.q99 - stats.q01 + 1e-6) + stats.q01
    np.testing.assert_allclose(result["actions"], by_hand, rtol=1e-6, atol=1e-6)
    # a batched observation gives the same rows
    batched = {key: np.stack([value, value]) if key != "prompt" else [prompt, prompt]
               for key, value in observation.items()}
    twice = policy.infer(batched, noise=torch.stack([noise, noise]))["actions"]
    assert twice.shape == (2, 10, 7)
    np.testing.assert_allclose(twice[1], result["actions"], rtol=1e-5, atol=1e-5)


def test_instruction_mask_covers_the_instruction_tokens(policy, tokenizer_path):
    prompt = "put the bowl on the plate"
    mask = policy.instruction_mask(prompt)
    encoded = PromptTokenizer(tokenizer_path).tokenize(prompt)
    assert mask.shape == (1, 200) and mask.dtype == torch.bool
    assert mask[0].nonzero().flatten().tolist() == list(range(1, encoded.n_valid - 1))  # not BOS, not "\n"


def test_metadata_is_json(policy):
    meta = json.loads(json.dumps(policy.metadata))
    assert meta["action_horizon"] == 10 and meta["action_dim"] == 32
    assert meta["steerable"] == {"lm": {"width": 64, "layers": 4}, "expert": {"width": 32, "layers": 4}}


def test_bfloat16_policy_keeps_float32_norms_and_heads(checkpoint, policy, batch, noise):
    half = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu", dtype="bfloat16")
    float32 = {name for name, p in half.expert.named_parameters() if p.dtype == torch.float32}
    heads = {f"{head}.{kind}" for head in ("action_in_proj", "action_out_proj", "time_mlp_in", "time_mlp_out")
             for kind in ("weight", "bias")}
    norms = {f"layers.{i}.{norm}.dense.{kind}" for i in range(EXPERT.depth)
             for norm in ("input_layernorm", "post_attention_layernorm") for kind in ("weight", "bias")}
    assert float32 == heads | norms | {"norm.dense.weight", "norm.dense.bias"}
    assert half.expert.layers[0].mlp.up_proj.weight.dtype == torch.bfloat16
    actions = half.sample_actions(*batch.args(), noise=noise, num_steps=3)
    reference = policy.sample_actions(*batch.args(), noise=noise, num_steps=3)
    assert actions.dtype == torch.float32
    assert 0 < (actions - reference).norm() / reference.norm() < 0.05


# ----------------------------------------------------------------------------- bad input


def test_bad_steering_is_one_clear_error(policy, batch):
    with pytest.raises(ValueError) as err:
        policy.sample_actions(*batch.args(), steering=[
            Steering(1, vector(EXPERT.width, 1)),  # an expert-width vector on the lm stream
            Steering(4, vector(ARCH.width, 1)),
            Steering(0, vector(ARCH.width, 1), token_mask=torch.ones(3, 5, dtype=torch.bool)),
            Steering(0, vector(ARCH.width, 1), prefix_mask=torch.ones(2, PREFIX_LEN, dtype=torch.bool)),
            Steering(4, vector(EXPERT.width, 1), stream="expert"),
        ])
    message = str(err.value)
    assert "steering[0] (lm layer 1): vector width 32, expected 64 for the lm stream; a width-32 vector fits the " \
           "expert stream" in message
    assert "steering[1] (lm layer 4): layer out of range, the lm stream has 4 layers (0..3)" in message
    assert "steering[2] (lm layer 0): token_mask is (3, 5), expected (3, 24)" in message
    assert f"steering[3] (lm layer 0): prefix_mask is (2, {PREFIX_LEN}), expected (3, {PREFIX_LEN})" in message
    assert "steering[4] (expert layer 4): layer out of range, the expert stream has 4 layers" in message
    with pytest.raises(ValueError, match="give token_mask or prefix_mask, not both"):
        Steering(0, vector(ARCH.width, 1), token_mask=batch.token_mask, prefix_mask=batch.valid(ARCH))
    with pytest.raises(ValueError, match="expert steering applies at every action token; it takes no token_mask"):
        Steering(0, vector(EXPERT.width, 1), token_mask=batch.token_mask, stream="expert")
    with pytest.raises(ValueError, match=r"token_mask must be a 2-D bool tensor, found \(3, 24\) torch.int64"):
        Steering(0, vector(ARCH.width, 1), token_mask=batch.token_mask.long())
    with pytest.raises(ValueError, match=r"noise: found \(3, 10, 7\) torch.float32, expected \(3, 10, 32\)"):
        policy.sample_actions(*batch.args(), noise=torch.zeros(3, 10, 7))
    with pytest.raises(ValueError, match=r"images\[0\]: found \(3, 3, 14, 28\)"):
        policy.sample_actions([batch.images[0][:, :, :14], *batch.images[1:]], *batch.args()[1:])


def test_prefix_only_checkpoint_is_refused(checkpoint, tmp_path):
    tensors = load_file(str(checkpoint / MODEL_FILE))
    prefix_only = {name: t for name, t in tensors.items() if name.startswith("paligemma_with_expert.paligemma.")}
    save_file(prefix_only, str(tmp_path / MODEL_FILE))
    with pytest.raises(ValueError, match="no action expert .* prefix-only checkpoint"):
        Pi05Policy.from_checkpoint(tmp_path, ARCH, device="cpu")
    without_layer = {name: t for name, t in tensors.items() if ".gemma_expert.model.layers.3." not in name}
    save_file(without_layer, str(tmp_path / MODEL_FILE))
    with pytest.raises(ValueError, match="the Pi05Arch asks for depth 4, but it holds 3 action expert layers"):
        Pi05Policy.from_checkpoint(tmp_path, ARCH, device="cpu")
    without_head = {name: t for name, t in tensors.items() if not name.startswith("time_mlp_out")}
    save_file(without_head, str(tmp_path / MODEL_FILE))
    with pytest.raises(ValueError, match=r"2 of \d+ action expert tensors are missing.*\n  time_mlp_out.bias: missing"):
        Pi05Policy.from_checkpoint(tmp_path, ARCH, device="cpu")


def test_missing_norm_stats_and_tokenizer_name_what_is_needed(checkpoint, tmp_path, policy):
    bare = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu", norm_stats_path=tmp_path / "none.json")
    with pytest.raises(FileNotFoundError, match="none.json: norm stats not found"):
        bare.robot_actions(np.zeros((10, 32)))
    with pytest.raises(ValueError, match="no tokenizer: pass tokenizer_path="):
        bare.instruction_mask("open the drawer")
    with pytest.raises(ValueError, match=r"actions: found shape \(10, 7\), expected \(\.\.\., 32\)"):
        policy.robot_actions(np.zeros((10, 7)))


def test_bad_observation_names_the_key(policy):
    image = np.zeros((32, 32, 3), dtype=np.uint8)
    good = {"observation/image": image, "observation/wrist_image": image, "observation/state": np.zeros(8),
            "prompt": "open the drawer"}
    with pytest.raises(ValueError, match=r"missing keys \['observation/wrist_image'\]"):
        policy.infer({k: v for k, v in good.items() if k != "observation/wrist_image"})
    with pytest.raises(ValueError, match=r"`observation/image` is \(32, 32\) uint8, expected \(H, W, 3\)"):
        policy.infer({**good, "observation/image": image[..., 0]})
    with pytest.raises(ValueError, match=r"`observation/wrist_image` is \(3, 32, 32\) uint8"):
        policy.infer({**good, "observation/wrist_image": image.transpose(2, 0, 1)})
    with pytest.raises(ValueError, match=r"`prompt` gives 2 prompts for a batch of 1"):
        policy.infer({**good, "prompt": ["a", "b"]})
