"""The compiled denoising step: the eager policy's actions within rounding, steered or not, on a bounded set of shapes.

Compiling is slow on a CPU (about a minute for the tiny model): the module compiles one policy once, at the
batch size and prompt slots every comparison uses, so a single variant serves them all.
"""

from __future__ import annotations

import pytest
import torch
from helpers_pi05 import make_batch

from steering_core.pi05 import Pi05Policy, PromptTokenizer, Steering
from steering_core.pi05.denoise import dense_additions, pad_prefix, pad_rows, row_bucket
from steering_core.pi05.model import MASKED_LOGIT
from steering_core.pi05.steering import Splice
from steering_core.synthetic.pi05 import tiny_arch, tiny_expert_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

ARCH = tiny_arch()
EXPERT = tiny_expert_arch(ARCH)
MAX_LEN = 24
FULL_PREFIX = 3 * ARCH.tokens_per_image + MAX_LEN
ROWS = 3  # the batch's rows; a sweep of three entries over one row has as many
BUCKET = 4  # the compiled rows they run at: padded to the next row bucket
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: the compiled step's CUDA graphs")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_pi05_checkpoint(tmp_path_factory.mktemp("pi05") / "ckpt", ARCH, seed=3)


@pytest.fixture(scope="module")
def tokenizer(tmp_path_factory):
    return PromptTokenizer(write_tokenizer(tmp_path_factory.mktemp("tok") / "tokenizer.model"), max_len=MAX_LEN)


@pytest.fixture(scope="module")
def eager(checkpoint):
    return Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu")


@pytest.fixture(scope="module")
def compiled(checkpoint, tokenizer):
    """One policy compiled by its warm-up at batch ROWS, as a server would be; returns it and the graphs dynamo
    compiled meanwhile."""
    policy = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu", compiled=True)
    policy.tokenizer = tokenizer  # short prompt slots keep the one compiled variant small
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    policy.warm_up(batch=ROWS)
    return policy, torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs


@pytest.fixture(scope="module")
def batch(tokenizer):
    return make_batch(ARCH, tokenizer)


@pytest.fixture(scope="module")
def noise():
    return torch.randn(ROWS, 10, 32, generator=torch.Generator().manual_seed(5))


def vector(width, seed):
    return torch.randn(width, generator=torch.Generator().manual_seed(seed))


def test_defaults_compile_on_cuda_only(checkpoint):
    assert Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cpu").compiled is False


def test_padded_prefix_leaves_the_velocity_unchanged(eager):
    """The padding columns are zero keys under a masked logit: the expert's output is the unpadded one."""
    generator = torch.Generator().manual_seed(0)
    rows, cached, horizon = 2, 7, 10
    keys_values = [tuple(torch.randn(rows, 1, cached, EXPERT.head_dim, generator=generator) for _ in range(2))
                   for _ in range(EXPERT.depth)]
    allowed = torch.ones(rows, cached + horizon, dtype=torch.bool)
    allowed[0, 2] = False
    mask = torch.where(allowed, 0.0, MASKED_LOGIT)[:, None, None, :]
    positions = torch.arange(cached, cached + horizon).repeat(rows, 1)
    rotary = eager.prefix.rotary_emb(torch.empty(0), positions)
    actions = torch.randn(rows, horizon, EXPERT.action_dim, generator=generator)
    cond = eager.expert.condition(torch.full((rows,), 0.7))
    padded_kv, padded_mask = pad_prefix(keys_values, mask, cached + 5)
    assert padded_kv[0][0].shape == (rows, 1, cached + 5, EXPERT.head_dim)
    assert padded_mask.shape == (rows, 1, 1, cached + 5 + horizon)
    assert torch.equal(padded_mask[..., cached:cached + 5], torch.full((rows, 1, 1, 5), MASKED_LOGIT))
    assert torch.equal(padded_mask[..., cached + 5:], mask[..., cached:])
    torch.testing.assert_close(eager.expert.velocity(actions, cond, rotary, padded_kv, padded_mask),
                               eager.expert.velocity(actions, cond, rotary, keys_values, mask), rtol=1e-5, atol=1e-6)


def test_dense_additions_place_each_layer():
    addition = torch.arange(8.0)[None, None]
    dense = dense_additions({1: addition}, depth=3, rows=2, width=8, dtype=torch.float32, device=torch.device("cpu"))
    assert dense.shape == (3, 2, 1, 8)
    assert torch.equal(dense[1], addition.expand(2, 1, 8)) and not dense[[0, 2]].any()


def test_rows_run_at_the_smallest_bucket_holding_them():
    assert [row_bucket(rows) for rows in (1, 2, 3, 5, 9, 16, 17)] == [1, 2, 4, 8, 16, 16, None]
    assert row_bucket(9, max_rows=8) is None
    padded = pad_rows(torch.ones(3, 2), 4)
    assert padded.shape == (4, 2) and torch.equal(padded[:3], torch.ones(3, 2)) and not padded[3].any()


def test_warm_up_compiles_one_variant(compiled):
    policy, graphs = compiled
    assert graphs >= 1  # dynamo really compiled the step: no silent fallback to eager
    assert policy.denoiser.variants == {(BUCKET, FULL_PREFIX)}


@pytest.mark.parametrize("case", ["plain", "lm and expert", "splice"])
def test_compiled_matches_eager(compiled, eager, batch, noise, case):
    policy, _ = compiled
    steering, splice = None, None
    if case == "lm and expert":
        steering = [Steering(1, vector(ARCH.width, 1), 3.0, token_mask=batch.token_mask),
                    Steering(2, vector(EXPERT.width, 2), 2.0, stream="expert")]
    if case == "splice":
        splice = Splice(1, lambda rows: torch.zeros_like(rows))
    expected = eager.sample_actions(*batch.args(), noise=noise, steering=steering, splice=splice)
    actions = policy.sample_actions(*batch.args(), noise=noise, steering=steering, splice=splice)
    torch.testing.assert_close(actions, expected, rtol=1e-4, atol=1e-4)
    plain = eager.sample_actions(*batch.args(), noise=noise)
    assert case == "plain" or (expected - plain).abs().max() > 1e-2  # the steering or splice really acts
    assert policy.denoiser.variants == {(BUCKET, FULL_PREFIX)}  # steering needs no other compiled shape


def test_compiled_sweep_matches_eager(compiled, eager, batch, noise):
    """A sweep of ROWS entries over one row fills the same compiled shape as a batch of ROWS."""
    policy, _ = compiled
    one = batch.row(0)
    entries = [None, Steering(1, vector(ARCH.width, 1), 4.0), Steering(0, vector(EXPERT.width, 2), -3.0, stream="expert")]
    expected = eager.sample_actions_sweep(*one.args(), entries, noise=noise[:1])
    torch.testing.assert_close(policy.sample_actions_sweep(*one.args(), entries, noise=noise[:1]), expected,
                               rtol=1e-4, atol=1e-4)
    assert policy.denoiser.variants == {(BUCKET, FULL_PREFIX)}


def test_shapes_past_the_bound_run_eagerly(eager, batch, noise, caplog):
    policy = Pi05Policy(eager.prefix, eager.expert, eager.action_horizon, None, eager.normalization, compiled=True)
    policy.denoiser.max_variants = 0
    actions = policy.sample_actions(*batch.args(), noise=noise, num_steps=2)
    assert torch.equal(actions, eager.sample_actions(*batch.args(), noise=noise, num_steps=2))
    assert policy.denoiser.variants == set() and policy.denoiser.refused == {(BUCKET, FULL_PREFIX)}
    assert "compiled already, the most per policy" in caplog.text


def test_batches_past_the_row_bound_run_eagerly(eager, batch, noise):
    policy = Pi05Policy(eager.prefix, eager.expert, eager.action_horizon, None, eager.normalization, compiled=True)
    policy.denoiser.max_rows = ROWS - 1
    actions = policy.sample_actions(*batch.args(), noise=noise, num_steps=2)
    assert torch.equal(actions, eager.sample_actions(*batch.args(), noise=noise, num_steps=2))
    assert policy.denoiser.variants == set() == policy.denoiser.refused


def test_hooks_on_the_expert_see_every_step(compiled, eager, batch, noise):
    """Capture records expert layer outputs with forward hooks added after compilation: they must still fire."""
    policy, _ = compiled
    seen = {}
    for name, model in (("compiled", policy), ("eager", eager)):
        outputs = []
        handle = model.expert.layers[1].register_forward_hook(lambda _m, _a, output: outputs.append(output.clone()))
        try:
            model.sample_actions(*batch.args(), noise=noise, num_steps=3)
        finally:
            handle.remove()
        seen[name] = outputs
    assert len(seen["compiled"]) == 3
    torch.testing.assert_close(torch.stack(seen["compiled"]), torch.stack(seen["eager"]), rtol=1e-5, atol=1e-5)


@CUDA
def test_cuda_compiled_matches_eager_within_bfloat16_rounding(checkpoint, tokenizer):
    """On CUDA (bfloat16 by default) the compiled policy is as close to the eager one as bfloat16's rounding moves
    the eager policy from float32."""
    exact = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cuda", dtype="float32", compiled=False)
    eager_half = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cuda", compiled=False)
    policy = Pi05Policy.from_checkpoint(checkpoint, ARCH, device="cuda")
    assert policy.compiled  # the default on CUDA
    batch = make_batch(ARCH, tokenizer)
    noise = torch.randn(ROWS, 10, 32, generator=torch.Generator().manual_seed(5))
    steered = [Steering(1, vector(ARCH.width, 1), 3.0), Steering(2, vector(EXPERT.width, 2), 2.0, stream="expert")]
    for steering in (None, steered):
        rounding = (eager_half.sample_actions(*batch.args(), noise=noise, steering=steering)
                    - exact.sample_actions(*batch.args(), noise=noise, steering=steering)).abs().max()
        for _ in range(2):  # the first call records the CUDA graphs, the second replays them
            actions = policy.sample_actions(*batch.args(), noise=noise, steering=steering)
            assert (actions - exact.sample_actions(*batch.args(), noise=noise, steering=steering)).abs().max() \
                <= 2 * rounding
    entries = [None, Steering(0, vector(EXPERT.width, 2), -3.0, stream="expert")]
    swept = policy.sample_actions_sweep(*batch.args(), entries, noise=noise)
    expected = exact.sample_actions_sweep(*batch.args(), entries, noise=noise)
    rounding = (eager_half.sample_actions_sweep(*batch.args(), entries, noise=noise) - expected).abs().max()
    assert (swept - expected).abs().max() <= 2 * rounding
