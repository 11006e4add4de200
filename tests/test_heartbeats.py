"""Dead-child detection (`flows.heartbeats`): silence counts only while the server records the parent's heartbeats.

The rule's table runs on timestamps alone; the watch reads heartbeat events sent to the session's Prefect server
(with their `occurred` set, so a stall of minutes needs no minutes of waiting).
"""

from __future__ import annotations

import datetime
import time
import uuid
from types import SimpleNamespace

import pytest
from prefect.client.orchestration import get_client
from prefect.events import emit_event
from prefect.events.filters import EventFilter, EventNameFilter, EventResourceFilter
from prefect.events.worker import EventsWorker

from flows.heartbeats import HEARTBEAT, PAGE, HeartbeatWatch, dead

NOW = datetime.datetime(2026, 1, 1, 12, tzinfo=datetime.UTC)
INTERVAL, WINDOW = 30.0, 300.0
LIVE, KILLED = uuid.uuid4(), uuid.uuid4()


def beats(first: float, last: float, step: float = INTERVAL) -> list[datetime.datetime]:
    """Heartbeats every `step` seconds from `first` to `last` seconds relative to NOW (both included)."""
    count = int((last - first) // step)
    return [NOW + datetime.timedelta(seconds=first + i * step) for i in range(count + 1)]


# case -> (the parent's recorded heartbeats, each child's latest recorded one (s before NOW), the runs judged dead)
CASES = {
    # the server stalls (a locked database) for twice the window: nobody's heartbeats are recorded, nobody is dead
    "server stalled past the window": (beats(-900, -600), {LIVE: -600, KILLED: -600}, []),
    # ...and recovers: the live child's heartbeats come again, the parent's for less than a window: still nobody
    "stall over, the parent recorded again for less than a window": (
        beats(-900, -600) + beats(-120, 0), {LIVE: -10, KILLED: -600}, []),
    # silence counts from the end of the stall: a whole window of recorded parent heartbeats proves the child dead
    "stall over, the parent recorded again for a window": (
        beats(-900, -600) + beats(-330, 0), {LIVE: -10, KILLED: -600}, [KILLED]),
    # a machine killed while the server is healthy: its child is dead once silent for the window
    "child killed, server healthy": (beats(-900, 0), {LIVE: -20, KILLED: -WINDOW}, [KILLED]),
    "child silent for less than the window": (beats(-900, 0), {LIVE: -20, KILLED: -WINDOW + 1}, []),
    # the parent's latest recorded heartbeat is more than two intervals old: the server stalls now
    "stalling now": (beats(-900, -61), {LIVE: -400, KILLED: -400}, []),
    # one gap of more than two intervals in the parent's heartbeats voids the silence before it
    "a short stall inside the window": (
        beats(-900, -200) + beats(-130, 0), {LIVE: -20, KILLED: -250}, []),
    "the parent sends no heartbeat": ([], {LIVE: -900, KILLED: -900}, []),
}


@pytest.mark.parametrize("case", CASES)
def test_only_silence_while_the_parent_is_recorded_counts(case):
    own, last, expected = CASES[case]
    latest = {run: NOW + datetime.timedelta(seconds=seconds) for run, seconds in last.items()}
    assert dead(latest, own, NOW, WINDOW, INTERVAL) == expected


def send_heartbeats(run_id: uuid.UUID, seconds_ago: list[float]) -> None:
    """Send heartbeat events of flow run `run_id` that occurred `seconds_ago` seconds before now."""
    now = datetime.datetime.now(datetime.UTC)
    for ago in seconds_ago:
        emit_event(HEARTBEAT, resource={"prefect.resource.id": f"prefect.flow-run.{run_id}"},
                   occurred=now - datetime.timedelta(seconds=ago))


def recorded(run_ids: list[uuid.UUID], count: int) -> None:
    """Wait until the server recorded `count` heartbeats of `run_ids` (it persists events in batches)."""
    EventsWorker.drain_all()
    deadline = time.monotonic() + 120  # generous: persisting is a flush every few seconds on an idle machine
    with get_client(sync_client=True) as client:
        while (found := client.read_events(EventFilter(
                event=EventNameFilter(name=[HEARTBEAT]),
                resource=EventResourceFilter(id=[f"prefect.flow-run.{r}" for r in run_ids])), limit=PAGE).total) < count:
            assert time.monotonic() < deadline, f"{found} of {count} heartbeats recorded"
            time.sleep(0.5)


@pytest.mark.timeout(600)  # generous: the session server may start first, beside other jobs
def test_the_watch_judges_from_the_heartbeats_the_server_recorded(prefect_server):
    """A stalled server (every run silent past the window, the parent too) crashes nothing; a child silent for the
    window while the parent's heartbeats were recorded is dead, its live sibling is not. Window 60 s, interval 10 s:
    the children's last heartbeats (70 s ago) lie within what the watch reads, so it judges them."""
    stalled = [uuid.uuid4() for _ in range(3)]  # parent, child, child: all silent for the last 70 s
    healthy = [uuid.uuid4() for _ in range(3)]  # parent, live child, killed child
    for run in stalled:
        send_heartbeats(run, [80, 70])
    send_heartbeats(healthy[0], list(range(80, -1, -10)))
    send_heartbeats(healthy[1], list(range(80, 0, -10)))
    send_heartbeats(healthy[2], [80, 70])
    recorded(stalled + healthy, 3 * 2 + 9 + 8 + 2)
    runs = [SimpleNamespace(id=run_id) for run_id in healthy[1:]]
    with get_client(sync_client=True) as client:
        assert HeartbeatWatch(stalled[0], 60, 10).dead(client, [SimpleNamespace(id=r) for r in stalled[1:]]) == []
        assert HeartbeatWatch(healthy[0], 60, 10).dead(client, runs) == [runs[1]]
