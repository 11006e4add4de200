"""Ctrl-C and SIGTERM for every command: the command unwinds (atomic writes remove their staging, complete outputs
stay, child processes are stopped, Prefect records its runs Crashed), then one line says what was interrupted and
that a rerun resumes, and the command exits 130 (SIGINT) or 143 (SIGTERM).

SIGTERM is raised as the same `KeyboardInterrupt` (`Interrupted`); inside a flow run Prefect raises its own
`TerminationSignal` first and sends SIGTERM again once its runs are recorded, which lands here. From the first
signal on, the console's log lines are held back (the crash reports of every run level, a server stopping): what
was running is gathered from them for the one line. A second signal stops the process at once.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

import typer

# Prefect's report of a run stopped by a signal (`prefect.states.exception_to_crashed_state`): SIGTERM inside a flow
# run reaches this module only once every run level has reported, so its reports mark the interruption too.
PREFECT_ABORTED = ("Execution was aborted by an interrupt signal", "Execution was aborted by a termination signal")
RERUN = "nothing half-written was kept; rerun the same command to resume"


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; `signum` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class _HeldBack(logging.Filter):
    """Console filter: from the interruption on, drops every record, noting the Prefect task runs reported stopped."""

    def __init__(self) -> None:
        super().__init__()
        self.signum: int | None = None
        self.stopped: list[str] = []
        self.handlers: list[logging.Handler] = []

    def attach(self) -> None:
        """Filter every console handler there is now (Prefect and uvicorn add their own after the command starts)."""
        for handler in _console_handlers():
            if handler not in self.handlers:
                handler.addFilter(self)
                self.handlers.append(handler)

    def reset(self) -> None:
        """Forget a previous command's interruption (tests run several commands in one process)."""
        self.signum, self.stopped = None, []
        for handler in self.handlers:
            handler.removeFilter(self)
        self.handlers = []

    def hold(self, signum: int) -> None:
        """Hold back the console's lines from now on: `signum` arrived."""
        if self.signum is None:
            self.signum = signum
            self.attach()

    def filter(self, record: logging.LogRecord) -> bool:
        aborted = any(text in str(record.msg) for text in PREFECT_ABORTED)
        if aborted:
            self.hold(signal.SIGINT if "interrupt" in str(record.msg) else signal.SIGTERM)
            name = getattr(record, "task_run_name", None)
            if name and name not in self.stopped:
                self.stopped.append(name)
        return self.signum is None


# the console's filter: `configure_logging` puts it on its handler, so that Prefect's reports are seen from the start
held_back = _HeldBack()


@contextlib.contextmanager
def interruptible(command: Callable[[], str]) -> Iterator[None]:
    """Run a command (named by `command()`) so that SIGINT and SIGTERM end it in one `interrupted: ...` line, exit
    128 + the signal."""
    held = held_back
    held.reset()

    received: list[int] = []

    def interrupt(signum: int, _frame: Any) -> None:
        if received:
            _exit_now(command(), signum)  # already unwinding from the first signal: stop now
        received.append(signum)
        held.hold(signum)
        raise Interrupted(signum)

    main = threading.current_thread() is threading.main_thread()  # signal handlers are the main thread's only
    previous = {signum: signal.signal(signum, interrupt) for signum in (signal.SIGINT, signal.SIGTERM) if main}
    try:
        yield
    except KeyboardInterrupt as err:
        signum = held.signum or getattr(err, "signum", signal.SIGINT)
        during = f" during {', '.join(held.stopped)}" if held.stopped else ""
        typer.secho(f"interrupted: {command()} stopped{during} by {signal.Signals(signum).name}; {RERUN}",
                    fg=typer.colors.YELLOW, err=True)
        raise typer.Exit(128 + signum) from None
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)  # the filter stays: what runs at exit (Prefect's server stop) is held back


def _console_handlers() -> list[logging.Handler]:
    """Return the stream handlers of every logger (the root's, and any a library such as Prefect set up)."""
    loggers = [logging.getLogger(), *(logger for logger in list(logging.Logger.manager.loggerDict.values())
                                      if isinstance(logger, logging.Logger))]
    return list({id(h): h for logger in loggers for h in logger.handlers
                 if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)}.values())


def _exit_now(command: str, signum: int) -> None:
    """End the process now, on a second signal: the staging a clean stop removes is removed by the next run."""
    sys.stderr.write(f"interrupted again: {command} stopped at once by {signal.Signals(signum).name}; its staging "
                     "is removed by the next run; rerun the same command to resume\n")
    sys.stderr.flush()
    os._exit(128 + signum)
