"""The GPU check's sections on the pi0.5 policy: capture's forward, `sample_actions` latency, the steering sweep,
precision on the device against float32 on the CPU, and the policy server (see `bench.gpu_check`)."""

from __future__ import annotations

import contextlib
import importlib.util
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch

from bench import capture_throughput, policy_sweep, serve_latency
from bench.capture_throughput import REAL_PROMPT_TOKENS, ours_flops_selected_queries, seed_flops
from bench.common import median, repeat_timed, timed
from bench.gpu_harness import (
    Comparison,
    Context,
    Section,
    one_minus_cosine,
    relative_error,
    row_relative_error,
    tolerance,
)
from bench.policy_latency import measure_latency
from steering_core.pi05 import Pi05Arch, Pi05Policy, Steering
from steering_core.pi05.steering import Splice

PROMPT_TOKENS = REAL_PROMPT_TOKENS  # valid tokens of each frame's prompt
STEPS = 10  # denoising steps
BATCH1_TARGET_MS = 40.0  # batch-1 sample_actions on an H100/H200-class GPU (published pi0.5: 22-57 ms on 4090 / L40S)
SWEEP_ALPHAS = policy_sweep.ALPHAS  # 8 steerings
VECTOR_NORM = 10.0  # steering vectors' norm (alpha 1)
# The precision section steers the LM at every prefix position with alpha 16: in the mid-size random model that
# moves the float32 actions by 17%, against bf16's 0.3% rounding; steering the 14 instruction tokens moved them
# by 0.8% at most (whatever alpha), too little for the effect to be compared in bf16.
LM_ALPHA = 16.0


@contextlib.contextmanager
def full_float32() -> Iterator[None]:
    """Run the block with TF32 off for matmuls and cuDNN convolutions (SigLIP's patches), then restore both:
    float32 on CUDA must round like float32, not like TF32's 10-bit mantissa."""
    matmul, cudnn = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = matmul, cudnn


# ----------------------------------------------------------------------------- inputs


def frames(arch: Pi05Arch, batch: int, device: torch.device) -> tuple[list, list, torch.Tensor, torch.Tensor]:
    """Return `batch` LIBERO-shaped frames (`bench.policy_sweep.frame`) on `device`."""
    images, masks, tokens, token_mask = policy_sweep.frame(arch, PROMPT_TOKENS, batch)
    return ([image.to(device) for image in images], [mask.to(device) for mask in masks], tokens.to(device),
            token_mask.to(device))


def instruction_mask(batch: int) -> torch.Tensor:
    """Return (batch, 200) bool on the CPU: the prompt's instruction tokens (BOS and the closing "\\n" left out)."""
    mask = torch.zeros(batch, policy_sweep.TOKEN_SLOTS, dtype=torch.bool)
    mask[:, 1 : PROMPT_TOKENS - 1] = True
    return mask


def random_vector(width: int, seed: int) -> torch.Tensor:
    """Return a random (width,) float32 CPU vector of norm VECTOR_NORM."""
    vector = torch.randn(width, generator=torch.Generator().manual_seed(seed))
    return vector / vector.norm() * VECTOR_NORM


def noise(policy: Pi05Policy, batch: int) -> torch.Tensor:
    """Return fixed (batch, horizon, action_dim) float32 CPU noise."""
    generator = torch.Generator().manual_seed(3)
    return torch.randn(batch, policy.action_horizon, policy.action_dim, generator=generator)

def capture(ctx: Context) -> Section:
    """Capture's forward (selected rows) against the seed's whole inference call with a hook, same rows."""
    from bench.seed_pi05 import SeedPi05, expert_arch
    from steering_core.capture.selected_rows import selected_residuals

    section = Section()
    arch, layer, device = ctx.sizes.arch, ctx.sizes.layer, ctx.device
    model = SeedPi05.from_checkpoint(ctx.checkpoint, arch, device, layout=ctx.layout)
    ours_flops = ours_flops_selected_queries(arch, layer, PROMPT_TOKENS)
    peak_flops = ctx.peak_flops()
    instruction = torch.arange(1, PROMPT_TOKENS - 1)  # BOS and "\n" are not instruction tokens
    for batch in ctx.sizes.capture_batches:
        inputs = frames(arch, batch, device)
        frame_of_row = torch.arange(batch).repeat_interleave(len(instruction)).to(device)
        positions = (arch.prefix_length(3, 0) + instruction).repeat(batch).to(device)

        def ours() -> torch.Tensor:
            return selected_residuals(model.prefix, *inputs, [layer], frame_of_row, positions)[layer]

        def seed() -> torch.Tensor:  # the seed's hook point: one decoder layer, for one whole inference call
            hooked: list[torch.Tensor] = []
            handle = model.prefix.layers[layer].register_forward_hook(lambda _m, _i, output: hooked.append(output))
            try:
                model.sample_actions(*inputs)
            finally:
                handle.remove()
            return hooked[-1][frame_of_row, positions]

        ours_s = median(repeat_timed(ours, device, warmup=1, repeats=ctx.sizes.repeats))
        seed_s = median(repeat_timed(seed, device, warmup=1, repeats=ctx.sizes.repeats))
        ours_fps, seed_fps = batch / ours_s, batch / seed_s
        section.figures.setdefault("capture_frames_per_s", {})[str(batch)] = ours_fps
        section.measure(f"ours frames/s, layer {layer}, batch {batch}", ours_fps,
                        f"seed {seed_fps:.3g} frames/s", ours_fps / seed_fps)
        section.measure(f"ours TFLOP/s (MFU), batch {batch}", ours_fps * ours_flops / 1e12,
                        f"peak {peak_flops / 1e12:.3g} TFLOP/s", ours_fps * ours_flops / peak_flops)
        section.measure(f"seed TFLOP/s (MFU), batch {batch}", seed_fps * seed_flops(arch, 1) / 1e12,
                        f"peak {peak_flops / 1e12:.3g} TFLOP/s", seed_fps * seed_flops(arch, 1) / peak_flops)
        section.comparisons.append(Comparison(f"capture rows vs seed, batch {batch}", "max row relative error",
                                              row_relative_error(ours(), seed()), tolerance(ctx.dtype)))
    section.notes.append(
        f"capture: {PROMPT_TOKENS}-token prompts in 200 slots, two cameras and the masked third, inputs on the "
        f"device; analytic FLOPs per frame (matrix products): ours {ours_flops / 1e9:.3g} G, the seed's "
        f"{seed_flops(arch, 1) / 1e9:.3g} G; medians of {ctx.sizes.repeats} calls after a warm-up.")
    shaped, expert = expert_arch(arch), model.gemma_expert.model.layers[0].mlp
    if (model.action_in_proj.out_features, expert.intermediate_size) != (shaped.width, shaped.mlp_dim):
        section.notes.append(
            f"capture: the checkpoint's action expert ({model.action_in_proj.out_features} wide, MLP "
            f"{expert.intermediate_size}) is not gemma_300m-shaped beside its language model ({shaped.width}, "
            f"{shaped.mlp_dim}): the timed seed runs the checkpoint's expert, its analytic FLOPs count the "
            "gemma_300m-shaped one.")
    return section


def policy_latency(policy: Pi05Policy, batches: tuple[int, ...], repeats: int, label: str) -> Section:
    """Time `sample_actions` at each batch size, and the GPU kernel time of the batch-1 call against its wall time.

    Takes any policy, so that eager and compiled builds of the same checkpoint can be measured alike.
    """
    section = Section()
    device = policy.device
    arch = policy.arch
    wall: dict[int, float] = {}
    calls: dict[int, Callable[[], torch.Tensor]] = {}
    for batch in batches:
        inputs, start = frames(arch, batch, device), noise(policy, batch)
        calls[batch] = lambda inputs=inputs, start=start: policy.sample_actions(*inputs, noise=start, num_steps=STEPS)
        wall[batch] = median(repeat_timed(calls[batch], device, warmup=1, repeats=repeats))
        section.figures.setdefault("sample_actions_ms", {})[str(batch)] = wall[batch] * 1e3
        section.measure(f"sample_actions ms, batch {batch} ({label})", wall[batch] * 1e3,
                        f"batch {batches[0]} x {batch}: {wall[batches[0]] * batch * 1e3:.4g} ms",
                        wall[batch] / (wall[batches[0]] * batch))
    kernel = kernel_seconds(calls[batches[0]], device)
    if kernel is None:
        section.measure(f"GPU kernel ms, batch 1 ({label})", "n/a (CPU)", f"wall {wall[batches[0]] * 1e3:.4g} ms")
    else:
        section.measure(f"GPU kernel ms, batch 1 ({label})", kernel * 1e3, f"wall {wall[batches[0]] * 1e3:.4g} ms",
                        kernel / wall[batches[0]])
    return section


def kernel_seconds(call: Callable[[], Any], device: torch.device) -> float | None:
    """Return the summed time of the CUDA kernels (and copies) one call launches, by torch.profiler; None on the CPU."""
    if device.type != "cuda":
        return None
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    call()  # warm: the profiled call launches what a steady call launches
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as profiler:
        timed(call, device)
    kernels = [event for event in profiler.events() if event.device_type == DeviceType.CUDA]
    return sum(event.time_range.elapsed_us() for event in kernels) / 1e6


def latency(ctx: Context) -> Section:
    """Load the policy; time sample_actions against batch size and its kernel time against wall time; then the
    batch-1 call of the other build (compiled denoising against eager), with its actions compared."""
    policy, load_seconds = ctx.policy()
    parameters = sum(p.numel() * p.element_size() for p in policy.parameters()) / 2**30
    build = "compiled" if policy.compiled else "eager"
    section = policy_latency(policy, ctx.sizes.latency_batches, ctx.sizes.repeats, f"as from_checkpoint builds it: {build}")
    section.measures.insert(0, {"measure": "from_checkpoint s", "value": load_seconds,
                                "against": f"{parameters:.3g} GiB of parameters", "ratio": ""})
    other = Pi05Policy(policy.prefix, policy.expert, policy.action_horizon, policy.tokenizer, policy.normalization,
                       compiled=not policy.compiled)  # the same weights
    mine, theirs = measure_latency(policy, 1, ctx.sizes.repeats), measure_latency(other, 1, ctx.sizes.repeats)
    compiled, eager = (mine, theirs) if policy.compiled else (theirs, mine)
    section.measure("sample_actions ms, batch 1, compiled denoising", compiled["median_ms"],
                    f"eager {eager['median_ms']:.4g} ms", compiled["median_ms"] / eager["median_ms"])
    section.measure("compiled batch-1 ms against the 40 ms target", compiled["median_ms"], "40 ms",
                    compiled["median_ms"] / BATCH1_TARGET_MS)
    section.measure("compilation s (warm-up, batch 1)", compiled["warm_up_s"], "paid once per process and batch size")
    section.comparisons.append(Comparison("compiled vs eager actions, batch 1", "relative error",
                                          relative_error(compiled["actions"], eager["actions"]), tolerance(ctx.dtype)))
    section.figures["compiled_batch1_ms"] = compiled["median_ms"]
    section.notes.append(f"latency: {STEPS} denoising steps, fixed noise, {PROMPT_TOKENS}-token prompts; "
                         "the ratio is the time against batch 1 times the batch (below 1: batching pays); kernel "
                         "time is the sum of the batch-1 call's CUDA kernels and copies (torch.profiler); the "
                         "compiled denoising step (default on CUDA) against eager on the same weights, its first "
                         "call (the compilation) timed apart.")
    return section


def sweep(ctx: Context) -> Section:
    """sample_actions_sweep of 8 steerings (CPU vectors) against 8 separate sample_actions calls."""
    section = Section()
    policy, _ = ctx.policy()
    inputs = frames(policy.arch, 1, ctx.device)
    start = noise(policy, 1)
    vector = random_vector(policy.arch.width, 1)
    entries = [Steering(ctx.sizes.layer, vector, alpha) for alpha in SWEEP_ALPHAS]

    def swept() -> torch.Tensor:
        return policy.sample_actions_sweep(*inputs, entries, noise=start, num_steps=STEPS)

    def separate() -> torch.Tensor:
        return torch.stack([policy.sample_actions(*inputs, noise=start, num_steps=STEPS, steering=e) for e in entries])

    sweep_s = median(repeat_timed(swept, ctx.device, warmup=1, repeats=ctx.sizes.repeats))
    separate_s = median(repeat_timed(separate, ctx.device, warmup=1, repeats=ctx.sizes.repeats))
    section.measure(f"sweep of {len(entries)} steerings s", sweep_s, f"{len(entries)} calls {separate_s:.3g} s",
                    sweep_s / separate_s)
    section.comparisons.append(Comparison("sweep vs separate calls", "relative error",
                                          relative_error(swept(), separate()), tolerance(ctx.dtype)))
    return section


def precision_outputs(policy: Pi05Policy, sae_dir: Path, batch: int) -> dict[str, torch.Tensor]:
    """Return the compared outputs of one policy, float32 on the CPU: actions unsteered, LM-steered,
    expert-steered and SAE-spliced, and the decision rows; steering vectors and masks start on the CPU."""
    from steering_core.capture.action_rows import decision_rows
    from steering_core.sae.model import load_sae

    arch = policy.arch
    layer = arch.depth * 2 // 3  # 12 of 18: the seed's layer
    inputs = frames(arch, batch, policy.device)
    start = noise(policy, batch)
    sae = load_sae(sae_dir, device=policy.device)
    mask = instruction_mask(batch)
    every_position = torch.ones(batch, arch.prefix_length(3, mask.shape[1]), dtype=torch.bool)  # on the CPU

    def actions(**kwargs: Any) -> torch.Tensor:
        return policy.sample_actions(*inputs, noise=start, num_steps=STEPS, **kwargs).float().cpu()

    expert_layer = policy.expert_arch.depth - 1
    rows = decision_rows(policy, *inputs, start, [expert_layer], STEPS)[expert_layer]
    return {
        "unsteered actions": actions(),
        "LM-steered actions": actions(steering=Steering(layer, random_vector(arch.width, 1), LM_ALPHA,
                                                        prefix_mask=every_position)),
        "expert-steered actions": actions(steering=Steering(expert_layer, random_vector(policy.expert_arch.width, 2),
                                                            1.0, stream="expert")),
        "SAE-spliced actions": actions(splice=Splice(layer, lambda x: sae.reconstruct(x)[0], token_mask=mask)),
        "decision rows": rows.float().cpu(),
    }


def precision(ctx: Context) -> Section:
    """float32 and bfloat16 on the device against float32 on the CPU at the mid-size model."""
    from steering_core.synthetic.sae import write_sae_folder

    section = Section()
    arch, batch = ctx.sizes.precision_arch, ctx.sizes.precision_batch
    checkpoint, _ = capture_throughput.model_files(ctx.folder / "precision", arch)
    sae_dir = ctx.folder / "precision" / f"sae-{arch.width}x{4 * arch.width}"
    if not sae_dir.is_dir():
        write_sae_folder(sae_dir, d_in=arch.width, d_sae=4 * arch.width)
    reference = precision_outputs(Pi05Policy.from_checkpoint(checkpoint, arch, device="cpu", dtype="float32"),
                                  sae_dir, batch)
    unsteered = reference["unsteered actions"]
    for dtype in (torch.float32, torch.bfloat16):
        name = str(dtype).removeprefix("torch.")
        with full_float32():
            policy = Pi05Policy.from_checkpoint(checkpoint, arch, device=ctx.device, dtype=dtype)
            got = precision_outputs(policy, sae_dir, batch)
        for case, want in reference.items():
            metric = "max row relative error" if case == "decision rows" else "relative error"
            error = (row_relative_error if case == "decision rows" else relative_error)(got[case], want)
            section.comparisons.append(Comparison(f"{name} {ctx.device.type} vs float32 cpu: {case}", metric, error,
                                                  tolerance(dtype)))
        for case in ("LM-steered actions", "expert-steered actions"):
            effect, want = got[case] - got["unsteered actions"], reference[case] - unsteered
            label = f"{name} {ctx.device.type} vs float32 cpu: effect of {case.split()[0]} steering"
            # the effect carries the rounding of both actions it is the difference of, each within the tolerance
            scale = float((reference[case].norm() + unsteered.norm()) / want.norm())
            section.comparisons.append(Comparison(label, "relative error", relative_error(effect, want),
                                                  tolerance(dtype) * scale))
            section.comparisons.append(Comparison(label, "1 - cosine", one_minus_cosine(effect, want),
                                                  tolerance(dtype)))
    effects = {case.split()[0]: relative_error(reference[case], unsteered)
               for case in ("LM-steered actions", "expert-steered actions", "SAE-spliced actions")}
    section.notes.append(
        f"precision: model width {arch.width} x {arch.depth} layers (SigLIP {arch.vision_width} x "
        f"{arch.vision_depth}, {arch.image_size} px), batch {batch}; TF32 off; LM steering (alpha {LM_ALPHA:g}, "
        f"every prefix position) and the SAE splice (instruction tokens) at LM layer {arch.depth * 2 // 3}, expert "
        "steering (alpha 1) at its last layer, vectors and masks on the CPU; each changes the float32 actions by "
        + ", ".join(f"{case} {value:.3g}" for case, value in effects.items())
        + " (relative), so an effect lost on the device fails its comparison.")
    return section


@contextlib.contextmanager
def openpi_connection(port: int) -> Iterator[tuple[Callable[[dict], dict], str]]:
    """Yield (infer(observation) -> reply, the client's name): openpi-client's WebsocketClientPolicy when
    installed, else the same protocol with the project's codec (msgpack-numpy, metadata first)."""
    if importlib.util.find_spec("openpi_client") is not None:
        from openpi_client.websocket_client_policy import WebsocketClientPolicy

        client = WebsocketClientPolicy("127.0.0.1", port)
        try:
            yield client.infer, "openpi-client WebsocketClientPolicy"
        finally:
            client._ws.close()  # the client has no close(); an open connection would hold the server's shutdown
        return
    from websockets.sync.client import connect

    from steering_core.serve.codec import pack, unpack

    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
        ws.recv()  # the server's metadata

        def infer(observation: dict) -> dict:
            ws.send(pack(observation))
            return unpack(ws.recv())

        yield infer, "the project's codec (openpi-client not installed)"


def server(ctx: Context) -> Section:
    """A steered request (CPU vector, policy on the device) over loopback against a direct infer."""
    from steering_core.serve import PolicyServer, parse_steering
    from steering_core.serve.server import serving_in_thread

    section = Section()
    policy, _ = ctx.policy()
    served, catalog = serve_latency.steered(policy, ctx.checkpoint)
    observation = serve_latency.observation()
    entry = {"pair": serve_latency.PAIR, "layer": serve_latency.LAYER, "alpha": serve_latency.ALPHA,
             "alpha_units": "vector"}
    steering = parse_steering(entry, catalog)
    direct = served.infer(observation, steering)["actions"]  # also the warm-up
    plain = served.infer(observation, ())["actions"]
    direct_s = median(repeat_timed(lambda: served.infer(observation, steering), ctx.device, warmup=0,
                                   repeats=ctx.sizes.server_rounds))
    round_trips = []
    with serving_in_thread(PolicyServer(served, catalog, host="127.0.0.1", port=0)) as running, \
            openpi_connection(running.port) as (infer, client):
        for _ in range(ctx.sizes.server_rounds + 1):  # the first warms up
            start = time.perf_counter()
            remote = infer(observation | {"steering": entry})["actions"]
            round_trips.append(time.perf_counter() - start)
    trip_s = median(round_trips[1:])
    section.measure("steered round trip ms", trip_s * 1e3, f"direct infer {direct_s * 1e3:.3g} ms", trip_s / direct_s)
    remote_t, direct_t, plain_t = (torch.tensor(actions) for actions in (remote, direct, plain))
    section.comparisons.append(Comparison("served steered actions vs direct infer", "relative error",
                                          relative_error(remote_t, direct_t), tolerance(ctx.dtype)))
    change = relative_error(direct_t, plain_t)
    section.notes.append(f"server: client {client}; the vector ({serve_latency.PAIR}, layer {serve_latency.LAYER}, "
                         f"alpha {serve_latency.ALPHA}) is on the CPU and the policy on {ctx.device}; steering "
                         f"changes the actions by {change:.3g} (relative); served == direct bit for bit: "
                         f"{remote.tobytes() == direct.tobytes()}.")
    return section
