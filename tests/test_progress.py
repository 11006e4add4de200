"""Progress: log lines at a steady interval off a terminal, a bar on one, and every update to the callback."""

from __future__ import annotations

import io
import logging

import pytest

from steering_core.reporting.progress import Progress


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class FakeTTY(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_off_a_terminal_logs_done_rate_and_time_left_at_the_interval(caplog):
    clock, calls = FakeClock(), []
    caplog.set_level(logging.INFO, logger="steering_core.reporting.progress")
    with Progress(100, "capture", "frame", callback=lambda d, t: calls.append((d, t)), interval=10.0,
                  stream=io.StringIO(), clock=clock) as bar:
        for _ in range(10):  # 10 frames every 4 s: 2.5 frames/s
            clock.now += 4.0
            bar.update(10)
    lines = [r.getMessage() for r in caplog.records]
    # logged after 12 s (30 frames), 24 s (60), 36 s (90); then the closing line at 40 s
    assert lines == [
        "capture: 30/100 frames (30%), 2.5 frames/s, about 28 s left",
        "capture: 60/100 frames (60%), 2.5 frames/s, about 16 s left",
        "capture: 90/100 frames (90%), 2.5 frames/s, about 4 s left",
        "capture: 100 frames in 40 s",
    ]
    assert calls == [(10 * i, 100) for i in range(1, 11)]


def test_a_quick_step_logs_nothing(caplog):
    clock = FakeClock()
    caplog.set_level(logging.INFO, logger="steering_core.reporting.progress")
    with Progress(3, "encode", "row", interval=10.0, stream=io.StringIO(), clock=clock) as bar:
        clock.now += 9.0
        bar.update(3)
    assert caplog.records == []


def test_a_failed_step_logs_no_closing_line(caplog):
    clock = FakeClock()
    caplog.set_level(logging.INFO, logger="steering_core.reporting.progress")
    with pytest.raises(RuntimeError), Progress(5, "slice", "shard", interval=10.0, stream=io.StringIO(),
                                               clock=clock) as bar:
        clock.now += 11.0
        bar.update(1)  # logged: the interval has passed
        clock.now += 11.0
        raise RuntimeError("boom")
    assert [r.getMessage() for r in caplog.records] == ["slice: 1/5 shards (20%), 327 shards/hour, about 44 s left"]  # 1 shard in 11 s = 327/hour


def test_on_a_terminal_a_bar_and_no_log_lines(caplog):
    stream, clock = FakeTTY(), FakeClock()
    caplog.set_level(logging.INFO, logger="steering_core.reporting.progress")
    with Progress(4, "encode", "row", stream=stream, interval=0.0, clock=clock) as bar:
        for _ in range(4):
            clock.now += 100.0
            bar.update(1)
    assert caplog.records == []
    assert "encode: 100%" in stream.getvalue() and "4/4" in stream.getvalue()


@pytest.mark.parametrize(("seconds", "text"), [(42, "42 s"), (185, "3 min 5 s"), (7440, "2 h 4 min")])
def test_durations_read_as_time(seconds, text):
    clock = FakeClock()
    progress = Progress(2, "x", "row", stream=io.StringIO(), clock=clock)
    clock.now += seconds
    progress.update(1)  # half done: as much time left as spent
    assert progress.describe().endswith(f"about {text} left")
