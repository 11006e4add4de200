"""The parent's child runs (`flows.children`) on the session's Prefect test server, with no worker at all."""

from __future__ import annotations

import threading
import time

import pytest
from prefect import flow
from prefect.client.orchestration import get_client
from prefect.client.schemas.actions import WorkPoolCreate
from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
from prefect.events import emit_event
from prefect.exceptions import ObjectAlreadyExists
from prefect.states import Running

from flows import children
from flows.children import Child, run_children
from flows.heartbeats import HEARTBEAT
from steering_core.config.sections import OrchestrationSection


@pytest.fixture(scope="module")
def idle_deployment(prefect_server) -> tuple[str, object]:
    """A deployment on a pool nobody polls: its runs stay Scheduled."""
    with get_client(sync_client=True) as client:
        try:
            client.create_work_pool(WorkPoolCreate(name="nobody", type="process"))
        except ObjectAlreadyExists:
            pass
        deployment_id = client.create_deployment(flow_id=client.create_flow_from_name("idle-child"), name="idle",
                                                 work_pool_name="nobody", entrypoint="idle.py:child")
    return "idle-child/idle", deployment_id


@flow
def parent(deployment: str, orchestration: OrchestrationSection) -> None:
    run_children(deployment, [Child("child a", {}), Child("child b", {})], "test", orchestration)


def child_states(deployment_id) -> list[str]:
    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment_id])))
    return [run.state.name for run in runs]


@pytest.mark.timeout(180)
def test_children_past_the_deadline_are_cancelled_and_named_in_one_line(idle_deployment):
    deployment, deployment_id = idle_deployment
    before = len(child_states(deployment_id))
    with pytest.raises(RuntimeError) as err:
        parent(deployment, OrchestrationSection(poll_seconds=0.2, deadline_seconds=2))
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith("test run(s) child a (Scheduled), child b (Scheduled) not finished after 2 s "
                              "(orchestration.deadline_seconds)"), message
    states = child_states(deployment_id)
    assert len(states) == before + 2 and set(states) == {"Cancelled"}  # never left to start later


@pytest.mark.timeout(180)
def test_unstarted_children_with_no_worker_fail_naming_the_pool(idle_deployment):
    deployment, _ = idle_deployment
    with pytest.raises(RuntimeError) as err:
        parent(deployment, OrchestrationSection(poll_seconds=0.2, worker_wait_seconds=1))
    message = str(err.value)
    assert "\n" not in message and message.startswith("no worker is polling pool 'nobody': 2 test run(s) still "
                                                      "scheduled after 1 s were cancelled"), message


def child_runs(client, deployment_id) -> list:
    return client.read_flow_runs(deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment_id])))


def heartbeat(run_id) -> None:
    emit_event(HEARTBEAT, resource={"prefect.resource.id": f"prefect.flow-run.{run_id}"})


def play_machines(deployment_id, known: set, stop: threading.Event) -> None:
    """Act as the machines of the two new child runs: both start Running, `child a` sends one heartbeat and dies,
    `child b` keeps sending, and so does the parent (the test harness's flow runs send none of their own)."""
    with get_client(sync_client=True) as client:
        while len(runs := [r for r in child_runs(client, deployment_id) if r.id not in known]) < 2:
            time.sleep(0.2)
        for run in runs:
            client.set_flow_run_state(run.id, Running(), force=True)
        by_name = {run.name: run for run in runs}
        parent_id = client.read_task_run(by_name["child a"].parent_task_run_id).flow_run_id
    heartbeat(by_name["child a"].id)
    while not stop.wait(1):
        heartbeat(parent_id)
        heartbeat(by_name["child b"].id)


@pytest.mark.slow  # a minute: it waits for the phase deadline
@pytest.mark.timeout(600)  # generous: the session server may start first, beside other jobs
def test_a_child_silent_while_the_parent_is_heard_is_crashed_and_started_again(idle_deployment, monkeypatch):
    """`child a` stops sending heartbeats while the parent's are recorded: after the window the parent marks it
    Crashed and starts it again; `child b`, whose heartbeats go on, stays Running. Heartbeats every 5 s (the
    server records events in batches every few seconds), window 10 s."""
    deployment, deployment_id = idle_deployment
    monkeypatch.setattr(children, "heartbeat_interval", lambda: 5.0)
    with get_client(sync_client=True) as client:
        known = {run.id for run in child_runs(client, deployment_id)}
    stop = threading.Event()
    machines = threading.Thread(target=play_machines, args=(deployment_id, known, stop), daemon=True)
    machines.start()
    orchestration = OrchestrationSection(poll_seconds=0.5, deadline_seconds=60).model_copy(
        update={"heartbeat_timeout_seconds": 10})  # below the setting's minimum, to keep the test short
    try:
        with pytest.raises(RuntimeError) as err:
            parent(deployment, orchestration)
    finally:
        stop.set()
        machines.join(30)
    with get_client(sync_client=True) as client:
        runs = [r for r in child_runs(client, deployment_id) if r.id not in known]
    states = sorted((run.name, run.state.name) for run in runs)
    # b (Running) and the new a (Scheduled) were cancelled at the deadline
    assert states == [("child a", "Cancelled"), ("child a", "Crashed"), ("child b", "Cancelled")], states
    crashed = next(run for run in runs if run.state.name == "Crashed")
    assert crashed.state.message.startswith("no heartbeat for 10 s while its parent's were recorded"), crashed.state
    assert "child a (Scheduled), child b (Running) not finished after 60 s" in str(err.value), str(err.value)
