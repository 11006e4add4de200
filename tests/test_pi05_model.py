"""pi0.5 prefix forward: equivalence with a naive float64 reference, early exit, exact speed savings."""

from __future__ import annotations

import pytest
import torch
from helpers_pi05 import make_batch
from reference_pi05 import reference_residuals

from steering_core.capture.selected_rows import selected_residuals
from steering_core.pi05 import Pi05Prefix, PromptTokenizer
from steering_core.pi05.checkpoint import MODEL_FILE
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

ARCH = tiny_arch()
ALL_LAYERS = list(range(ARCH.depth))
TOL = {"rtol": 1e-5, "atol": 1e-5}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_pi05_checkpoint(tmp_path_factory.mktemp("pi05") / "ckpt", ARCH, seed=1)


@pytest.fixture(scope="module")
def tokenizer(tmp_path_factory):
    return PromptTokenizer(write_tokenizer(tmp_path_factory.mktemp("tok") / "tokenizer.model"), max_len=24)


@pytest.fixture(scope="module")
def model(checkpoint):
    return Pi05Prefix.from_checkpoint(checkpoint, ARCH, device="cpu")


@pytest.fixture(scope="module")
def batch(tokenizer):
    return make_batch(ARCH, tokenizer)


def assert_valid_close(actual, expected, valid, **tol):
    """Compare two (B, S, width) residuals on valid positions only."""
    torch.testing.assert_close(actual[valid].double(), expected[valid].double(), **(tol or TOL))


def test_residuals_match_naive_reference_at_every_layer(model, checkpoint, batch):
    out = model.residuals(*batch.args(), ALL_LAYERS)
    expected = reference_residuals(checkpoint / MODEL_FILE, ARCH, *batch.args(), ALL_LAYERS)
    valid = batch.valid(ARCH)
    assert sorted(out) == ALL_LAYERS
    for layer in ALL_LAYERS:
        assert out[layer].shape == (3, 3 * ARCH.tokens_per_image + 24, ARCH.width)
        assert out[layer].dtype == torch.float32
        assert torch.isnan(expected[layer][~valid]).all()  # the reference only fills valid positions
        assert_valid_close(out[layer], expected[layer], valid)
    # layers really differ: a test comparing one layer to itself could not fail
    assert (out[0][valid] - out[3][valid]).abs().max() > 1.0


def test_openpi_full_path_matches_reference(model, checkpoint, batch):
    # no savings: every camera, every pad column, eager attention with openpi's explicit additive mask
    out = model.residuals(*batch.args(), [1], skip_masked_images=False, trim_padding=False, attention="eager")
    expected = reference_residuals(checkpoint / MODEL_FILE, ARCH, *batch.args(), [1])
    assert_valid_close(out[1], expected[1], batch.valid(ARCH))


def test_bfloat16_stored_checkpoint_matches_reference(tmp_path, batch):
    folder = write_pi05_checkpoint(tmp_path / "bf16", ARCH, seed=2, dtype=torch.bfloat16)
    model = Pi05Prefix.from_checkpoint(folder / MODEL_FILE, ARCH, device="cpu")
    assert model.compute_dtype == torch.float32
    out = model.residuals(*batch.args(), [2])
    expected = reference_residuals(folder / MODEL_FILE, ARCH, *batch.args(), [2])
    assert_valid_close(out[2], expected[2], batch.valid(ARCH))


@pytest.mark.parametrize(
    "saving",
    [{"skip_masked_images": False}, {"trim_padding": False}, {"attention": "eager"}],
    ids=["skip-masked-images", "trim-padding", "fused-attention"],
)
def test_each_speed_saving_leaves_valid_residuals_unchanged(model, batch, saving):
    fast = model.residuals(*batch.args(), ALL_LAYERS)
    slow = model.residuals(*batch.args(), ALL_LAYERS, **saving)
    valid = batch.valid(ARCH)
    for layer in ALL_LAYERS:
        assert_valid_close(fast[layer], slow[layer], valid, rtol=1e-6, atol=1e-5)


def test_skipped_camera_and_trimmed_padding_are_not_computed(model, batch):
    out = model.residuals(*batch.args(), [0])[0]
    per_image = ARCH.tokens_per_image
    longest = int(batch.token_mask.sum(dim=1).max())
    right_wrist = out[:, 2 * per_image : 3 * per_image]
    trimmed = out[:, 3 * per_image + longest :]
    assert right_wrist.abs().sum() == 0 and trimmed.abs().sum() == 0
    full = model.residuals(*batch.args(), [0], skip_masked_images=False, trim_padding=False)[0]
    assert full[:, 2 * per_image : 3 * per_image].abs().min() > 0


def test_early_exit_equals_full_depth(checkpoint, model, batch):
    shallow = Pi05Prefix.from_checkpoint(checkpoint, ARCH, max_layer=1, device="cpu")
    assert len(shallow.layers) == 2 and shallow.max_layer == 1
    valid = batch.valid(ARCH)
    assert_valid_close(shallow.residuals(*batch.args(), [1])[1], model.residuals(*batch.args(), [1])[1], valid)


def test_several_layers_in_one_pass_equal_single_layer_runs(model, batch):
    together = model.residuals(*batch.args(), [3, 0, 2])
    assert sorted(together) == [0, 2, 3]
    for layer in (0, 2, 3):
        torch.testing.assert_close(together[layer], model.residuals(*batch.args(), [layer])[layer])


def test_valid_residuals_ignore_padding_length_and_batch_neighbours(model, checkpoint, tokenizer):
    short = make_batch(ARCH, tokenizer)
    long_tokenizer = PromptTokenizer(tokenizer.path, max_len=40)
    long = make_batch(ARCH, long_tokenizer)
    out_short = model.residuals(*short.args(), [3], trim_padding=False)[3]
    out_long = model.residuals(*long.args(), [3], trim_padding=False)[3]
    prefix = 3 * ARCH.tokens_per_image + 24
    valid = short.valid(ARCH)
    assert_valid_close(out_long[:, :prefix], out_short, valid)
    for index in range(3):
        alone = model.residuals(*short.row(index).args(), [3])[3]
        assert_valid_close(alone, out_short[index : index + 1], valid[index : index + 1])


def test_batch_without_any_valid_token_returns_zeros(model, batch):
    masks = [torch.zeros_like(mask) for mask in batch.image_masks]
    out = model.residuals(batch.images, masks, batch.tokens, torch.zeros_like(batch.token_mask), [0])[0]
    assert out.shape == (3, 3 * ARCH.tokens_per_image + 24, ARCH.width) and out.abs().sum() == 0


def test_bfloat16_policy_keeps_openpi_float32_parameters(checkpoint, model, batch):
    half = Pi05Prefix.from_checkpoint(checkpoint, ARCH, device="cpu", dtype="bfloat16")
    dtypes = {name: p.dtype for name, p in half.named_parameters()}
    float32 = {name for name, dtype in dtypes.items() if dtype == torch.float32}
    assert float32 == {
        "vision_model.embeddings.patch_embedding.weight",
        "vision_model.embeddings.patch_embedding.bias",
        "vision_model.embeddings.position_embedding.weight",
        *(f"layers.{i}.input_layernorm.weight" for i in range(ARCH.depth)),
        *(f"layers.{i}.post_attention_layernorm.weight" for i in range(ARCH.depth)),
    }
    assert set(dtypes.values()) == {torch.float32, torch.bfloat16}
    out = half.residuals(*batch.args(), [3])[3]
    assert out.dtype == torch.float32
    reference = model.residuals(*batch.args(), [3])[3]
    valid = batch.valid(ARCH)
    error = (out[valid] - reference[valid]).norm() / reference[valid].norm()
    assert 0 < error < 0.05  # bfloat16 rounding, but the same computation


def test_loaded_model_has_no_meta_tensors(model):
    tensors = [*model.parameters(), *model.buffers()]
    assert tensors and all(t.device.type == "cpu" for t in tensors)
    assert not any(p.requires_grad for p in model.parameters())


def test_bad_inputs_raise_one_error_naming_each(model, batch):
    images = [batch.images[0][:, :, :14], *batch.images[1:]]
    with pytest.raises(ValueError) as err:
        model.residuals(images, batch.image_masks[:2], batch.tokens.float(), batch.token_mask, [0])
    message = str(err.value)
    assert "tokens: found (3, 24) torch.float32, expected (B, T) int64" in message
    assert "images: 3 cameras but 2 image_masks" in message
    assert "images[0]: found (3, 3, 14, 28) torch.float32, expected (3, 3, 28, 28)" in message
    tokens = batch.tokens.clone()
    tokens[1, 2] = ARCH.vocab_size
    with pytest.raises(ValueError, match=r"tokens: ids span 0\.\.512, expected 0\.\.511"):
        model.residuals(*batch.args()[:2], tokens, batch.token_mask, [0])


def test_layer_out_of_range_is_one_clear_error(checkpoint):
    expected = r"max_layer 4 is out of range: the language model has 4 decoder layers \(0\.\.3\)"
    with pytest.raises(ValueError, match=expected):
        Pi05Prefix.from_checkpoint(checkpoint, ARCH, max_layer=4, device="cpu")
    shallow = Pi05Prefix.from_checkpoint(checkpoint, ARCH, max_layer=1, device="cpu")
    with pytest.raises(ValueError, match=r"layers \[0, 2\] invalid: .*loaded with max_layer=1.*bad: \[2\]"):
        shallow.residuals([], [], torch.zeros(1, 2, dtype=torch.long), torch.ones(1, 2, dtype=torch.bool), [0, 2])


def selected_rows(batch, valid, per_frame=(5, 0, 3), seed=0):
    """Pick (frame, position) rows among valid tokens, unsorted, uneven per frame (one frame none, one image row)."""
    generator = torch.Generator().manual_seed(seed)
    frames, positions = [], []
    for frame, count in enumerate(per_frame):
        candidates = valid[frame].nonzero().flatten()
        chosen = candidates[torch.randperm(len(candidates), generator=generator)[:count]]
        frames += [frame] * len(chosen)
        positions += chosen.tolist()
    shuffle = torch.randperm(len(frames), generator=generator)
    return torch.tensor(frames)[shuffle], torch.tensor(positions)[shuffle]


def assert_rounding_close(actual, expected):
    """Equal up to float32 rounding: max |difference| at most 1e-6 of the rows' largest magnitude."""
    assert (actual - expected).abs().max() <= 1e-6 * expected.abs().max()


@pytest.mark.parametrize("attention", ["sdpa", "eager"])
def test_selected_rows_equal_the_full_residuals(model, checkpoint, batch, attention):
    valid = batch.valid(ARCH)
    frames, positions = selected_rows(batch, valid)
    full = model.residuals(*batch.args(), ALL_LAYERS, attention=attention)
    rows = selected_residuals(model, *batch.args(), [3, 0, 2], frames, positions, attention=attention)
    assert sorted(rows) == [0, 2, 3]
    for layer in (0, 2):  # before the deepest layer: the same computation, bit for bit
        assert torch.equal(rows[layer], full[layer][frames, positions])
    deepest = rows[3]  # queries, attention output and MLP of the selected rows only
    assert deepest.shape == (len(frames), ARCH.width) and deepest.dtype == torch.float32
    assert_rounding_close(deepest, full[3][frames, positions])
    alone = selected_residuals(model, *batch.args(), [1], frames, positions, attention=attention)[1]
    assert_rounding_close(alone, full[1][frames, positions])
    if attention == "sdpa":
        expected = reference_residuals(checkpoint / MODEL_FILE, ARCH, *batch.args(), [3])[3]
        torch.testing.assert_close(deepest.double(), expected[frames, positions], **TOL)


def test_selected_rows_must_be_valid_tokens(model, batch):
    valid = batch.valid(ARCH)
    masked = int((~valid[0]).nonzero()[0])  # the right wrist camera is masked in every frame
    frames, positions = torch.tensor([0, 1]), torch.tensor([int(valid[0].nonzero()[0]), masked])
    with pytest.raises(ValueError, match=rf"row 1 \(frame 1, position {masked}\) is not a valid token"):
        selected_residuals(model, *batch.args(), [2], frames, positions)
