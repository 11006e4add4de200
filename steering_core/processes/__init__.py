"""Child processes and Ctrl-C: a terminal sends SIGINT to its whole foreground process group, so every child a
command starts (frame workers and their forkserver, simulation workers, the embedded Prefect server) gets it too,
and would die mid-import with a traceback, or before its parent has told it what it needs (the server, its runs'
final states). Children ignore it instead, from their first import on; the process that started them stops them
as it unwinds (the DataLoader's shutdown, `SimulationWorkers.close`, Prefect's server stop), and they die with it.
"""

from __future__ import annotations

import signal
import sys

PR_SET_PDEATHSIG = 1


def ignore_ctrl_c() -> None:
    """Ignore SIGINT in this (child) process: its parent handles Ctrl-C and stops it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def die_with_parent(signum: int = signal.SIGKILL) -> None:
    """Have this (child) process get `signum` when the thread that started it ends (Linux; elsewhere nothing)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signum)
