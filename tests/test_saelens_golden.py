"""Our SAE reader against SAELens itself: folders SAELens saved, and its encode/decode of fixed inputs.

The golden files were written once by `tests/fixtures/make_saelens_golden.py` in an isolated
environment with SAELens (its VERSION file says which); the project never imports SAELens.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from steering_core.sae import load_sae

GOLDEN = Path(__file__).resolve().parent / "fixtures" / "saelens"
ARCHITECTURES = ("standard", "jumprelu", "topk")


@pytest.mark.parametrize("architecture", ARCHITECTURES)
def test_encode_and_decode_equal_saelens(architecture):
    folder = GOLDEN / architecture
    golden = load_file(folder / "golden.safetensors")
    sae = load_sae(folder)
    assert (sae.cfg.d_in, sae.cfg.d_sae) == (golden["x"].shape[1], golden["latents"].shape[1])
    assert sae.cfg.hook_layer == 1  # blocks.1.hook_resid_post, from SAELens's metadata
    latents = sae.encode(golden["x"])
    assert int((golden["latents"] > 0).sum()) > 0  # the fixture exercises firing latents
    torch.testing.assert_close(latents, golden["latents"], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(sae.decode(latents), golden["reconstruction"], rtol=1e-5, atol=1e-5)


def test_golden_files_come_from_saelens():
    assert (GOLDEN / "VERSION").read_text().startswith("sae-lens 6.54.12")
    assert sorted(p.name for p in GOLDEN.iterdir() if p.is_dir()) == sorted(ARCHITECTURES)
