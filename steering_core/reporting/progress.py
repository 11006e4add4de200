"""Progress of a long step, for whoever watches: a bar on a terminal, log lines elsewhere, and a callback.

On a terminal (stderr is a TTY) a tqdm bar; otherwise (worker logs, CI, files) an INFO line at a steady
interval with what is done, the rate and the time left, and one line at the end (for steps that
lasted an interval or more; quick ones stay quiet). A `callback(done,
total)` sees every update (the Prefect tasks turn it into a progress artifact).
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import IO, Any

from tqdm import tqdm

ProgressCallback = Callable[[int, int], None]  # (done, total), in the step's unit

LOG_EVERY_SECONDS = 15.0

_logger = logging.getLogger(__name__)


class Progress:
    """Count a step's work; report it as a bar (TTY) or as log lines (elsewhere), and to `callback`.

    Use as a context manager: `with Progress(total, "capture", "frame") as bar: bar.update(16)`.
    """

    def __init__(
        self,
        total: int,
        desc: str,
        unit: str,
        *,
        callback: ProgressCallback | None = None,
        logger: logging.Logger | None = None,
        interval: float = LOG_EVERY_SECONDS,
        stream: IO[str] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total, self.desc, self.unit, self.done = total, desc, unit, 0
        self._callback, self._logger, self._interval, self._clock = callback, logger or _logger, interval, clock
        stream = stream if stream is not None else sys.stderr
        self._bar = tqdm(total=total, desc=desc, unit=unit, file=stream) if _is_tty(stream) else None
        self._start = self._last_log = clock()
        self._logged = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, kind: Any, *_: Any) -> None:
        self.close(failed=kind is not None)

    def update(self, amount: int = 1) -> None:
        """Count `amount` more units done."""
        self.done += amount
        if self._bar is not None:
            self._bar.update(amount)
        elif self._clock() - self._last_log >= self._interval and self.done < self.total:
            self._last_log, self._logged = self._clock(), True
            self._logger.info("%s", self.describe())
        if self._callback is not None:
            self._callback(self.done, self.total)

    def describe(self) -> str:
        """Return e.g. `capture: 480/1200 frames (40%), 35.2 frames/s, about 20 s left` (a rate below one a second
        per hour: `rollouts: 12/400 episodes (3%), 96 episodes/hour, about 4 h 2 min left`)."""
        elapsed = max(self._clock() - self._start, 1e-9)
        rate = self.done / elapsed
        percent = f" ({100 * self.done / self.total:.0f}%)" if self.total else ""
        left = f", about {_duration((self.total - self.done) / rate)} left" if rate > 0 and self.done < self.total else ""
        speed = f"{rate:.3g} {self.unit}s/s" if rate >= 1 or rate == 0 else f"{rate * 3600:.3g} {self.unit}s/hour"
        return f"{self.desc}: {self.done}/{self.total} {self.unit}s{percent}, {speed}{left}"

    def close(self, failed: bool = False) -> None:
        """Close the bar, or log the final count and time of a long step (not after a failure: the error says enough)."""
        elapsed = self._clock() - self._start
        if self._bar is not None:
            self._bar.close()
        elif not failed and (self._logged or elapsed >= self._interval):
            self._logger.info("%s: %d %ss in %s", self.desc, self.done, self.unit, _duration(elapsed))


def _is_tty(stream: IO[str]) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # closed or replaced streams
        return False


def _duration(seconds: float) -> str:
    """Return `42 s`, `3 min 5 s` or `2 h 4 min`."""
    seconds = round(seconds)
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60} min"
