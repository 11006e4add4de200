"""`latent-steering deploy --storage <url>`: the bucket is checked writable, Prefect's result-storage block is saved
with its basepath, and every deployment's job env names the storage; a bad or unreachable URL is one line, before
the server changes; without `--storage` the deployments carry no storage setting.

Runs against the session's Prefect server and the local S3 endpoint (a real bucket or MinIO works the same way).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from prefect.blocks.core import Block
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterTags
from prefect.exceptions import ObjectNotFound
from typer.testing import CliRunner

from deployments.setup import CRASH_AUTOMATION, GPU_TAG, PROJECT_TAG, deploy_all
from latent_steering_cli import app
from steering_core.demo import build_demo
from steering_core.remote import filesystems

pytestmark = pytest.mark.slow  # `prefect deploy` against a real server

DEPLOYMENTS = {"pipeline", "gpu", "gpu-train-sae", "gpu-evaluate", "sim-rollout", "scheduled"}
BASE_ENV = {"PREFECT_LOGGING_EXTRA_LOGGERS": "steering_core", "HF_HUB_OFFLINE": "1",
            "PREFECT_FLOWS_HEARTBEAT_FREQUENCY": "30", "PREFECT_RESULTS_DEFAULT_SERIALIZER": "json"}
STORAGE_KEYS = {"LATENT_STEERING_STORAGE", "PREFECT_RESULTS_DEFAULT_STORAGE_BLOCK", "PREFECT_RESULTS_PERSIST_BY_DEFAULT"}


@pytest.fixture(scope="module")
def config_path(tmp_path_factory, prefect_server) -> Iterator[Path]:
    """A valid run config; afterwards, the `gpu` limit and the crash automation `deploy` made are removed from the
    session's server unless they were there before (other modules' runs share it)."""
    with get_client(sync_client=True) as client:
        had_limit = gpu_limit(client) is not None
        had_automation = bool(client.read_automations_by_name(CRASH_AUTOMATION))
    yield build_demo(tmp_path_factory.mktemp("fleet") / "demo", demos_per_task=1)
    with get_client(sync_client=True) as client:
        if not had_limit and gpu_limit(client) is not None:
            client.delete_concurrency_limit_by_tag(GPU_TAG)
        for automation in [] if had_automation else client.read_automations_by_name(CRASH_AUTOMATION):
            client.delete_automation(automation.id)


def gpu_limit(client) -> int | None:
    try:
        return client.read_concurrency_limit_by_tag(GPU_TAG).concurrency_limit
    except ObjectNotFound:
        return None


def deploy(config_path: Path, *options: str) -> tuple[int, list[str]]:
    """Run `latent-steering deploy` in this process (so against the session's server); return (exit code, lines)."""
    result = CliRunner().invoke(app, ["deploy", "--config", str(config_path), *options])
    return result.exit_code, result.output.strip().splitlines()


def deployments() -> dict[str, object]:
    """Return every project deployment on the server, by name."""
    tagged = DeploymentFilter(tags=DeploymentFilterTags(all_=[PROJECT_TAG]))
    with get_client(sync_client=True) as client:
        return {d.name: d for d in client.read_deployments(deployment_filter=tagged)}


def job_envs() -> dict[str, dict[str, str]]:
    """Return the job env of every project deployment, by name."""
    return {name: d.job_variables["env"] for name, d in deployments().items()}


def results_basepath() -> str:
    with get_client(sync_client=True) as client:
        return client.read_block_document_by_name("latent-steering-results", "remote-file-system").data["basepath"]


def test_storage_is_saved_as_the_result_block_and_named_in_every_deployment(config_path, bucket):
    url = f"{bucket}/fleet"
    code, lines = deploy(config_path, "--storage", f"{url}/")
    assert code == 0 and f"result storage: block latent-steering-results -> {url}/.prefect-cache" in lines, lines
    assert results_basepath() == f"{url}/.prefect-cache"
    envs = job_envs()
    assert set(envs) == DEPLOYMENTS
    for name, env in envs.items():
        assert env == {**BASE_ENV, **({"MUJOCO_GL": "egl"} if name == "sim-rollout" else {}),
                       "LATENT_STEERING_STORAGE": url,
                       "PREFECT_RESULTS_DEFAULT_STORAGE_BLOCK": "remote-file-system/latent-steering-results",
                       "PREFECT_RESULTS_PERSIST_BY_DEFAULT": "true"}, name
    fs = filesystems.filesystem("s3")
    assert fs.find(bucket.removeprefix("s3://")) == []  # the write probe is gone
    # the block the flow runs load writes into the bucket, with this machine's credentials from the environment
    Block.load(envs["pipeline"]["PREFECT_RESULTS_DEFAULT_STORAGE_BLOCK"]).write_path("result", b"42")
    assert fs.cat_file(f"{url.removeprefix('s3://')}/.prefect-cache/result") == b"42"



def test_without_storage_the_deployments_carry_no_storage_setting(config_path, monkeypatch):
    """Also after a deploy with --storage (the test above); a stray shell setting does not leak in."""
    monkeypatch.setenv("LATENT_STEERING_STORAGE", "s3://stray")
    code, lines = deploy(config_path)
    assert code == 0, lines
    envs = job_envs()
    assert set(envs) == DEPLOYMENTS
    assert all(not STORAGE_KEYS & set(env) and BASE_ENV.items() <= env.items() for env in envs.values()), envs
    assert crash_window() == 600  # the default: deployments/README.md says why


def crash_window() -> float:
    """Return the crash automation's window on the server, in seconds."""
    with get_client(sync_client=True) as client:
        [automation] = client.read_automations_by_name(CRASH_AUTOMATION)
    return automation.trigger.within.total_seconds()


@pytest.mark.parametrize("seconds", ["89", "0", "-600"])
def test_a_crash_window_shorter_than_three_heartbeats_is_one_line_and_changes_nothing(config_path, seconds):
    with get_client(sync_client=True) as client:
        before = gpu_limit(client)
    code, lines = deploy(config_path, "--heartbeat-timeout", seconds, "--gpu-slots", "7")
    assert code == 1 and len(lines) == 1, lines
    assert lines[0].startswith(f"error: --heartbeat-timeout is {seconds}, expected a finite number of at least 90 seconds"), lines
    with get_client(sync_client=True) as client:
        assert gpu_limit(client) == before != 7


def test_a_config_url_is_every_deployment_parameter_as_it_is(config_path, bucket):
    """Workers on other machines read the run config from the bucket (a path would be made absolute)."""
    url = f"{bucket}/fleet/run.yaml"
    deploy_all(url)
    assert {name: d.parameters for name, d in deployments().items()} == {name: {"config_path": url} for name in DEPLOYMENTS}


@pytest.mark.parametrize("storage", ["ftp://host/folder", "s3://", "s3://bucket/../up", "/local/folder"])
def test_a_bad_storage_url_is_one_line_and_changes_nothing(config_path, storage):
    with get_client(sync_client=True) as client:
        before = gpu_limit(client)
    code, lines = deploy(config_path, "--storage", storage, "--gpu-slots", "7")
    assert code == 1 and len(lines) == 1 and lines[0].startswith("error: ") and storage in lines[0], lines
    with get_client(sync_client=True) as client:
        assert gpu_limit(client) == before != 7


def test_an_unreachable_bucket_is_one_line_naming_it(config_path, bucket):
    missing = f"{bucket}-missing/fleet"
    code, lines = deploy(config_path, "--storage", missing)
    assert code == 1 and len(lines) == 1, lines
    assert lines[0].startswith(f"error: {missing}: not writable from this machine") and "bucket does not exist" in lines[0]
    assert not filesystems.filesystem("s3").exists(missing.removeprefix("s3://").split("/")[0])  # the probe made nothing
