"""Real size, whole policy: `Pi05Policy` loads a real-layout random checkpoint on the CPU and acts on one frame.

A random checkpoint with openpi's real layout (812 tensors, bfloat16 on disk, as openpi's converter writes) is
generated once in a child process (`steering_core.synthetic.pi05.write_pi05_checkpoint`) and cached, the same
one `bench.real_size` uses. Another
fresh process loads `Pi05Policy` on the CPU (float32) and runs `infer` on one LIBERO observation (two 224 px
cameras, 10 denoising steps, fixed noise). Reported: load and inference time, peak resident memory (VmHWM)
against the float32 bytes of the parameters (target: at most 1.25x), and whether the actions are finite.

Opt-in (`bench.run_all --real-size`): it needs about 15 GB of free memory and 8 GB of disk, and refuses to
start with less than MIN_AVAILABLE_GIB available.

    uv run python -m bench.policy_real_size [--quick]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open

from bench.common import Result, cache_dir, command, finish, parser, peak_rss_mib, print_child_result, run_child
from bench.real_size import checkpoint_folder
from steering_core.pi05 import Pi05Arch, Pi05Policy
from steering_core.synthetic.pi05 import checkpoint_tensor_shapes, tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

MIN_AVAILABLE_GIB = 18.0  # float32 policy ~14 GiB plus the interpreter and one frame's activations
TARGET = 1.25  # peak RSS / float32 parameter bytes, at most
STEPS = 10
PROMPT = "open the top drawer of the cabinet"


def available_gib() -> float:
    """Return MemAvailable from /proc/meminfo in GiB (0 when unknown)."""
    meminfo = Path("/proc/meminfo")
    for line in meminfo.read_text().splitlines() if meminfo.is_file() else []:
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) / 1024**2
    return 0.0


def measure(checkpoint: Path, tokenizer: Path, arch: Pi05Arch) -> dict:
    """Load the policy, act on one observation; return times, memory and checks (runs in a fresh process)."""
    start = time.perf_counter()
    policy = Pi05Policy.from_checkpoint(checkpoint, arch, device="cpu", tokenizer_path=tokenizer)
    load_s = time.perf_counter() - start
    parameter_mib = sum(p.numel() * p.element_size() for p in policy.parameters()) / 2**20
    generator = np.random.default_rng(0)
    observation = {
        "observation/image": generator.integers(0, 256, (256, 256, 3), dtype=np.uint8),
        "observation/wrist_image": generator.integers(0, 256, (256, 256, 3), dtype=np.uint8),
        "observation/state": generator.standard_normal(8).astype(np.float32),
        "prompt": PROMPT,
    }
    noise = torch.randn(policy.action_horizon, policy.action_dim, generator=torch.Generator().manual_seed(0))
    start = time.perf_counter()
    out = policy.infer(observation, noise=noise, num_steps=STEPS)
    infer_s = time.perf_counter() - start
    with safe_open(str(policy.prefix.model_file), framework="pt") as handle:
        tensors = len(list(handle.keys()))
    return {"load_s": load_s, "infer_s": infer_s, "peak_mib": peak_rss_mib(), "parameter_mib": parameter_mib,
            "tensors": tensors, "actions_shape": list(out["actions"].shape),
            "finite": bool(np.isfinite(out["actions"]).all())}


def main(argv: list[str] | None = None) -> Result | None:
    """Generate the checkpoint (child), measure the policy (child); return the result (None in a child)."""
    arguments = parser(__doc__.splitlines()[0])
    arguments.add_argument("--child", choices=("generate", "measure"), help=argparse.SUPPRESS)
    args = arguments.parse_args(argv)
    arch = tiny_arch() if args.quick else Pi05Arch()
    checkpoint = checkpoint_folder(args)  # the same generated checkpoint as bench.real_size
    tokenizer = checkpoint.parent / "pi05-tokenizer.model"
    if args.child == "generate":
        if not (checkpoint / "model.safetensors").is_file():
            write_pi05_checkpoint(checkpoint, arch, dtype=torch.bfloat16, overwrite=True)
        write_tokenizer(tokenizer)
        print_child_result({"written": str(checkpoint)})
        return None
    if args.child == "measure":
        print_child_result(measure(checkpoint, tokenizer, arch))
        return None
    if not args.quick and (free := available_gib()) < MIN_AVAILABLE_GIB:
        raise SystemExit(f"bench.policy_real_size: {free:.1f} GiB available, needs {MIN_AVAILABLE_GIB:.0f} GiB")
    flags = ["--quick"] if args.quick else []
    flags.append(f"--cache-dir={cache_dir(args)}")
    if not (checkpoint / "model.safetensors").is_file() or not tokenizer.is_file():
        run_child("policy_real_size", [*flags, "--child=generate"])
    measured = run_child("policy_real_size", [*flags, "--child=measure"])
    ratio = measured["peak_mib"] / measured["parameter_mib"]
    expected_tensors = len(checkpoint_tensor_shapes(arch))
    return finish(Result(
        name="policy_real_size",
        title="11. Real-size pi0.5 policy on the CPU: load and one frame" + (" (quick: tiny size)" if args.quick else ""),
        command=command("policy_real_size", args),
        measured=f"{measured['peak_mib']:.0f} MiB peak",
        baseline=f"{measured['parameter_mib']:.0f} MiB float32 parameters",
        ratio=ratio,
        target=f"<= {TARGET}x",
        met=ratio <= TARGET and measured["finite"] and measured["tensors"] == expected_tensors,
        table=[{"checkpoint tensors": measured["tensors"], "load": f"{measured['load_s']:.1f} s",
                f"infer ({STEPS} steps)": f"{measured['infer_s']:.1f} s", "actions": measured["actions_shape"],
                "finite": measured["finite"]}],
        notes=[f"checkpoint: {expected_tensors} tensors expected, bfloat16 on disk, loaded in float32"],
        checks={"finite": measured["finite"], "tensors": measured["tensors"], "expected_tensors": expected_tensors},
    ), args)


if __name__ == "__main__":
    main()
