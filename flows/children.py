"""The parent's phases on workers: one child deployment run per target, or all in this process.

`run_phase` decides once for every phase that can run on workers (capture, SAE training, evaluation, rollouts):
with `orchestration.mode` `deployment` (or `auto` in a flow run started from a deployment) it starts one child
run per target not cached yet, otherwise it calls the phase's flow in this process.

A child run ends Crashed when its process died: its worker reports that, or, when the worker died with it
(a machine lost), the parent marks it Crashed once its heartbeats stopped for `orchestration.heartbeat_timeout_seconds`
while the server kept recording the parent's own (`flows.heartbeats`: a stalled server is not a dead machine); the
automation `latent-steering deploy` creates is the last resort for runs nobody watches (the parent itself). The
parent starts such a run again, at most `orchestration.resubmits` times; every child's tasks are cached and
capture keeps complete shards, so a new attempt redoes only what the dead one had not finished. A phase whose runs
are not all final after `orchestration.deadline_seconds` is cancelled and fails naming them; runs left unstarted
with no worker on their pool fail after `orchestration.worker_wait_seconds`, naming the pool.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any
from uuid import UUID

import httpx
from prefect import get_run_logger, runtime
from prefect.client.orchestration import get_client
from prefect.client.schemas.objects import FlowRun, WorkerStatus
from prefect.deployments import run_deployment
from prefect.states import Cancelled, Crashed

from flows.heartbeats import HeartbeatWatch, heartbeat_interval
from steering_core.config import RunConfig
from steering_core.config.sections import OrchestrationSection

REPORT_SECONDS = 60.0  # how often a waiting parent logs what it waits for


def orchestration_mode(config: RunConfig) -> str:
    """Return `deployment` or `local`: `auto` means deployments when this flow run came from a deployment."""
    mode = config.orchestration.mode
    if mode == "auto":
        return "deployment" if runtime.deployment.id else "local"
    return mode


def uncached(targets: Sequence[Any], cached: Callable[[Any], bool], what: str) -> list[Any]:
    """Return the targets whose child run would not be all `Cached` (not started: a process start costs seconds)."""
    wanted = [target for target in targets if not cached(target)]
    if len(wanted) < len(targets):
        get_run_logger().info("%d of %d %s run(s) cached: not started", len(targets) - len(wanted), len(targets), what)
    return wanted


def run_phase(config: RunConfig, config_path: str | Path, what: str, *, deployment: str,
              phase_flow: Callable[[str, list[Any]], Any], targets: Sequence[Sequence[Any]],
              name_of: Callable[[Sequence[Any]], str], cached: Callable[[Any], bool] | None = None) -> None:
    """Run the phase's `targets`: in this process as one run of `phase_flow(config_path, targets)`, or as one
    run of `deployment` per target (its `targets` parameter) left by `cached`, waiting for all (`run_children`)."""
    if orchestration_mode(config) == "local":
        phase_flow(str(config_path), list(targets))
        return
    wanted = list(targets) if cached is None else uncached(targets, cached, what)
    run_children(deployment, [Child(name_of(target), {"config_path": str(config_path), "targets": [list(target)]})
                              for target in wanted], what, config.orchestration)


@dataclasses.dataclass(frozen=True)
class Child:
    """One child run: its flow run name and the parameters of its deployment."""

    name: str
    parameters: dict[str, Any]


def run_children(deployment: str, children: Sequence[Child], what: str,
                 orchestration: OrchestrationSection) -> list[FlowRun]:
    """Start one run of `deployment` per child and wait until all completed; return them, in order.

    Crashed runs are started again (at most `orchestration.resubmits` times each); RuntimeError in one line
    naming the runs that did not complete, the pool nobody polls, or the runs past the phase's deadline.
    """
    logger = get_run_logger()
    if not children:
        return []
    runs = {child.name: _start(deployment, child) for child in children}
    attempts = dict.fromkeys(runs, 1)
    logger.info("started %d %s run(s) of %s; waiting", len(runs), what, deployment)
    began = time.monotonic()
    worker_check: float | None = began + orchestration.worker_wait_seconds
    next_report = began + REPORT_SECONDS
    watch = _watch(orchestration)
    next_watch = began + (watch.interval if watch else 0)
    finished: dict[str, FlowRun] = {}
    with get_client(sync_client=True) as client:
        while True:
            for child in children:
                if child.name in finished:
                    continue
                run = runs[child.name] = client.read_flow_run(runs[child.name].id)
                if run.state is None or not run.state.is_final():
                    continue
                if run.state.is_crashed() and attempts[child.name] <= orchestration.resubmits:
                    attempts[child.name] += 1
                    logger.warning("%s crashed (%s); starting it again, attempt %d of %d", child.name,
                                   run.state.message or "no message", attempts[child.name], orchestration.resubmits + 1)
                    runs[child.name] = _start(deployment, child)
                    worker_check = time.monotonic() + orchestration.worker_wait_seconds  # is anyone left to run it?
                else:
                    finished[child.name] = run
            pending = [runs[child.name] for child in children if child.name not in finished]
            if not pending:
                break
            now = time.monotonic()
            if watch is not None and now >= next_watch:
                _crash_dead(client, watch, pending)
                next_watch = now + watch.interval
            if worker_check is not None and now > worker_check:
                _fail_if_nobody_polls(client, pending, orchestration.worker_wait_seconds, what)
                worker_check = None  # a worker is there: wait as long as the runs take
            if now - began > orchestration.deadline_seconds:
                _cancel(client, pending, f"not finished after orchestration.deadline_seconds = "
                                         f"{orchestration.deadline_seconds:.0f} s")
                raise RuntimeError(f"{what} run(s) {describe(pending)} not finished after "
                                   f"{orchestration.deadline_seconds:.0f} s (orchestration.deadline_seconds): "
                                   "cancelled; re-run to resume (finished work is kept)")
            if now >= next_report:
                logger.info("waiting for %d %s run(s) of %s: %s", len(pending), what, deployment, describe(pending))
                next_report = now + REPORT_SECONDS
            time.sleep(orchestration.poll_seconds)
    failed = [run for run in finished.values() if run.state is None or not run.state.is_completed()]
    if failed:
        raise RuntimeError(f"{what} run(s) did not complete: {describe(failed)}; see them in the Prefect UI, fix the "
                           "cause and re-run (finished work is kept)")
    return [finished[child.name] for child in children]


def describe(runs: Sequence[FlowRun]) -> str:
    """Return `name (state), ...` of flow runs, e.g. `capture episodes 0-3 (Running)`."""
    return ", ".join(f"{run.name} ({run.state.name if run.state else 'no state'})" for run in runs)


def _start(deployment: str, child: Child) -> FlowRun:
    """Create one run of `deployment` for `child`, linked to the current flow run, without waiting."""
    return run_deployment(deployment, parameters=child.parameters, flow_run_name=child.name, timeout=0)


def _watch(orchestration: OrchestrationSection) -> HeartbeatWatch | None:
    """Return the heartbeat watch of this flow run's children (None outside a flow run)."""
    parent_id = runtime.flow_run.id
    if not parent_id:
        return None
    return HeartbeatWatch(UUID(str(parent_id)), orchestration.heartbeat_timeout_seconds, heartbeat_interval())


def _crash_dead(client: Any, watch: HeartbeatWatch, pending: Sequence[FlowRun]) -> None:
    """Mark Crashed the running runs of `pending` the watch judges dead (the next poll starts them again)."""
    running = [run for run in pending if run.state is not None and run.state.is_running()]
    try:
        dead = watch.dead(client, running) if running else []
    except httpx.HTTPError as error:  # a server that does not answer gives no evidence: judge at the next check
        get_run_logger().info("heartbeats not read (%s); the children are judged at the next check", error)
        return
    for run in dead:
        get_run_logger().warning("%s sent no heartbeat for %.0f s while this run's own were recorded: marking it "
                                 "Crashed", run.name, watch.window)
        client.set_flow_run_state(run.id, Crashed(message=f"no heartbeat for {watch.window:.0f} s while its parent's "
                                                          "were recorded: its process or machine died"), force=True)


def _cancel(client: Any, runs: Sequence[FlowRun], why: str) -> None:
    """Set `runs` Cancelled (forced: a run on a dead machine cannot acknowledge a cancellation)."""
    for run in runs:
        client.set_flow_run_state(run.id, Cancelled(message=why), force=True)


def _fail_if_nobody_polls(client: Any, pending: Sequence[FlowRun], waited: float, what: str) -> None:
    """Cancel `pending` and raise if none has started and their work pool has no online worker."""
    if any(run.state is None or not run.state.is_scheduled() for run in pending):
        return  # a worker picked one up
    pools = sorted({run.work_pool_name for run in pending if run.work_pool_name})
    online = [pool for pool in pools
              if any(worker.status == WorkerStatus.ONLINE for worker in client.read_workers_for_work_pool(pool))]
    if online:
        return
    _cancel(client, pending, f"no worker polled pool {', '.join(pools)}")
    raise RuntimeError(
        f"no worker is polling pool {', '.join(repr(p) for p in pools) or '(none)'}: {len(pending)} {what} run(s) "
        f"still scheduled after {waited:.0f} s were cancelled; start one with "
        f"`prefect worker start --pool {pools[0] if pools else 'gpu'}` and re-run (finished work is kept)"
    )
