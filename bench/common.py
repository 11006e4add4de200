"""Shared pieces of the benchmarks: environment, flags, timing, memory, child processes and results.

Every benchmark is a standalone module (`uv run python -m bench.<name>`) with its settings at the top,
synthetic inputs it generates itself, and a baseline measured in the same run. It returns a `Result`,
prints it, and with `--json` writes it for `bench.run_all`, which rewrites BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime as dt
import importlib.metadata
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

# Everything is generated locally: never reach the model hub, and keep the datasets library's Arrow
# cache beside the benchmark inputs instead of in the home folder. Set before lerobot is imported.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

import torch  # noqa: E402  (after the environment above)

REPO_ROOT = Path(__file__).resolve().parent.parent
CACHE_ENV = "LATENT_STEERING_BENCH_CACHE"
DEFAULT_CACHE = Path(tempfile.gettempdir()) / "latent-steering-bench"
VERSIONED_PACKAGES = ("torch", "transformers", "lerobot", "prefect", "numpy", "safetensors", "datasets")


@dataclasses.dataclass
class Result:
    """One benchmark's outcome: a headline ratio against its target, a table, and how to reproduce it."""

    name: str
    title: str
    command: str  # reproduces every row of `table`
    measured: str  # our side of the headline, with units
    baseline: str  # the baseline's side, with units
    ratio: float  # the headline ratio, read against `target`
    target: str  # e.g. ">= 2.5x"
    met: bool
    table: list[dict[str, Any]]
    notes: list[str] = dataclasses.field(default_factory=list)
    checks: dict[str, Any] = dataclasses.field(default_factory=dict)  # correctness facts, e.g. ours == seed

    def to_json(self) -> dict[str, Any]:
        """Return the result as JSON data."""
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, payload: dict[str, Any]) -> Result:
        """Return a result read back from `to_json` data."""
        return cls(**payload)

    def report(self) -> str:
        """Return a plain-text report: headline, table and notes."""
        verdict = "met" if self.met else "MISSED"
        lines = [
            f"== {self.title}",
            f"ours {self.measured} vs baseline {self.baseline}: {self.ratio:.2f}x (target {self.target}: {verdict})",
            *markdown_table(self.table),
            *(f"note: {note}" for note in self.notes),
        ]
        return "\n".join(lines)


def parser(description: str) -> argparse.ArgumentParser:
    """Return an argument parser with the flags every benchmark takes."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    parser.add_argument("--quick", action="store_true", help="tiny sizes that keep the script working")
    parser.add_argument(
        "--cache-dir", type=Path, default=None, help=f"generated inputs (default ${CACHE_ENV} or {DEFAULT_CACHE})"
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the result here as JSON")
    return parser


def cache_dir(args: argparse.Namespace) -> Path:
    """Return the folder of generated inputs: --cache-dir, else $LATENT_STEERING_BENCH_CACHE, else a temp folder."""
    folder = args.cache_dir or Path(os.environ.get(CACHE_ENV, DEFAULT_CACHE))
    folder.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("HF_DATASETS_CACHE", str(folder / "hf-datasets"))
    return folder


def command(module: str, args: argparse.Namespace, *extra: str) -> str:
    """Return the command line that reproduces a benchmark run with these flags."""
    flags = [f"--device {args.device}"] if args.device != "cpu" else []
    flags += ["--quick"] if args.quick else []
    return " ".join(["uv run python -m", f"bench.{module}", *flags, *extra])


def finish(result: Result, args: argparse.Namespace) -> Result:
    """Print the result, write it as JSON when asked, and return it."""
    print(result.report(), flush=True)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result.to_json(), indent=2) + "\n", encoding="utf-8")
    return result


# ----------------------------------------------------------------------------- timing


def synchronize(device: torch.device) -> None:
    """Wait for queued GPU work, so a clock read after it measures the work itself."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], Any], device: torch.device) -> tuple[Any, float]:
    """Return fn()'s result and its wall time in seconds, synchronised on CUDA."""
    synchronize(device)
    start = time.perf_counter()
    result = fn()
    synchronize(device)
    return result, time.perf_counter() - start


def repeat_timed(fn: Callable[[], Any], device: torch.device, *, warmup: int, repeats: int) -> list[float]:
    """Return the wall times of `repeats` calls of fn after `warmup` untimed ones."""
    for _ in range(warmup):
        timed(fn, device)
    return [timed(fn, device)[1] for _ in range(repeats)]


def median(values: Sequence[float]) -> float:
    """Return the median of a non-empty sequence."""
    return statistics.median(values)


# ----------------------------------------------------------------------------- memory


def _status_kib(field: str) -> int:
    """Return one `/proc/self/status` field in KiB (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field} line; peak memory needs Linux")


def rss_mib() -> float:
    """Return this process's resident memory now, in MiB."""
    return _status_kib("VmRSS") / 1024


def peak_rss_mib() -> float:
    """Return this process's peak resident memory so far (VmHWM), in MiB."""
    return _status_kib("VmHWM") / 1024


def session_processes(sid: int) -> list[int]:
    """Return the running processes (zombies excluded) of session `sid` (a child started with a session of its
    own: its whole process tree)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError, ValueError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[3]) == sid and fields[0] != "Z":
                found.append(int(stat.parent.name))
    return found


def rss_bytes(pid: int) -> int:
    """Return a process's resident memory in bytes (0 once it has ended)."""
    with contextlib.suppress(OSError, IndexError, ValueError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


def run_child(module: str, argv: Sequence[str], *, env: dict[str, str] | None = None) -> dict[str, Any]:
    """Run `python -m bench.<module> *argv` in a fresh process and return the JSON object it printed last.

    A fresh process per measurement keeps one size's memory out of the next one's peak.
    """
    environment = {**os.environ, **(env or {})}
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), environment.get("PYTHONPATH")]))
    done = subprocess.run(
        [sys.executable, "-m", f"bench.{module}", *argv],
        cwd=REPO_ROOT,
        env=environment,
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise RuntimeError(f"bench.{module} {' '.join(argv)} failed (exit {done.returncode}):\n{done.stderr[-4000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def print_child_result(payload: dict[str, Any]) -> None:
    """Print a child measurement as the single JSON line `run_child` reads."""
    print(json.dumps(payload), flush=True)


# ----------------------------------------------------------------------------- reporting


def machine() -> dict[str, str]:
    """Return what the numbers depend on: CPU or GPU, cores, memory, Python and package versions, commit, date."""
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        lines = cpuinfo.read_text().splitlines()
        names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
        cpu = names[0] if names else cpu
    memory = ""
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        total_kib = int(meminfo.read_text().split("MemTotal:")[1].split()[0])
        memory = f"{total_kib / 1024**2:.1f} GiB"
    info = {
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": f"{cpu}, {os.cpu_count()} logical cores, torch uses {torch.get_num_threads()} threads",
        "memory": memory,
        "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none",
        "os": platform.platform(),
        "python": platform.python_version(),
    }
    for package in VERSIONED_PACKAGES:
        try:
            info[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            info[package] = "not installed"
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True)
        info["commit"] = commit.stdout.strip() or "unknown"
    except OSError:
        info["commit"] = "unknown"
    return info


def markdown_table(rows: list[dict[str, Any]]) -> list[str]:
    """Return the lines of a markdown table whose columns are the keys of the first row."""
    if not rows:
        return []
    columns = list(rows[0])
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    lines += ["| " + " | ".join(_cell(row.get(column, "")) for column in columns) + " |" for row in rows]
    return lines


def _cell(value: Any) -> str:
    """Return a table cell: floats with 3 significant digits (or fewer decimals when large)."""
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) >= 1000 else f"{value:.3g}"
    return str(value)


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block with torch on `count` intra-op threads and put the count back after: a benchmark run in-process
    (as the tests run them) must not change the float32 bits of what runs after it in that process."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)
