"""Caller tensors may live on any device: every public entry point moves them to the model's device, once.

On the CPU the suite plays "another device" with `helpers_devices.Foreign` (a CPU tensor that refuses to meet
an ordinary one, as a CPU tensor refuses a CUDA one): each entry point gets every tensor it takes as a Foreign
one and must give the same result as with ordinary tensors, bit for bit. Where CUDA is present, the same calls
run with the model on CUDA and the inputs on the CPU, compared with the CPU model: float32 within float32
rounding of the model's depth, bfloat16 within bfloat16 rounding (see `CUDA_TOLERANCES`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers_devices import Foreign, elsewhere
from helpers_pi05 import make_batch

from steering_core.capture.action_rows import decision_rows
from steering_core.capture.selected_rows import selected_residuals
from steering_core.pi05 import Pi05Policy, PromptTokenizer, Steering
from steering_core.pi05.steering import Splice
from steering_core.sae.model import load_sae
from steering_core.sae_quality.fidelity import row_fidelity
from steering_core.serve.catalog import SteeringVector
from steering_core.serve.policy import SteeredPi05Policy
from steering_core.serve.request import AppliedSteering
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.sae import write_sae_folder
from steering_core.synthetic.tokenizer import write_tokenizer

ARCH = tiny_arch()
MAX_LEN = 24
CUDA = torch.cuda.is_available()
NEEDS_CUDA = pytest.mark.skipif(not CUDA, reason="no CUDA device here: the Foreign-tensor tests stand in on the CPU")
# CUDA against the CPU, as the largest |difference| over the largest |value| of the reference. float32: the
# kernels differ (TF32 is off by default, but reductions split differently), so a few ulps per op through
# the tiny model's depth; bfloat16: 8 bits of mantissa (2^-8 = 0.4%) per rounding, a few roundings deep.
CUDA_TOLERANCES = {torch.float32: 1e-4, torch.bfloat16: 3e-2}


@dataclass
class Model:
    policy: Pi05Policy
    sae: Any
    tokenizer: PromptTokenizer


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("devices")
    checkpoint = write_pi05_checkpoint(folder / "ckpt", ARCH, seed=3)
    tokenizer = write_tokenizer(folder / "tokenizer.model")
    sae = write_sae_folder(folder / "sae", d_in=ARCH.width, d_sae=4 * ARCH.width, seed=2)
    return checkpoint, tokenizer, sae


def load(files, device: str, dtype: torch.dtype | None = None) -> Model:
    checkpoint, tokenizer, sae = files
    policy = Pi05Policy.from_checkpoint(checkpoint, ARCH, device=device, dtype=dtype, tokenizer_path=tokenizer)
    return Model(policy, load_sae(sae, device=device), PromptTokenizer(tokenizer, max_len=MAX_LEN))


@pytest.fixture(scope="module")
def cpu(files):
    return load(files, "cpu")


def vector(width: int, seed: int) -> torch.Tensor:
    return torch.randn(width, generator=torch.Generator().manual_seed(seed))


def inputs(model: Model, place: Callable[[torch.Tensor], torch.Tensor]) -> dict[str, Any]:
    """Return every tensor an entry point takes, each passed through `place` (elsewhere, or left as it is)."""
    batch = make_batch(ARCH, model.tokenizer)
    size = batch.tokens.shape[0]
    prefix_mask = torch.zeros(size, 3 * ARCH.tokens_per_image + MAX_LEN, dtype=torch.bool)
    prefix_mask[:, 3 * ARCH.tokens_per_image : 3 * ARCH.tokens_per_image + 3] = True
    return {
        "images": [place(image) for image in batch.images],
        "image_masks": [place(mask) for mask in batch.image_masks],
        "tokens": place(batch.tokens),
        "token_mask": place(batch.token_mask),
        "noise": place(torch.randn(size, 10, 32, generator=torch.Generator().manual_seed(5))),
        "instruction": place(batch.token_mask & (torch.arange(MAX_LEN) % 2 == 0)),
        "prefix_mask": place(prefix_mask),
        "lm_vector": place(vector(ARCH.width, 1)),
        "expert_vector": place(vector(model.policy.expert_arch.width, 2)),
        "frame_of_row": place(torch.tensor([0, 0, 1, 2])),
        "positions": place(torch.tensor([3 * ARCH.tokens_per_image, 3 * ARCH.tokens_per_image + 1,
                                         3 * ARCH.tokens_per_image + 2, ARCH.tokens_per_image])),
        "rows": place(torch.randn(6, ARCH.width, generator=torch.Generator().manual_seed(7))),
        "latents": place(torch.rand(6, 4 * ARCH.width, generator=torch.Generator().manual_seed(8))),
    }


def prompt(x):
    return (x["images"], x["image_masks"], x["tokens"], x["token_mask"])


def actions(model, x, steering=None, splice=None):
    return model.policy.sample_actions(*prompt(x), noise=x["noise"], steering=steering, splice=splice)


# Each entry point as it is called with the caller's tensors; the result is a tensor or a dict of tensors.
CALLS: dict[str, Callable[[Model, dict[str, Any]], Any]] = {
    "residuals": lambda m, x: m.policy.prefix.residuals(*prompt(x), layers=[0, 2]),
    "selected_residuals": lambda m, x: selected_residuals(m.policy.prefix, *prompt(x), [0, 2], x["frame_of_row"],
                                                          x["positions"]),
    "sample_actions": lambda m, x: actions(m, x),
    "lm_steered_at_tokens": lambda m, x: actions(m, x, Steering(1, x["lm_vector"], 4.0, token_mask=x["instruction"])),
    "lm_steered_at_prefix": lambda m, x: actions(m, x, Steering(1, x["lm_vector"], 4.0, prefix_mask=x["prefix_mask"])),
    "lm_steered_every_token": lambda m, x: actions(m, x, Steering(0, x["lm_vector"], 4.0)),
    "expert_steered": lambda m, x: actions(m, x, Steering(1, x["expert_vector"], 4.0, stream="expert")),
    "spliced": lambda m, x: actions(m, x, splice=Splice(1, lambda rows: 0.5 * rows, token_mask=x["instruction"])),
    "sae_spliced": lambda m, x: actions(m, x, splice=Splice(1, lambda rows: m.sae.reconstruct(rows)[0])),
    "sweep": lambda m, x: m.policy.sample_actions_sweep(
        *prompt(x), [None, Steering(1, x["lm_vector"], 4.0, token_mask=x["instruction"]),
                     [Steering(0, x["lm_vector"], -2.0), Steering(1, x["expert_vector"], 4.0, stream="expert")]],
        noise=x["noise"]),
    "decision_rows": lambda m, x: decision_rows(m.policy, *prompt(x), x["noise"], [0, 1], num_steps=3),
    "sae_encode": lambda m, x: m.sae.encode(x["rows"]),
    "sae_reconstruct": lambda m, x: m.sae.reconstruct(x["rows"])[0],
    "sae_decode": lambda m, x: m.sae.decode(x["latents"]),
    "sae_decode_direction": lambda m, x: m.sae.decode_direction(x["latents"][0]),
    "row_fidelity": lambda m, x: torch.tensor(row_fidelity({"sae": m.sae}, [x["rows"]])["sae"].fvu),
}


def as_dict(result) -> dict:
    return result if isinstance(result, dict) else {"": result}


def test_foreign_tensors_refuse_to_meet_ordinary_ones():
    """The stand-in must fail as CUDA does, or the tests below could not fail."""
    foreign = elsewhere(torch.ones(3))
    with pytest.raises(RuntimeError, match="Expected all tensors to be on the same device"):
        foreign + torch.ones(3)
    with pytest.raises(RuntimeError, match="Expected all tensors to be on the same device"):
        torch.cat([torch.zeros(2), foreign])
    assert isinstance(foreign * 2, Foreign)  # operations among foreign tensors stay foreign
    moved = foreign.to("cpu")
    assert type(moved) is torch.Tensor and torch.equal(moved + torch.ones(3), torch.full((3,), 2.0))


@pytest.mark.parametrize("name", sorted(CALLS))
def test_entry_point_moves_caller_tensors_to_the_model(cpu, name):
    expected = as_dict(CALLS[name](cpu, inputs(cpu, lambda t: t)))
    found = as_dict(CALLS[name](cpu, inputs(cpu, elsewhere)))
    assert found.keys() == expected.keys()
    for key in expected:
        assert type(found[key]) is torch.Tensor, f"{name}[{key}] came back as a caller's tensor"
        assert torch.equal(found[key], expected[key]), f"{name}[{key}] differs with the inputs elsewhere"


def test_served_steering_with_a_mask_made_elsewhere(cpu, monkeypatch):
    """The server's path: `instruction_mask` gives a CPU mask whatever the policy's device; the vector too."""
    observation = {
        "observation/image": np.full((32, 32, 3), 90, dtype=np.uint8),
        "observation/wrist_image": np.full((32, 32, 3), 160, dtype=np.uint8),
        "observation/state": np.zeros(8, dtype=np.float32),
        "prompt": "open the top drawer of the cabinet",
    }
    served = SteeredPi05Policy(cpu.policy, noise_seed=3)
    steering = [AppliedSteering(SteeringVector("pair", 1, "direction", vector(ARCH.width, 4), 1.0, Path("v.pt"),
                                                  "residual"), 4.0,
                                 alpha_units="vector")]
    expected = served.infer(observation, steering)["actions"]
    unmoved = cpu.policy.instruction_mask
    monkeypatch.setattr(cpu.policy, "instruction_mask", lambda text: elsewhere(unmoved(text)))
    np.testing.assert_array_equal(served.infer(observation, steering)["actions"], expected)
    assert not np.array_equal(served.infer(observation, [])["actions"], expected)  # the steering does something


@NEEDS_CUDA
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16], ids=["float32", "bfloat16"])
@pytest.mark.parametrize("name", sorted(CALLS))
def test_entry_point_on_cuda_with_cpu_inputs_matches_the_cpu(files, cpu, name, dtype):
    cuda = load(files, "cuda", dtype)
    expected = as_dict(CALLS[name](cpu, inputs(cpu, lambda t: t)))
    found = as_dict(CALLS[name](cuda, inputs(cpu, lambda t: t)))  # the caller's tensors stay on the CPU
    for key in expected:
        difference = (found[key].cpu().double() - expected[key].double()).abs().max()
        scale = expected[key].double().abs().max().clamp(min=1e-12)
        assert difference / scale <= CUDA_TOLERANCES[dtype], f"{name}[{key}]: {float(difference / scale):.2e}"
