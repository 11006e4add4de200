"""Another process holding an output lock, and a step started beside it: for the tests of waiting and skipping."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any


def python(code: str, *args: str) -> subprocess.Popen:
    """Return a Python process running `code` with `args`, its stdin and stdout pipes of text."""
    return subprocess.Popen([sys.executable, "-c", code, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def hold_output_lock(output) -> subprocess.Popen:
    """Return a process that holds `locks.output_lock(output)` until it reads a line (it holds it on return)."""
    holder = python("import sys; from steering_core.remote.locks import output_lock\n"
                    "with output_lock(sys.argv[1]):\n    print('locked', flush=True); sys.stdin.readline()", str(output))
    assert holder.stdout.readline().strip() == "locked"
    return holder


def start_waiting(step: Callable[[], Any], seconds: float = 3) -> tuple[threading.Thread, dict[str, Any]]:
    """Run `step` in a thread; return it (still running after `seconds`) and the dict its result lands in."""
    outcome: dict[str, Any] = {}
    worker = threading.Thread(target=lambda: outcome.update(result=step()))
    worker.start()
    worker.join(timeout=seconds)
    assert worker.is_alive(), "the step did not wait for the lock"
    return worker, outcome
