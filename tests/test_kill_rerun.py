"""kill -9 in the middle of a step, then the same command again: the output holds the bytes of an uninterrupted run.

Each step runs from the finished tiny run's inputs into a fresh folder: once uninterrupted (the reference),
then, in the same place, as a process killed with SIGKILL once half as many files as the reference holds
exist (staging files included), then again to completion. Every file of the output (LeRobot's `meta/stats.json` included) must be byte-identical to the
reference, and no staging folder, temporary file or lock may be left beside it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers_attack import good
from typer.testing import CliRunner

from latent_steering_cli import app

pytestmark = pytest.mark.slow

LATENT_STEERING = str(Path(sys.executable).parent / "latent-steering")  # the console script of this venv
OUTPUTS = {"convert": "dataset", "capture": "run", "slice": "slices", "steer": "steering", "evaluate": "eval"}


def files(folder: Path) -> dict[str, bytes]:
    """Every file under `folder`, by relative path."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def run_to_completion(argv: list[str]) -> None:
    result = CliRunner().invoke(app, argv)
    assert result.exit_code == 0, (argv[0], result.output, result.exception)


def kill_when_writing(argv: list[str], out: Path, count: int, timeout: float = 300.0) -> bool:
    """Start the step as a process and SIGKILL it once `out` holds `count` files; return whether it was killed
    before it finished by itself."""
    process = subprocess.Popen([LATENT_STEERING, *argv], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    deadline = time.monotonic() + timeout
    while process.poll() is None and time.monotonic() < deadline:
        if sum(path.is_file() for path in out.rglob("*")) >= count:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            return True
        time.sleep(0.01)
    process.wait(timeout=10)
    return False


@pytest.mark.timeout(900)
@pytest.mark.parametrize("step", list(OUTPUTS))
def test_a_killed_step_rerun_writes_the_uninterrupted_bytes(attack_world, tmp_path, step):
    work = tmp_path / "work"
    work.mkdir()
    argv = [step, *map(str, good(attack_world, work)[step])]
    output = work / OUTPUTS[step]
    run_to_completion(argv)
    reference = files(work)
    shutil.rmtree(work)
    work.mkdir()

    killed = kill_when_writing(argv, work, max(1, len(reference) // 2))
    run_to_completion(argv)
    assert killed, f"{step} finished before anything was written: nothing was interrupted"
    assert files(work) == reference
    assert output.exists()
