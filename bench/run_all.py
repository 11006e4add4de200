"""Run every benchmark, each in its own process, and rewrite BENCHMARKS.md from their results.

    uv run python -m bench.run_all [--device cuda] [--only capture_throughput ...] [--real-size]

`--real-size` adds the real-size sections (bench.real_size and bench.policy_real_size: one 7.2 GB generated
checkpoint, up to 14 GB of memory, a few minutes), which the 10-minute budget leaves out; so does
bench.policy_latency (`--only policy_latency`: minutes of compilation per batch size on a CPU).

`--quick` runs the tiny sizes (a smoke run: the numbers mean nothing) and writes its report next to the
generated inputs instead of over BENCHMARKS.md, unless --output says otherwise.
"""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import REPO_ROOT, Result, cache_dir, machine, markdown_table, parser

BENCHMARKS = (
    "capture_throughput", "concept_map_speed", "slicing_memory", "sae_encoding", "incremental_refresh", "policy_sweep",
    "cli_startup",
    "serve_latency",
    "serve_throughput",
    "evaluate_cost",
    "rollout_throughput",
    "sae_training",
    "slicing_remote",
    "capture_input",
)
# run only when asked (--real-size or --only): minutes of loading, or of compiling (policy_latency)
OPT_IN = ("real_size", "policy_real_size", "policy_latency")
REPORT = REPO_ROOT / "BENCHMARKS.md"
QUICK_REPORT = "BENCHMARKS.quick.md"  # under the cache folder
BUDGET_MINUTES = 10  # the whole set on a 2-core machine


def run_one(name: str, flags: list[str], folder: Path) -> tuple[Result, float]:
    """Run one benchmark module in a fresh process; return its result and wall time in seconds."""
    output = folder / f"{name}.json"
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", f"bench.{name}", *flags, f"--json={output}"], cwd=REPO_ROOT)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"bench.{name} failed with exit code {done.returncode}; see its output above")
    return Result.from_json(json.loads(output.read_text(encoding="utf-8"))), seconds


def description(name: str) -> list[str]:
    """Return a benchmark module's docstring without its first line and usage line, as markdown lines."""
    doc = importlib.import_module(f"bench.{name}").__doc__ or ""
    lines = [line for line in doc.strip().splitlines()[1:] if "uv run python" not in line]
    return "\n".join(lines).strip().splitlines()


def render(results: list[tuple[str, Result, float]], info: dict[str, str], total: float, invocation: str) -> str:
    """Return BENCHMARKS.md: machine, summary table with a reproducing command per line, then each benchmark."""
    opt_in = sum(seconds for name, _, seconds in results if name in OPT_IN)
    took = f"The whole set took {(total - opt_in) / 60:.1f} min (budget: {BUDGET_MINUTES} min on a 2-core machine)"
    if opt_in:
        took += f", and the opt-in real-size sections {opt_in / 60:.1f} min more"
    lines = [
        "# Benchmarks",
        "",
        f"Written by `{invocation}`; every number below comes from that one run. Each ratio compares our code "
        "with a baseline measured in the same run (in the same process, or in sibling processes where peak "
        f"memory is measured). {took}. Generated inputs are cached in a temporary folder, so a second run "
        "skips their creation.",
        "",
        "## Machine",
        "",
        *markdown_table([{"": key, "value": value} for key, value in info.items()]),
        "",
        "## Summary",
        "",
        *markdown_table([
            {
                "benchmark": result.title,
                "ours": result.measured,
                "baseline": result.baseline,
                "ratio": f"{result.ratio:.2f}x",
                "target": result.target,
                "met": "yes" if result.met else "**no**",
                "run time": f"{seconds:.0f} s",
                "reproduce": f"`{result.command}`",
            }
            for _, result, seconds in results
        ]),
    ]
    for name, result, _ in results:
        lines += ["", f"## {result.title}", "", *description(name), "", *markdown_table(result.table), ""]
        lines += [f"- {note}" for note in result.notes]
        lines += ["", f"Reproduce: `{result.command}`"]
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str] | None = None) -> Path:
    """Run the selected benchmarks and write the report; return its path."""
    arguments = parser(__doc__.splitlines()[0])
    arguments.add_argument("--only", nargs="+", choices=BENCHMARKS + OPT_IN, default=list(BENCHMARKS))
    arguments.add_argument("--real-size", action="store_true", help="also run the opt-in real-size section")
    arguments.add_argument("--output", type=Path, default=None, help="report path (default BENCHMARKS.md)")
    args = arguments.parse_args(argv)
    folder = cache_dir(args)
    output = args.output or (folder / QUICK_REPORT if args.quick else REPORT)
    flags = [f"--device={args.device}", f"--cache-dir={folder}", *(["--quick"] if args.quick else [])]
    results = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-results-") as scratch:
        selected = [*args.only, *(OPT_IN if args.real_size else ())]
        for name in [n for n in BENCHMARKS + OPT_IN if n in selected]:
            result, seconds = run_one(name, flags, Path(scratch))
            results.append((name, result, seconds))
    total = time.perf_counter() - start
    invocation = " ".join(["uv run python -m bench.run_all", *(argv if argv is not None else sys.argv[1:])])
    output.write_text(render(results, machine(), total, invocation), encoding="utf-8")
    print(f"wrote {output} ({total / 60:.1f} min)")
    return output


if __name__ == "__main__":
    main()
