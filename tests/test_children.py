"""The parent's child runs (`flows.children`) on the session's Prefect test server, with no worker at all."""

from __future__ import annotations

import pytest
from prefect import flow
from prefect.client.orchestration import get_client
from prefect.client.schemas.actions import WorkPoolCreate
from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
from prefect.exceptions import ObjectAlreadyExists

from flows.children import Child, run_children
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
