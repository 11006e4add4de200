"""Clamp steering: each steered token's projection on the unit vector set to its level, by hand at the layer's
output (lm and expert), against addition, in sweeps, compiled, and its bad input."""

from __future__ import annotations

from contextlib import contextmanager

import pytest
import torch
from helpers_pi05 import make_batch

from steering_core.pi05 import Pi05Policy, PromptTokenizer, Steering
from steering_core.synthetic.pi05 import tiny_arch, tiny_expert_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

ARCH = tiny_arch()
EXPERT = tiny_expert_arch(ARCH)
MAX_LEN = 24
STEPS = 3


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_pi05_checkpoint(tmp_path_factory.mktemp("pi05") / "ckpt", ARCH, seed=3)


@pytest.fixture(scope="module")
def policy(checkpoint):
    return Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu")


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    tokenizer = PromptTokenizer(write_tokenizer(tmp_path_factory.mktemp("tok") / "tokenizer.model"), max_len=MAX_LEN)
    return make_batch(ARCH, tokenizer)


@pytest.fixture(scope="module")
def noise():
    return torch.randn(3, 10, 32, generator=torch.Generator().manual_seed(5))


def vector(width, seed):
    return torch.randn(width, generator=torch.Generator().manual_seed(seed))


def unit(v):
    return v / v.norm()


def clamp(layer, v, alpha, levels=(-2.0, 3.0), **kwargs):
    return Steering(layer, v, alpha, mode="clamp", levels=levels, **kwargs)


@contextmanager
def layer_output(layers, index):
    """Record, per call, the output of layer `index` before steering (its forward hook) and after (the next
    layer's input)."""
    seen = {"before": [], "after": []}
    handles = [layers[index].register_forward_hook(lambda _m, _a, out: seen["before"].append(out.clone())),
               layers[index + 1].register_forward_pre_hook(lambda _m, args: seen["after"].append(args[0].clone()))]
    try:
        yield seen
    finally:
        for handle in handles:
            handle.remove()


def steered_columns(policy, batch, token_mask):
    """Return (B, S, 1) bool: the computed prefix columns at the prompt positions of `token_mask`."""
    _, _, columns = policy.prefix.embed_prefix(*policy.prefix.on_device(*batch.args()))
    prefix = torch.cat([torch.zeros(token_mask.shape[0], 3 * ARCH.tokens_per_image, dtype=torch.bool), token_mask], 1)
    return prefix[:, columns, None]


def run(policy, batch, noise, stream, layer, steering):
    """Return the layer's outputs before and after steering (lm: the prefix forward; expert: every step)."""
    layers = policy.prefix.layers if stream == "lm" else policy.expert.layers
    with layer_output(layers, layer) as seen:
        policy.sample_actions(*batch.args(), noise=noise, num_steps=STEPS, steering=steering)
    return torch.cat(seen["before"]), torch.cat(seen["after"])


# ----------------------------------------------------------------------------- by hand


@pytest.mark.parametrize("alpha", [0.0, 1.0, 0.3])
def test_lm_clamp_sets_the_projection_at_the_steered_tokens_only(policy, batch, noise, alpha):
    v = vector(ARCH.width, 1)
    instruction = batch.token_mask.clone()
    instruction[:, 0] = False  # not BOS
    levels = (-2.0, 3.0)
    target = levels[0] + alpha * (levels[1] - levels[0])
    before, after = run(policy, batch, noise, "lm", 1, clamp(1, v, alpha, levels, token_mask=instruction))
    plain, _ = run(policy, batch, noise, "lm", 1, None)
    assert torch.equal(before, plain)  # the layers below are not steered
    where = steered_columns(policy, batch, instruction)
    assert where.sum() > 10
    projection = after @ unit(v)
    torch.testing.assert_close(projection[where[..., 0]], torch.full((int(where.sum()),), target), rtol=0, atol=1e-5)
    expected = before + (target - before @ unit(v))[..., None] * unit(v)
    torch.testing.assert_close(after, torch.where(where, expected, before), rtol=1e-6, atol=1e-5)
    assert torch.equal(after[~where[..., 0]], before[~where[..., 0]])  # every other token untouched


def test_expert_clamp_sets_the_projection_at_every_action_token_of_every_step(policy, batch, noise):
    v = vector(EXPERT.width, 2)
    before, after = run(policy, batch, noise, "expert", 1, clamp(1, v, 0.25, stream="expert"))
    assert before.shape == (STEPS * 3, 10, EXPERT.width)
    plain, _ = run(policy, batch, noise, "expert", 1, None)
    assert torch.equal(before[:3], plain[:3])  # the first step's layer 1 sees no steering yet
    torch.testing.assert_close(after @ unit(v), torch.full(after.shape[:2], -0.75), rtol=0, atol=1e-5)
    torch.testing.assert_close(after, before + (-0.75 - before @ unit(v))[..., None] * unit(v), rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("stream", ["lm", "expert"])
def test_a_clamp_applies_before_the_additions_of_its_layer(policy, batch, noise, stream):
    width = ARCH.width if stream == "lm" else EXPERT.width
    v, w = vector(width, 1), vector(width, 2)
    steering = [Steering(1, w, 0.5, stream=stream), clamp(1, v, 0.6, stream=stream), Steering(1, v, -2.0, stream=stream)]
    before, after = run(policy, batch, noise, stream, 1, steering)
    clamped = before + (1.0 - before @ unit(v))[..., None] * unit(v)
    expected = clamped + 0.5 * w - 2.0 * v
    if stream == "lm":
        expected = torch.where(steered_columns(policy, batch, batch.token_mask), expected, before)
    torch.testing.assert_close(after, expected, rtol=1e-6, atol=1e-5)


def test_clamp_and_add_differ_as_their_formulas_say(policy, batch, noise):
    """A token already at the target is left alone by a clamp and moved by an addition; elsewhere both move it,
    each by its own formula."""
    v = vector(ARCH.width, 1)
    one = torch.zeros_like(batch.token_mask)
    one[0, 3] = True
    where = steered_columns(policy, batch, one)[..., 0]
    plain, _ = run(policy, batch, noise, "lm", 1, None)
    at = float(plain[where] @ unit(v))
    levels = (at - 1.0, at + 1.0)  # alpha 0.5 targets the token's own projection
    _, clamped = run(policy, batch, noise, "lm", 1, clamp(1, v, 0.5, levels, token_mask=one))
    _, added = run(policy, batch, noise, "lm", 1, Steering(1, v, 0.5, token_mask=one))
    torch.testing.assert_close(clamped[where], plain[where], rtol=0, atol=1e-5)
    torch.testing.assert_close(added[where], plain[where] + 0.5 * v, rtol=1e-6, atol=1e-5)

    _, clamped = run(policy, batch, noise, "lm", 1, clamp(1, v, 2.0, levels, token_mask=one))
    _, added = run(policy, batch, noise, "lm", 1, Steering(1, v, 2.0, token_mask=one))
    torch.testing.assert_close(clamped[where], plain[where] + 3.0 * unit(v), rtol=1e-6, atol=1e-5)  # t = at + 3
    torch.testing.assert_close(added[where], plain[where] + 2.0 * v, rtol=1e-6, atol=1e-5)
    assert (clamped[where] - added[where]).norm() > 1.0


# ----------------------------------------------------------------------------- sweeps, compiled, devices


def sweep_entries():
    lm_v, lm_w, ex_v = vector(ARCH.width, 1), vector(ARCH.width, 2), vector(EXPERT.width, 3)
    return [
        None,
        Steering(2, lm_v, 1.5),
        clamp(1, lm_w, 0.3),
        [clamp(0, lm_v, 1.2, (0.5, -1.0)), Steering(2, lm_w, -2.0)],  # the shallowest steered layer is clamped
        [Steering(0, lm_w, 3.0), clamp(0, lm_v, 0.0)],  # an addition and a clamp at one layer
        [clamp(1, ex_v, 0.7, stream="expert"), Steering(2, ex_v, 1.0, stream="expert")],
    ]


def test_sweep_equals_separate_calls(policy, batch, noise):
    entries = sweep_entries()
    swept = policy.sample_actions_sweep(*batch.args(), entries, noise=noise, num_steps=STEPS)
    plain = policy.sample_actions(*batch.args(), noise=noise, num_steps=STEPS)
    for index, entry in enumerate(entries):
        alone = policy.sample_actions(*batch.args(), noise=noise, num_steps=STEPS, steering=entry)
        torch.testing.assert_close(swept[index], alone, rtol=1e-5, atol=1e-5)
        assert index == 0 or (alone - plain).abs().max() > 1e-2  # every steering really acts


def test_compiled_sweep_matches_eager(checkpoint, policy, batch, noise):
    """The compiled step takes the expert clamps as dense tensors: one graph for clamped and unclamped rows."""
    compiled = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu", compiled=True)
    one, entries = batch.row(0), sweep_entries()[-3:]
    expected = policy.sample_actions_sweep(*one.args(), entries, noise=noise[:1], num_steps=STEPS)
    actions = compiled.sample_actions_sweep(*one.args(), entries, noise=noise[:1], num_steps=STEPS)
    torch.testing.assert_close(actions, expected, rtol=1e-4, atol=1e-4)
    assert len(compiled.denoiser.variants) == 1


def test_a_moved_clamp_keeps_its_mode_and_levels(policy, batch, noise):
    item = clamp(1, vector(ARCH.width, 1), 0.4, token_mask=batch.token_mask)
    moved = item.to(torch.device("cpu"))
    assert (moved.mode, moved.levels, moved.alpha, moved.target) == ("clamp", (-2.0, 3.0), 0.4, item.target)
    assert torch.equal(moved.vector, item.vector) and torch.equal(moved.token_mask, item.token_mask)
    assert torch.equal(policy.sample_actions(*batch.args(), noise=noise, num_steps=STEPS, steering=moved),
                       policy.sample_actions(*batch.args(), noise=noise, num_steps=STEPS, steering=item))


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(("kwargs", "message"), [
    (dict(mode="clamp"), r"clamp needs levels \(m₋, m₊\), two finite numbers; found None"),
    (dict(mode="clamp", levels=(1.5, 1.5)),
     r"clamp needs two different levels \(m₋, m₊\); found equal levels 1.5: the concepts do not differ along this "
     r"direction"),
    (dict(mode="clamp", levels=(0.0, float("nan"))), r"clamp needs levels .*; found \(0.0, nan\)"),
    (dict(mode="clamp", levels=(0.0, 1.0), vector=torch.zeros(ARCH.width)),
     r"clamp needs a vector with a direction; found norm 0.0"),
    (dict(mode="clamp", levels=(0.0, 1.0), vector=torch.full((ARCH.width,), float("inf"))),
     r"clamp needs a vector with a direction; found norm inf"),
    (dict(levels=(0.0, 1.0)), r"levels apply to mode 'clamp' only; mode 'add' takes none, found \(0.0, 1.0\)"),
    (dict(mode="project"), r"mode 'project' unknown; expected one of \('add', 'clamp'\)"),
])
def test_bad_clamp_is_one_clear_error(kwargs, message):
    kwargs = {"vector": vector(ARCH.width, 1)} | kwargs
    with pytest.raises(ValueError, match=f"^Steering: {message}$"):
        Steering(1, **kwargs)


def test_two_clamps_of_one_layer_in_one_entry_are_refused(policy, batch, noise):
    v = vector(ARCH.width, 1)
    twice = [Steering(1, v), clamp(1, v, 0.0), clamp(0, v, 0.0), clamp(1, v, 1.0)]
    message = r"^steering\[1\] and steering\[3\] \(lm layer 1\): two clamps of one layer in one entry; give at most one$"
    with pytest.raises(ValueError, match=message):
        policy.sample_actions(*batch.args(), noise=noise, num_steps=STEPS, steering=twice)
    # in separate entries, or on separate streams, they are fine
    policy.sample_actions_sweep(*batch.args(), [clamp(1, v, 0.0), clamp(1, v, 1.0)], noise=noise, num_steps=1)
    policy.sample_actions(*batch.args(), noise=noise, num_steps=1,
                          steering=[clamp(1, v, 0.0), clamp(1, vector(EXPERT.width, 2), 1.0, stream="expert")])
