"""What a pipeline run did, read back from Prefect's API: one row per task run (step, pair, layer, state, time, output).

Prefect records task run states from events, asynchronously: right after a flow returns, a task may
still read as Running. `task_runs_of` polls until every state is final, or gives up after a while
and reports what it has.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from uuid import UUID

from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import (
    FlowRunFilter,
    FlowRunFilterId,
    FlowRunFilterParentFlowRunId,
)
from prefect.client.schemas.objects import TaskRun
from prefect.client.schemas.sorting import TaskRunSort
from prefect.results import ResultRecord
from prefect.tasks import Task

from steering_core.config import RunConfig
from steering_core.reporting.tables import text_table
from steering_core.storage.mirrors import is_url
from tasks import capture, data, preflight, report, rollout, sae
from tasks.cache_records import OUTPUTS, cache_store, read_record_bytes, record_location

SETTLE_SECONDS = 30.0
PAGE = 200  # task runs per API call (the server's default limit)
STATES = {"Completed": "ran", "Cached": "cached", "Failed": "failed", "Crashed": "failed", "TimedOut": "failed"}
_LAYER = re.compile(r"\b(expert )?layer (\d+)\b")  # `expert layer 2`: the action expert's
_EPISODES = re.compile(r"\b(?:decision )?episodes \d+-\d+\b")
_SIDES = ("positive", "negative")


@dataclass(frozen=True)
class TaskRow:
    """One task run as the closing table shows it."""

    step: str         # the task's name, e.g. slice-concepts
    pair: str         # the concept pair (and side), the episodes of a capture, or "-"
    layer: str        # the layer, or "-"
    state: str        # ran, cached, failed (or Prefect's state name when not final)
    seconds: float
    attempts: int
    output: str       # the file, or the folder holding the files, the task wrote


def step_names() -> dict[str, str]:
    """Return Prefect task key -> task name (e.g. `slice-concepts`) for every task of the pipeline."""
    return {obj.task_key: obj.name for module in (preflight, data, capture, sae, report, rollout)
            for obj in vars(module).values() if isinstance(obj, Task)}


def task_runs_of(flow_run_id: UUID, settle_seconds: float = SETTLE_SECONDS) -> list[TaskRun]:
    """Return the task runs of a flow run and its subflows (not the subflows' stand-ins), by start time."""
    deadline = time.monotonic() + settle_seconds
    with get_client(sync_client=True) as client:
        while True:
            flow_runs, frontier = [], [flow_run_id]
            while frontier:
                flow_runs += client.read_flow_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=frontier)))
                frontier = [r.id for r in client.read_flow_runs(flow_run_filter=FlowRunFilter(
                    parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=frontier)))]
            stand_ins = {r.parent_task_run_id for r in flow_runs}
            runs = [t for t in _all_task_runs(client, [r.id for r in flow_runs]) if t.id not in stand_ins]
            if all(t.state is not None and t.state.is_final() for t in runs) or time.monotonic() > deadline:
                break
            time.sleep(0.5)
    return sorted(runs, key=lambda t: (t.start_time or t.expected_start_time or t.created, t.name))


def _all_task_runs(client: Any, flow_run_ids: list[UUID]) -> list[TaskRun]:
    """Return every task run of the flow runs, page by page (the API returns at most a page per call)."""
    runs: list[TaskRun] = []
    while True:
        page = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=flow_run_ids)),
                                     sort=TaskRunSort.ID_DESC, offset=len(runs), limit=PAGE)
        runs += page
        if len(page) < PAGE:
            return runs


def task_rows(runs: list[TaskRun], config: RunConfig) -> list[TaskRow]:
    """Return the closing table's rows for `runs` of a pipeline run with `config`."""
    names = step_names()
    pairs = [pair.name for pair in config.pairs]
    rows = []
    for run in runs:
        state = run.state.name if run.state is not None else "Pending"
        rows.append(TaskRow(
            step=names.get(run.task_key, run.task_key.rsplit("-", 1)[0]),
            pair=_pair(run.name, pairs),
            layer=("".join(match.groups("")) if (match := _LAYER.search(run.name)) else "-"),
            state=STATES.get(state, state.lower()),
            seconds=run.total_run_time.total_seconds(),
            attempts=max(run.run_count, 1),
            output=_output(run, config),
        ))
    return rows


def format_task_rows(rows: list[TaskRow], output_root: Path) -> str:
    """Return the rows as an aligned table; outputs under `output_root` are shown relative to it."""
    counts = {state: sum(row.state == state for row in rows) for state in dict.fromkeys(r.state for r in rows)}
    table = text_table(
        ("step", "pair", "layer", "state", "time", f"output (under {output_root})"),
        [(row.step, row.pair, row.layer,
          row.state + (f" ({row.attempts} attempts)" if row.attempts > 1 else ""),
          f"{row.seconds:.1f} s", _relative(row.output, output_root)) for row in rows],
    )
    return f"{table}\n{len(rows)} task runs: " + ", ".join(f"{n} {state}" for state, n in counts.items())


def _pair(name: str, pairs: list[str]) -> str:
    words = name.split()
    pair = next((p for p in pairs if p in words), None)
    if pair is None:
        match = _EPISODES.search(name)
        return match.group(0) if match else "-"
    side = next((s for s in _SIDES if s in words), None)
    return f"{pair} {side}" if side else pair


def _output(run: TaskRun, config: RunConfig) -> str:
    """Return the single file a task wrote, or the deepest folder holding all of them; "-" when unknown."""
    outputs = _summary(run, config).get(OUTPUTS) or []
    if not outputs:
        return "-"
    if len(outputs) == 1:
        return str(outputs[0])
    common = Path(outputs[0]).parent
    while not all(Path(o).is_relative_to(common) for o in outputs):
        common = common.parent
    return f"{common}/"


def _summary(run: TaskRun, config: RunConfig) -> dict[str, Any]:
    """Return the JSON summary a task returned (read from its result record beside the outputs), or {}."""
    data = run.state.data if run.state is not None else None
    key = data.get("storage_key") if isinstance(data, dict) else getattr(data, "storage_key", None)
    if not key:
        return {}
    location = key if is_url(key) or Path(key).is_absolute() else record_location(cache_store(config.output_root), key)
    try:
        result = ResultRecord.deserialize(read_record_bytes(location) or b"").result
    except (OSError, ValueError):
        return {}
    return result if isinstance(result, dict) else {}


def _relative(path: str, root: Path) -> str:
    if path == "-":
        return path
    try:
        return str(Path(path).relative_to(root)) + ("/" if path.endswith("/") else "")
    except ValueError:
        return path
