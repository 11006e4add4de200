"""lerobot's own π0.5 (the installed lerobot, not a recording) as the reference in the suite: the fixture folder
loaded by lerobot's `PI05Policy.from_pretrained` and by ours gives the same actions on new inputs, plain and steered.

The fixture's tiny dimensions need lerobot's two hard-coded configs patched (configuration only, as the golden
generator does: tests/fixtures/lerobot_golden/README.md); the patches are undone after each test.
"""

from __future__ import annotations

import importlib.util

import pytest
import torch
from test_lerobot_golden import ARCH, GOLDEN, MODEL

from steering_core.pi05 import Pi05Policy, Steering

modeling = pytest.importorskip("lerobot.policies.pi05.modeling_pi05")  # lerobot >= 0.5 (Python 3.12)


def generator_constants():
    """Return the golden generator module (its tiny sizes), loaded from its file without running it."""
    spec = importlib.util.spec_from_file_location("make_lerobot_golden", GOLDEN / "make_lerobot_golden.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def lerobot_policy():
    """lerobot's PI05Policy of the fixture folder, its tiny configs patched while it is built."""
    sizes = generator_constants()
    patch = pytest.MonkeyPatch()
    real_paligemma, real_expert = modeling.PaliGemmaForConditionalGenerationWithPiGemma, modeling.PiGemmaForCausalLM

    def tiny_paligemma(config):
        for key, value in sizes.TINY_VISION.items():
            setattr(config.vision_config, key, value)
        config.vision_config.projection_dim = config.text_config.hidden_size
        config.text_config.vocab_size = config._vocab_size = config.image_token_index = sizes.VOCAB  # noqa: SLF001
        return real_paligemma(config=config)

    def tiny_expert(config):
        config.vocab_size = sizes.VOCAB
        return real_expert(config=config)

    tiny = {"gemma_2b": sizes.TINY_LM, "gemma_300m": sizes.TINY_EXPERT}
    patch.setattr(modeling, "get_gemma_config", lambda variant: modeling.GemmaConfig(**tiny[variant]))
    patch.setattr(modeling, "PaliGemmaForConditionalGenerationWithPiGemma", tiny_paligemma)
    patch.setattr(modeling, "PiGemmaForCausalLM", tiny_expert)
    patch.setenv("HF_HUB_OFFLINE", "1")
    try:
        policy = modeling.PI05Policy.from_pretrained(str(MODEL)).eval()
    finally:
        patch.undo()
    return policy


@pytest.fixture(scope="module")
def ours():
    return Pi05Policy.from_checkpoint(MODEL, ARCH, device="cpu")


def inputs(seed: int):
    """New inputs (not the goldens'): two cameras, an empty third, prompts of 40 and 70 tokens, noise."""
    generator = torch.Generator().manual_seed(seed)
    images = [torch.rand(2, 3, 28, 28, generator=generator) * 2 - 1 for _ in range(2)] + [torch.full((2, 3, 28, 28), -1.0)]
    masks = [torch.ones(2, dtype=torch.bool)] * 2 + [torch.zeros(2, dtype=torch.bool)]
    tokens = torch.randint(3, 384, (2, 96), generator=generator)
    token_mask = torch.arange(96)[None] < torch.tensor([[40], [70]])
    tokens = torch.where(token_mask, tokens, 0)
    tokens[:, 0] = 2
    return images, masks, tokens, token_mask, torch.randn(2, 10, 32, generator=generator)


def test_the_same_actions_as_lerobots_own_policy(lerobot_policy, ours):
    images, masks, tokens, token_mask, noise = inputs(11)
    with torch.no_grad():
        theirs = lerobot_policy.model.sample_actions(images, masks, tokens, token_mask, noise=noise)
    mine = ours.sample_actions(images, masks, tokens, token_mask, noise=noise)
    torch.testing.assert_close(mine, theirs, rtol=0, atol=1e-4)


def test_the_same_lm_steering_as_a_hook_on_lerobots_layer(lerobot_policy, ours):
    """Steering language-model layer 1 at four prefix positions: our Steering against a forward hook adding the
    same vector to lerobot's layer output in its prefix forward."""
    images, masks, tokens, token_mask, noise = inputs(12)
    vector, alpha, positions = torch.randn(ARCH.width, generator=torch.Generator().manual_seed(3)), 3.0, [0, 5, 13, 20]
    prefix_len = 3 * ARCH.tokens_per_image + tokens.shape[1]

    def add(module, args, output):
        hidden = output[0] if isinstance(output, tuple) else output
        if hidden.shape[1] != prefix_len:  # the denoising steps reuse the layer for nothing here; only the prefix
            return output
        hidden = hidden.clone()
        hidden[:, positions] += alpha * vector
        return (hidden, *output[1:]) if isinstance(output, tuple) else hidden

    layer = lerobot_policy.model.paligemma_with_expert.paligemma.model.language_model.layers[1]
    handle = layer.register_forward_hook(add)
    try:
        with torch.no_grad():
            theirs = lerobot_policy.model.sample_actions(images, masks, tokens, token_mask, noise=noise)
    finally:
        handle.remove()
    prefix_mask = torch.zeros(2, prefix_len, dtype=torch.bool)
    prefix_mask[:, positions] = True
    mine = ours.sample_actions(images, masks, tokens, token_mask, noise=noise,
                               steering=Steering(1, vector, alpha, prefix_mask=prefix_mask))
    torch.testing.assert_close(mine, theirs, rtol=0, atol=1e-4)
    assert (mine - ours.sample_actions(images, masks, tokens, token_mask, noise=noise)).abs().max() > 1e-2
