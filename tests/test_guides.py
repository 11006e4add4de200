"""The guides' Python examples run as written (docs/python_api.md, docs/serving.md), on a tiny checkpoint,
tokenizer and SAE in their place."""

import re
from pathlib import Path

import torch

from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.sae import write_sae_folder
from steering_core.synthetic.tokenizer import write_tokenizer
from steering_core.vectors.methods.direction_file import MethodDirection, write_method_direction

DOCS = Path(__file__).resolve().parent.parent / "docs"
GUIDES = (DOCS / "python_api.md", DOCS / "serving.md")


def python_blocks() -> list[tuple[Path, str]]:
    return [(guide, block) for guide in GUIDES
            for block in re.findall(r"```python\n(.*?)```", guide.read_text(encoding="utf-8"), flags=re.S)]


def run_example(marker: str, substitutions: dict[str, str], arch, tmp_path, monkeypatch) -> dict:
    """Run the guides' Python block that mentions `marker`, its real sizes replaced; return its variables."""
    ((guide, block),) = [(g, b) for g, b in python_blocks() if marker in b]
    for text, tiny in substitutions.items():
        assert text in block, f"{guide.name}'s example changed: {text!r} no longer in it; update this test"
        block = block.replace(text, tiny)
    monkeypatch.chdir(tmp_path)
    scope = {"ARCH": arch}
    exec(compile(block, str(guide), "exec"), scope)
    return scope


def test_python_api_example_runs(tmp_path, monkeypatch):
    arch = tiny_arch()
    checkpoint = write_pi05_checkpoint(tmp_path / "pi05_libero_pytorch", arch, seed=0)
    tokenizer = write_tokenizer(tmp_path / "paligemma_tokenizer.model")
    sae_dir = write_sae_folder(tmp_path / "sae", d_in=arch.width, d_sae=96, hook_layer=2)
    language_start = 3 * arch.tokens_per_image
    # The real sizes in the text, each replaced by its tiny counterpart; every one must still be in the guide.
    substitutions = {
        '"pi05_libero_pytorch", max_layer=12)': f'{str(checkpoint)!r}, arch=ARCH, max_layer=2)',
        '"paligemma_tokenizer.model"': repr(str(tokenizer)),
        "layers=[12]": "layers=[2]",
        "resid[12]": "resid[2]",
        "768 + start : 768 + end": f"{language_start} + start : {language_start} + end",
        'load_sae("gemma-2b-it-res-jb", "blocks.12.hook_resid_post")': f"load_sae({str(sae_dir)!r})",
        "libero_camera_slots(agentview, wrist)": f"libero_camera_slots(agentview, wrist, {arch.image_size})",
    }
    scope = run_example("Pi05Prefix", substitutions, arch, tmp_path, monkeypatch)
    n_instruction = scope["prompt"].instruction[1] - scope["prompt"].instruction[0]
    assert scope["rows"].shape == (n_instruction, arch.width)
    assert scope["latents"].shape == (n_instruction, 96)
    assert torch.isfinite(scope["latents"]).all()


def test_policy_example_runs(tmp_path, monkeypatch):
    arch = tiny_arch()
    checkpoint = write_pi05_checkpoint(tmp_path / "pi05_libero_pytorch", arch, seed=0)
    tokenizer = write_tokenizer(tmp_path / "paligemma_tokenizer.model")
    folder = tmp_path / "data" / "latent_steering" / "layer12" / "open_vs_close"
    folder.mkdir(parents=True)
    unit = torch.nn.functional.normalize(torch.randn(arch.width), dim=0)
    write_method_direction(folder, MethodDirection("sae", "open_vs_close", 12, unit, 3.0, (-1.0, 1.0), 40.0, {}))
    substitutions = {
        '"pi05_libero_pytorch", tokenizer_path': f"{str(checkpoint)!r}, arch=ARCH, device='cpu', tokenizer_path",
        '"paligemma_tokenizer.model"': repr(str(tokenizer)),
        "layer=12": "layer=2",
    }
    scope = run_example("Pi05Policy, Steering", substitutions, arch, tmp_path, monkeypatch)
    assert scope["actions"].shape == (10, 7)
    scope = run_example("policy.warm_up", {key: value for key, value in substitutions.items() if key != "layer=12"},
                        arch, tmp_path, monkeypatch)
    assert scope["seconds"] > 0 and not scope["policy"].compiled  # compiled=None: eager on the CPU
