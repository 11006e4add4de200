"""Our SAE reader against SAELens itself: folders SAELens saved, and its encode/decode of fixed inputs.

The golden files were written by `tests/fixtures/make_saelens_golden.py` in an isolated environment with
SAELens, which records the SAELens version it ran in each golden.safetensors and in golden_meta.json;
the project never imports SAELens.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
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


def test_golden_files_record_the_saelens_that_wrote_them():
    meta = json.loads((GOLDEN / "golden_meta.json").read_text())
    assert meta["generator"] == "tests/fixtures/make_saelens_golden.py"
    assert re.fullmatch(r"\d+\.\d+\.\d+\S*", meta["sae-lens"]), meta  # what sae_lens.__version__ said
    assert sorted(meta["architectures"]) == sorted(ARCHITECTURES)
    assert sorted(p.name for p in GOLDEN.iterdir() if p.is_dir()) == sorted(ARCHITECTURES)
    for architecture in ARCHITECTURES:  # each golden file carries the same record, written in the same run
        with safe_open(str(GOLDEN / architecture / "golden.safetensors"), framework="pt") as handle:
            recorded = json.loads(handle.metadata()["meta"])
        assert recorded == {k: v for k, v in meta.items() if k != "architectures"}, architecture
