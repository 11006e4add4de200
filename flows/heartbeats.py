"""Which child runs are dead: their heartbeats stopped while the server kept recording the parent's own.

A flow run of the deployments sends a heartbeat event every `interval` seconds (PREFECT_FLOWS_HEARTBEAT_FREQUENCY,
30 in prefect.yaml). One run's silence alone does not tell a dead machine from a stalled server: a server whose
database is locked records nobody's heartbeats. The parent knows one run is alive, itself, so its own heartbeats
are the evidence that the server records heartbeats at all. A child counts as dead only when it has been silent
for `window` seconds of *healthy* time: time in which the server recorded the parent's heartbeats no more than two
intervals apart, up to now. A stall voids the evidence gathered so far; silence counts again from its end.

A child is judged only once it sent a heartbeat: one that never did (a worker that died while it was Pending) is
left to the phase's deadline, as is everything when the parent itself sends no heartbeat.
"""

from __future__ import annotations

import datetime
from collections.abc import Iterator, Mapping, Sequence
from typing import Any
from uuid import UUID

from prefect.client.schemas.objects import FlowRun
from prefect.events.filters import EventFilter, EventNameFilter, EventOccurredFilter, EventResourceFilter
from prefect.settings import PREFECT_FLOWS_HEARTBEAT_FREQUENCY
from prefect.types._datetime import now as utc_now

HEARTBEAT = "prefect.flow-run.heartbeat"
MINIMUM_INTERVAL = 30.0  # Prefect sends heartbeats at most this often, whatever the setting says
PAGE = 50  # events per page: the server's maximum (the client's default of 100 is refused)
GAP = 2  # intervals between two recorded heartbeats of the parent beyond which the server was not recording


def heartbeat_interval() -> float:
    """Seconds between two heartbeats of a flow run of this process's settings."""
    return max(float(PREFECT_FLOWS_HEARTBEAT_FREQUENCY.value() or MINIMUM_INTERVAL), MINIMUM_INTERVAL)


def healthy_since(own: Sequence[datetime.datetime], now: datetime.datetime, interval: float
                  ) -> datetime.datetime | None:
    """Return the start of the latest stretch in which the server recorded the parent's heartbeats `own` no more
    than GAP intervals apart, lasting up to `now`; None when the latest recorded one is older than that."""
    gap = datetime.timedelta(seconds=GAP * interval)
    beats = sorted(own)
    if not beats or now - beats[-1] > gap:
        return None
    start = beats[-1]
    for earlier in reversed(beats[:-1]):
        if start - earlier > gap:
            break
        start = earlier
    return start


def dead(last: Mapping[UUID, datetime.datetime], own: Sequence[datetime.datetime], now: datetime.datetime,
         window: float, interval: float) -> list[UUID]:
    """Return the runs of `last` (each with its latest recorded heartbeat) silent for `window` seconds of time in
    which the server demonstrably recorded the parent's heartbeats `own` (`healthy_since`)."""
    since = healthy_since(own, now, interval)
    if since is None:
        return []  # the server does not record even this live process's heartbeats: a stall, not a death
    return [run for run, beat in last.items() if (now - max(beat, since)).total_seconds() >= window]


class HeartbeatWatch:
    """The latest heartbeat of every child run seen so far, and the parent's recent ones, read from the server."""

    def __init__(self, parent_id: UUID, window: float, interval: float):
        self.parent_id, self.window, self.interval = parent_id, window, interval
        self.last: dict[UUID, datetime.datetime] = {}

    def dead(self, client: Any, running: Sequence[FlowRun]) -> list[FlowRun]:
        """Return the runs of `running` that `dead` judges so, reading the heartbeats recorded in the last window."""
        now = utc_now("UTC")
        horizon = now - datetime.timedelta(seconds=self.window + GAP * self.interval)
        own: list[datetime.datetime] = []
        for run_id, occurred in _heartbeats(client, [self.parent_id, *(run.id for run in running)], horizon, now):
            if run_id == self.parent_id:
                own.append(occurred)
            else:
                self.last[run_id] = max(occurred, self.last.get(run_id, occurred))
        judged = set(dead({run.id: self.last[run.id] for run in running if run.id in self.last}, own, now,
                          self.window, self.interval))
        return [run for run in running if run.id in judged]


def _heartbeats(client: Any, run_ids: Sequence[UUID], since: datetime.datetime, until: datetime.datetime
                ) -> Iterator[tuple[UUID, datetime.datetime]]:
    """Yield (flow run id, when) of every heartbeat of `run_ids` the server recorded between `since` and `until`."""
    resources = [f"prefect.flow-run.{run_id}" for run_id in run_ids]
    page = client.read_events(EventFilter(occurred=EventOccurredFilter(since=since, until=until),
                                          event=EventNameFilter(name=[HEARTBEAT]),
                                          resource=EventResourceFilter(id=resources)), limit=PAGE)
    while page is not None:
        for event in page.events:
            yield UUID(event.resource.id.removeprefix("prefect.flow-run.")), event.occurred
        page = client.read_events_page(str(page.next_page)) if page.next_page else None
