"""CLI start-up: how long `latent-steering --help` and the light commands take, against a bare `python -c pass`.

Each command runs in a fresh process, as a user types it (the installed `latent-steering` script of this
environment); its wall time from start to exit and its CPU time (user + system, which a busy shared
machine inflates far less than the wall time) are measured several times and the medians kept, on the
same machine and in the same run as the baseline, a Python interpreter that starts and does nothing.
Command modules are imported only when their command runs (`latent_steering_cli.lazy`), so `--help`, `filter` and
`manifest` never load torch, lerobot, transformers or Prefect; `steer --help`, which needs torch, is
measured for comparison. `filter` selects two of four generated LIBERO demo files (real work, small).
The target is an absolute one: under 2 s of start-up (CPU time, and wall time when the machine is not
shared) for the commands that need neither torch nor lerobot.

    uv run python -m bench.cli_startup [--quick]
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from bench.common import Result, cache_dir, command, finish, median, parser

# ----------------------------------------------------------------------------- settings

REPEATS = 5  # runs per command (median kept)
TARGET_SECONDS = 2.0  # light commands, wall time from start to exit
HEAVY = ("torch", "lerobot", "transformers", "prefect")
QUICK = {"repeats": 2}


def cli_command() -> list[str]:
    """Return how to start the installed `latent-steering` script with this interpreter's environment."""
    script = Path(sys.executable).parent / "latent-steering"
    return [str(script)] if script.is_file() else [sys.executable, "-c", "import sys; from latent_steering_cli import app; sys.exit(app())"]


def run_times(argv: list[str], repeats: int) -> tuple[float, float]:
    """Return the median wall and CPU (user + system) seconds of `repeats` fresh runs of `argv` (each must exit 0)."""
    walls, cpus = [], []
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        done = subprocess.run(argv, capture_output=True, text=True)
        walls.append(time.perf_counter() - start)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(argv)} failed (exit {done.returncode}):\n{done.stderr[-2000:]}")
    return median(walls), median(cpus)


def heavy_imports(args: list[str]) -> list[str]:
    """Return the heavy libraries a command imports (run once more in-process of a child that reports them)."""
    code = ("import sys\nfrom latent_steering_cli import app\n"
            f"sys.argv = ['latent-steering', *{args!r}]\n"
            "try:\n    app()\nexcept SystemExit:\n    pass\n"
            f"print(sorted({{m.split('.')[0] for m in sys.modules}} & {set(HEAVY)!r}))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return eval(done.stdout.strip().splitlines()[-1], {})  # noqa: S307  (our own printed list)


def demo_files(folder: Path) -> Path:
    """Return a folder of the four synthetic LIBERO task files (written once)."""
    from steering_core.synthetic.libero import SyntheticSettings, write_demo_suite

    demos = folder / "cli-startup-demos"
    if not demos.is_dir():
        write_demo_suite(demos, demos_per_task=2, settings=SyntheticSettings(image_size=8, num_steps=10))
    return demos


def main(argv: list[str] | None = None) -> Result:
    """Run the benchmark; return (and print) its result."""
    args = parser(__doc__.splitlines()[0]).parse_args(argv)
    repeats = QUICK["repeats"] if args.quick else REPEATS
    folder = cache_dir(args)
    demos = demo_files(folder)
    from steering_core.synthetic.libero import DRAWER_CLOSE, DRAWER_OPEN

    filter_args = ["filter", "--input-dir", str(demos), "--output-dir", str(folder / "cli-startup-filtered"),
                   "--task", DRAWER_OPEN, "--task", DRAWER_CLOSE]
    cases = {
        "latent-steering --help": (["--help"], True),
        "latent-steering filter --help": (["filter", "--help"], True),
        "latent-steering filter (2 of 4 files)": (filter_args, True),
        "latent-steering manifest --help": (["manifest", "--help"], True),
        "latent-steering steer --help (needs torch)": (["steer", "--help"], False),
    }
    load = os.getloadavg()[0]
    base_wall, base_cpu = run_times([sys.executable, "-c", "pass"], repeats)
    rows, light = [], []
    for name, (cli_args, is_light) in cases.items():
        wall, cpu = run_times([*cli_command(), *cli_args], repeats)
        heavy = heavy_imports(cli_args)
        if is_light:
            light.append((cpu, wall, heavy))
        rows.append({"command": name, "CPU s": cpu, "wall s": wall, "CPU over baseline (s)": cpu - base_cpu,
                     "heavy libraries imported": ", ".join(heavy) or "none"})
    rows.append({"command": "python -c pass (baseline)", "CPU s": base_cpu, "wall s": base_wall,
                 "CPU over baseline (s)": 0.0, "heavy libraries imported": "none"})
    slowest_cpu, slowest_wall, _ = max(light)
    result = Result(
        name="cli_startup",
        title="7. CLI start-up (help and light commands)",
        command=command("cli_startup", args),
        measured=f"{slowest_cpu:.2f} s CPU, {slowest_wall:.2f} s wall (slowest light command)",
        baseline=f"{base_cpu:.3f} s CPU (python -c pass)",
        ratio=slowest_cpu / base_cpu,
        target=f"< {TARGET_SECONDS:g} s absolute",
        met=slowest_cpu < TARGET_SECONDS and not any(heavy for *_, heavy in light),
        table=rows,
        notes=[
            f"median of {repeats} fresh processes per command; the ratio is the slowest light command's CPU time "
            "over the baseline interpreter's.",
            f"load average at the start: {load:.1f} on {os.cpu_count()} cores; wall times grow with the load, "
            "CPU times much less.",
            "light commands must import none of torch, lerobot, transformers, prefect (last column).",
        ],
        checks={"heavy": {row["command"]: row["heavy libraries imported"] for row in rows}},
    )
    return finish(result, args)


if __name__ == "__main__":
    main()
