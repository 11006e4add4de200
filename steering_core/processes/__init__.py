"""Child processes and Ctrl-C: a terminal sends SIGINT to its whole foreground process group, so every child a
command starts (frame workers and their forkserver, simulation workers, the embedded Prefect server) gets it too,
and would die mid-import with a traceback, or before its parent has told it what it needs (the server, its runs'
final states). Children ignore it instead (from exec on when started by the main thread, else from their first
import on); the process that started them stops them as it unwinds (the DataLoader's shutdown, `SimulationWorkers.close`, Prefect's server stop), and they die with it.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator

PR_SET_PDEATHSIG = 1


@contextlib.contextmanager
def children_ignore_ctrl_c() -> Iterator[None]:
    """Start processes in this block ignoring SIGINT from their first instruction on (an ignored signal stays
    ignored across exec), before any import of theirs can be cut short by a Ctrl-C.

    SIGINT is ignored process-wide meanwhile (only the main thread may set that; elsewhere the block changes
    nothing, and `ignore_ctrl_c` at the children's start is the shelter), and blocked in this thread, so a Ctrl-C
    arriving then is delivered here when the block ends, unless another thread took it first: then it is lost, and
    a second Ctrl-C stops the command."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def ignore_ctrl_c() -> None:
    """Ignore SIGINT in this (child) process: its parent handles Ctrl-C and stops it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def die_with_parent(signum: int = signal.SIGKILL) -> None:
    """Have this (child) process get `signum` when the thread that started it ends (Linux; elsewhere nothing)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signum)
