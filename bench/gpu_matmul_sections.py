"""The GPU check's matmul-shaped sections: the practical peak, and SAE encode + decode and one SAE training step
against matmuls of the same shapes (see `bench.gpu_check`)."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable

import torch

from bench import sae_encoding, sae_training
from bench.common import median, repeat_timed
from bench.gpu_harness import Context, Section

SAE_ARCHITECTURES = ("standard", "topk")
SAE_TOPK_K = 64


def peak(ctx: Context) -> Section:
    """The practical peak: a square matmul in the policy's dtype."""
    section = Section()
    n = ctx.sizes.matmul
    section.measure(f"{str(ctx.dtype).removeprefix('torch.')} matmul {n}^3 TFLOP/s", ctx.peak_flops() / 1e12)
    section.figures["peak_tflops"] = ctx.peak_flops() / 1e12
    return section


def saelens_installed() -> bool:
    """Return whether SAELens can be imported (the GPU machine may lack it)."""
    return importlib.util.find_spec("sae_lens") is not None


def torch_topk_step(batch: int, d_in: int, d_sae: int, k: int, device: torch.device) -> Callable[[], None]:
    """Return one TopK SAE training step in plain torch (used when SAELens is absent): encode, top-k, decode,
    squared error, backward, Adam."""
    generator = torch.Generator().manual_seed(0)
    parameters = [(torch.randn(*shape, generator=generator) / shape[0] ** 0.5).to(device).requires_grad_()
                  for shape in ((d_in, d_sae), (1, d_sae), (d_sae, d_in), (1, d_in))]
    w_enc, b_enc, w_dec, b_dec = parameters
    optimizer = torch.optim.Adam(parameters, lr=1e-4)
    x = torch.randn(batch, d_in, generator=generator).to(device)

    def step() -> None:
        pre = x @ w_enc + b_enc
        values, indices = pre.topk(k, dim=-1)
        latents = torch.zeros_like(pre).scatter(-1, indices, values.relu())
        loss = (latents @ w_dec + b_dec - x).pow(2).sum(-1).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return step


def sae(ctx: Context) -> Section:
    """SAE encode + decode against matmul of the same shapes; one training step against its matmul bound."""
    from steering_core.sae.model import load_sae
    from steering_core.synthetic.sae import write_sae_folder

    section = Section()
    d_in, d_sae, batch = ctx.sizes.sae
    device, repeats = ctx.device, 5 * ctx.sizes.repeats
    for architecture in SAE_ARCHITECTURES:
        folder = ctx.folder / f"sae-{architecture}-{d_in}x{d_sae}"
        if not folder.is_dir():
            write_sae_folder(folder, d_in=d_in, d_sae=d_sae, architecture=architecture, k=SAE_TOPK_K)
        calls = sae_encoding.references(load_sae(folder, device=device), batch, device)
        seconds = {name: median(repeat_timed(call, device, warmup=2, repeats=repeats)) for name, call in calls.items()}
        section.measure(f"{architecture} SAE encode + decode rows/s ({d_in} x {d_sae}, batch {batch})",
                        batch / seconds["reconstruct"], f"matmul {batch / seconds['matmul']:,.0f} rows/s",
                        seconds["matmul"] / seconds["reconstruct"])
    sizes = ctx.sizes.sae_training
    if saelens_installed():
        found = sae_training.measure(ctx.folder / "sae_training", sizes, device)
        step_s, bound_s, label = found["step_seconds"], found["bound_seconds"], "SAELens TopK step (train_sae)"
    else:
        step = torch_topk_step(sizes["batch_size"], sizes["d_in"], sizes["d_sae"], sizes["k"], device)
        bound = sae_training.matmul_bound(sizes["batch_size"], sizes["d_in"], sizes["d_sae"], device)
        step_s = median(repeat_timed(step, device, warmup=2, repeats=repeats))
        bound_s = median(repeat_timed(bound, device, warmup=2, repeats=repeats))
        label = "plain torch TopK step (SAELens not installed)"
        section.notes.append("sae: SAELens is not installed here; the training row times a plain torch TopK step "
                             "(encode, top-k, decode, squared error, backward, Adam), not the project's trainer.")
    section.measure(f"{label} ms ({sizes['d_in']} x {sizes['d_sae']}, k {sizes['k']}, batch {sizes['batch_size']})",
                    step_s * 1e3, f"five-product matmul bound {bound_s * 1e3:.3g} ms", bound_s / step_s)
    return section
