"""openpi checkpoint layout, lazy prefix-only reading, and one clear error per bad checkpoint."""

from __future__ import annotations

import json
import math

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

import steering_core.pi05.checkpoint as checkpoint_module
import steering_core.synthetic.pi05 as synthetic_pi05
from steering_core.pi05 import Pi05Arch, Pi05Prefix
from steering_core.pi05.checkpoint import (
    EMBEDDING_KEY,
    EXPERT_PREFIX,
    LM_PREFIX,
    MODEL_FILE,
    PROJECTOR_PREFIX,
    VISION_PREFIX,
    prefix_tensor_shapes,
)
from steering_core.storage.fileio import sha256_file
from steering_core.synthetic.pi05 import checkpoint_tensor_shapes, tiny_arch, write_pi05_checkpoint

ARCH = tiny_arch()


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return write_pi05_checkpoint(tmp_path_factory.mktemp("pi05") / "ckpt", ARCH, seed=3)


def rewrite(source, target, drop=(), replace=None):
    """Write a copy of checkpoint file `source` to `target` without `drop` and with `replace` tensors."""
    tensors = {name: t for name, t in load_file(source).items() if name not in drop}
    tensors.update(replace or {})
    target.parent.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(target))
    return target


def residuals(model, layer):
    generator = torch.Generator().manual_seed(0)
    images = [torch.rand(2, 3, 28, 28, generator=generator) * 2 - 1 for _ in range(2)]
    masks = [torch.ones(2, dtype=torch.bool)] * 2
    tokens = torch.randint(0, ARCH.vocab_size, (2, 5), generator=generator)
    return model.residuals(images, masks, tokens, torch.ones(2, 5, dtype=torch.bool), [layer])[layer]


def test_real_size_layout_has_openpi_counts():
    # totals from rebuilding openpi's module tree (spec 1.2): 812 tensors, 3,616,757,520 values
    shapes = checkpoint_tensor_shapes(Pi05Arch())
    numel = {name: math.prod(shape) for name, shape in shapes.items()}

    def total(select):
        return sum(n for name, n in numel.items() if select(name))

    assert len(shapes) == 812
    assert sum(numel.values()) == 3_616_757_520
    assert total(lambda name: name.startswith(VISION_PREFIX)) == 412_442_352
    assert total(lambda name: name.startswith(LM_PREFIX)) == 1_981_884_416
    expert_head = EXPERT_PREFIX + "lm_head.weight"
    assert total(lambda name: name.startswith(EXPERT_PREFIX) and name != expert_head) == 427_932_672
    assert shapes[EMBEDDING_KEY] == (257152, 2048)
    assert not any("embed_tokens" in name for name in shapes)  # tied: stored only as lm_head (spec 1.3)


def test_synthetic_folder_matches_openpi_layout(folder):
    with safe_open(str(folder / MODEL_FILE), framework="pt") as handle:
        stored = {name: tuple(handle.get_slice(name).get_shape()) for name in handle.keys()}
    assert stored == checkpoint_tensor_shapes(ARCH)
    assert json.loads((folder / "config.json").read_text()) == {
        "action_dim": 32,
        "action_horizon": 10,
        "paligemma_variant": "dummy",
        "action_expert_variant": "dummy",
        "precision": "float32",
    }
    stats = json.loads((folder / "assets/physical-intelligence/libero/norm_stats.json").read_text())
    assert [len(stats["norm_stats"][key]["q01"]) for key in ("state", "actions")] == [8, 7]


def test_synthetic_checkpoint_is_seeded(tmp_path, folder):
    again = write_pi05_checkpoint(tmp_path / "again", ARCH, seed=3)
    other = write_pi05_checkpoint(tmp_path / "other", ARCH, seed=4)
    assert sha256_file(again / MODEL_FILE) == sha256_file(folder / MODEL_FILE)
    assert sha256_file(other / MODEL_FILE) != sha256_file(folder / MODEL_FILE)


def test_checkpoint_is_written_block_by_block_as_save_file_would(tmp_path, monkeypatch):
    """Streamed in blocks, the file is what save_file writes for the same tensors; small blocks keep the layout."""
    generator = torch.Generator().manual_seed(5)
    shapes = checkpoint_tensor_shapes(ARCH)
    tensors = {name: synthetic_pi05._random_tensor(name, shape, generator).to(torch.bfloat16)
               for name, shape in shapes.items()}
    save_file(tensors, tmp_path / "reference.safetensors", metadata={"format": "pt"})
    folder = write_pi05_checkpoint(tmp_path / "streamed", ARCH, seed=5, dtype=torch.bfloat16)
    assert (folder / MODEL_FILE).read_bytes() == (tmp_path / "reference.safetensors").read_bytes()

    monkeypatch.setattr(synthetic_pi05, "GENERATE_VALUES", 100)  # many blocks per matrix
    blocks = write_pi05_checkpoint(tmp_path / "blocks", ARCH, seed=5, dtype=torch.bfloat16)
    again = load_file(blocks / MODEL_FILE)
    assert {name: tuple(t.shape) for name, t in again.items()} == shapes
    assert all(t.dtype == torch.bfloat16 and torch.isfinite(t).all() for t in again.values())
    embedding = again[EMBEDDING_KEY].float()
    assert abs(float(embedding.std()) * ARCH.width**0.5 - 1) < 0.05  # the same scale rule, block by block


def test_reads_only_the_prefix_up_to_max_layer(folder, monkeypatch):
    read = []
    original = checkpoint_module.read_tensor

    def spy(handle, location, *args):
        read.append(location.name)
        return original(handle, location, *args)

    monkeypatch.setattr(checkpoint_module, "read_tensor", spy)
    model = Pi05Prefix.from_checkpoint(folder, ARCH, max_layer=1, device="cpu")
    assert len(read) == len(set(read)) == len(prefix_tensor_shapes(ARCH, 1))
    assert set(read) == set(prefix_tensor_shapes(ARCH, 1))
    assert not [name for name in read if name.startswith((EXPERT_PREFIX, "action_", "time_mlp"))]
    assert not [name for name in read if name.startswith((f"{LM_PREFIX}layers.2.", f"{LM_PREFIX}norm"))]
    assert model.checkpoint_config["paligemma_variant"] == "dummy"


def test_loads_without_expert_heads_final_norm_or_later_layers(folder, tmp_path):
    needed = prefix_tensor_shapes(ARCH, 1)
    dropped = [name for name in checkpoint_tensor_shapes(ARCH) if name not in needed]
    assert len(dropped) > 30
    stripped = rewrite(folder / MODEL_FILE, tmp_path / "stripped" / MODEL_FILE, drop=dropped)
    full = Pi05Prefix.from_checkpoint(folder, ARCH, device="cpu")
    lean = Pi05Prefix.from_checkpoint(stripped, ARCH, max_layer=1, device="cpu")
    assert lean.checkpoint_config is None  # no config.json beside the bare file
    torch.testing.assert_close(residuals(lean, 1), residuals(full, 1))


def test_missing_and_mismatched_tensors_are_one_sorted_error(folder, tmp_path):
    q_proj = f"{LM_PREFIX}layers.1.self_attn.q_proj.weight"
    broken = rewrite(
        folder / MODEL_FILE,
        tmp_path / "broken" / MODEL_FILE,
        drop=[f"{VISION_PREFIX}post_layernorm.bias", EMBEDDING_KEY],
        replace={
            q_proj: torch.zeros(128, 32),
            f"{PROJECTOR_PREFIX}linear.bias": torch.zeros(64, dtype=torch.int64),
        },
    )
    with pytest.raises(ValueError) as err:
        Pi05Prefix.from_checkpoint(broken, ARCH, device="cpu")
    lines = str(err.value).splitlines()
    n_needed = len(prefix_tensor_shapes(ARCH, 3))
    assert lines[0].startswith(f"{broken}: 4 of {n_needed} prefix tensors (up to decoder layer 3) are missing")
    assert lines[1:5] == [
        f"  {EMBEDDING_KEY}: missing, expected (512, 64)",
        f"  {LM_PREFIX}layers.1.self_attn.q_proj.weight: found (128, 32) F32, expected (128, 64) floating point",
        f"  {PROJECTOR_PREFIX}linear.bias: found (64,) I64, expected (64,) floating point",
        f"  {VISION_PREFIX}post_layernorm.bias: missing, expected (32,)",
    ]
    assert "Pass the Pi05Arch this checkpoint was built with" in lines[5]


def test_wrong_arch_names_every_disagreeing_tensor(folder):
    wrong = ARCH.model_copy(update={"mlp_dim": 96})
    with pytest.raises(ValueError) as err:
        Pi05Prefix.from_checkpoint(folder, wrong, max_layer=0, device="cpu")
    message = str(err.value)
    assert "3 of" in message and "mlp_dim=96" in message
    assert f"{LM_PREFIX}layers.0.mlp.down_proj.weight: found (64, 128) F32, expected (64, 96)" in message


def test_missing_checkpoint_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match=f"{tmp_path / MODEL_FILE}: pi0.5 checkpoint not found"):
        Pi05Prefix.from_checkpoint(tmp_path, ARCH, device="cpu")


def test_bad_dtype_argument_is_rejected(folder):
    with pytest.raises(ValueError, match="dtype 'int8' is not a floating-point dtype"):
        Pi05Prefix.from_checkpoint(folder, ARCH, device="cpu", dtype="int8")
