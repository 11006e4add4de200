"""`latent-steering deploy`: work pools, the `gpu` concurrency limit, the crash automation, the result storage
(with `--storage`), then every deployment of prefect.yaml.

Runs against the server named by PREFECT_API_URL; without it, Prefect would silently deploy to a
throwaway embedded server, so that is refused, and so is an address where no Prefect server answers (one line
naming it, before Prefect's client retries).

Storage (`--storage s3://bucket/prefix`): checked writable from this machine, saved as the RemoteFileSystem block
`latent-steering-results` (basepath `<url>/.prefect-cache`), and named in the deployments' job env so flow results
go there too. Only the URL is stored: each worker reads the endpoint and credentials from its own environment.
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
from datetime import timedelta
from pathlib import Path

import httpx
from prefect.client.orchestration import get_client
from prefect.client.schemas.actions import WorkPoolCreate
from prefect.client.schemas.objects import StateType
from prefect.events.actions import ChangeFlowRunState
from prefect.events.schemas.automations import AutomationCore, EventTrigger, Posture
from prefect.exceptions import ObjectNotFound
from prefect.filesystems import RemoteFileSystem
from prefect.settings import PREFECT_API_URL
from prefect.workers.process import ProcessWorker

from steering_core.remote import filesystems
from steering_core.storage import mirrors

logger = logging.getLogger(__name__)

PROJECT_DIR = Path(__file__).resolve().parent.parent
PREFECT_FILE = "deployments/prefect.yaml"   # relative to the repository root
CONFIG_ENV = "LATENT_STEERING_CONFIG"        # read by prefect.yaml's `{{ $LATENT_STEERING_CONFIG }}`
RESULTS_BLOCK = "latent-steering-results"    # RemoteFileSystem block of Prefect's results on the storage
RESULTS_FOLDER = ".prefect-cache"            # under the storage URL, as under every output root
STORAGE_ENV = "LATENT_STEERING_STORAGE"      # the storage URL, in the deployments' job env (for information)
# prefect.yaml's storage template fields (`{{ NAME }}`, resolved from the environment of `prefect deploy`): an unset
# one drops its key from the job env, so deployments made without --storage carry no storage setting at all
STORAGE_PLACEHOLDERS = (STORAGE_ENV, "LATENT_STEERING_RESULTS_BLOCK", "LATENT_STEERING_PERSIST_RESULTS")
GPU_POOL, CPU_POOL, SIM_POOL = "gpu", "cpu", "sim"
GPU_TAG = "gpu"                              # tag of every GPU task; its limit = GPUs across all workers
PROJECT_TAG = "latent-steering"              # tag of every deployment in prefect.yaml, so of their flow runs
# Flow runs of the deployments send a heartbeat event every 30 s (PREFECT_FLOWS_HEARTBEAT_FREQUENCY in prefect.yaml,
# Prefect's minimum). A parent marks its dead children itself, on evidence (flows/heartbeats.py); this automation is
# the last resort for runs nobody watches (the parent itself). It sees one run's silence only, which a stalled server
# (a locked database: a 60 s stall was measured under load) causes too, so its default window is ten times that stall:
# 20 missed heartbeats (deployments/README.md, "When a worker or a machine dies").
HEARTBEAT_TIMEOUT = 600
MINIMUM_HEARTBEAT_TIMEOUT = 90  # three heartbeats: Prefect's own rule of thumb for the window
CRASH_AUTOMATION = "latent-steering: crash flow runs whose heartbeats stopped"
API_PROBE_TIMEOUT_S = 10  # a Prefect server answers its health check in milliseconds
_FINAL_EVENTS = {f"prefect.flow-run.{state}" for state in ("Completed", "Failed", "Cancelled", "Crashed")}


def require_api_url() -> str:
    """Return PREFECT_API_URL, or raise naming how to set it."""
    url = PREFECT_API_URL.value()
    if not url:
        raise ValueError(
            "PREFECT_API_URL is not set, so Prefect would deploy to a throwaway embedded server; "
            "start a server (`prefect server start`) and export PREFECT_API_URL=http://127.0.0.1:4200/api"
        )
    return url


def check_api_answers(url: str) -> None:
    """Return once the Prefect server at `url` answers its health check; ValueError naming the address otherwise."""
    health = f"{url.rstrip('/')}/health"
    try:
        answer = httpx.get(health, timeout=API_PROBE_TIMEOUT_S)
    except httpx.HTTPError as err:
        reason = str(err) or type(err).__name__
        raise ValueError(f"PREFECT_API_URL {url}: no Prefect server answers there ({reason}); start one "
                         "(`prefect server start`) or set PREFECT_API_URL to your server's address") from None
    if answer.status_code != 200:
        raise ValueError(f"PREFECT_API_URL {url}: {health} answers HTTP {answer.status_code}, not a Prefect server's "
                         "health check; set PREFECT_API_URL to the server's API address (ending in /api)")


def ensure_pools(pools: tuple[str, ...] = (GPU_POOL, CPU_POOL, SIM_POOL)) -> list[str]:
    """Create the missing process work pools; return the names of those created."""
    created = []
    with get_client(sync_client=True) as client:
        for name in pools:
            try:
                client.read_work_pool(name)
            except ObjectNotFound:
                client.create_work_pool(
                    WorkPoolCreate(
                        name=name, type="process", base_job_template=ProcessWorker.get_default_base_job_template()
                    )
                )
                created.append(name)
    logger.info("work pools %s ready (created: %s)", ", ".join(pools), ", ".join(created) or "none")
    return created


def set_gpu_limit(slots: int) -> None:
    """Set the tag concurrency limit that caps running GPU tasks at `slots` across all workers."""
    if slots < 1:
        raise ValueError(f"--gpu-slots is {slots}, expected at least 1 (the number of GPUs across your gpu workers)")
    with get_client(sync_client=True) as client:
        client.create_concurrency_limit(tag=GPU_TAG, concurrency_limit=slots)
    logger.info("concurrency limit: at most %d task(s) tagged %r at once", slots, GPU_TAG)


def crash_automation(timeout_seconds: float = HEARTBEAT_TIMEOUT) -> AutomationCore:
    """Return the automation that marks a project flow run Crashed when, after a heartbeat, neither another
    heartbeat nor a final state follows within `timeout_seconds` (so its parent can start it again)."""
    return AutomationCore(
        name=CRASH_AUTOMATION,
        description="A flow run of the latent-steering deployments whose heartbeats stopped lost its process: "
                    "mark it Crashed, so its parent starts it again and the pipeline's concurrency slot is freed.",
        trigger=EventTrigger(
            after={"prefect.flow-run.heartbeat"},
            expect={"prefect.flow-run.heartbeat", *_FINAL_EVENTS},
            match={"prefect.resource.id": "prefect.flow-run.*"},
            match_related={"prefect.resource.id": f"prefect.tag.{PROJECT_TAG}"},
            for_each={"prefect.resource.id"},
            posture=Posture.Proactive,
            threshold=1,
            within=timedelta(seconds=timeout_seconds),
        ),
        actions=[ChangeFlowRunState(state=StateType.CRASHED,
                                    message=f"no heartbeat for {timeout_seconds:.0f} s: its process or machine died")],
    )


def ensure_crash_automation(timeout_seconds: float = HEARTBEAT_TIMEOUT) -> None:
    """Create (or replace) the crash automation on the server."""
    with get_client(sync_client=True) as client:
        for existing in client.read_automations_by_name(CRASH_AUTOMATION):
            client.delete_automation(existing.id)
        client.create_automation(crash_automation(timeout_seconds))
    logger.info("automation %r: flow runs silent for %.0f s are marked Crashed", CRASH_AUTOMATION, timeout_seconds)


def check_storage(url: str) -> str:
    """Return `url` normalised (`<protocol>://<path>`) once a probe object was written and deleted under it from
    this machine; ValueError in one line naming the URL otherwise."""
    if not mirrors.is_url(url):
        raise ValueError(f"--storage {url!r}: expected a URL such as s3://bucket/prefix (or gs://, file://)")
    protocol, path = mirrors.split_url(url)
    return filesystems.check_writable(f"{protocol}://{path}")


def save_results_block(basepath: str) -> str:
    """Save (or replace) the result-storage block of `basepath`; return its slug (`<block type>/<name>`)."""
    RemoteFileSystem(basepath=basepath).save(RESULTS_BLOCK, overwrite=True)
    slug = f"{RemoteFileSystem.get_block_type_slug()}/{RESULTS_BLOCK}"
    logger.info("result storage: block %s -> %s", slug, basepath)
    return slug


def storage_values(url: str, block: str) -> dict[str, str]:
    """Return the values of STORAGE_PLACEHOLDERS for deployments whose results go to the block `block` of `url`."""
    return dict(zip(STORAGE_PLACEHOLDERS, (url, block, "true"), strict=True))


def deploy_all(config_path: str | os.PathLike, project_dir: Path = PROJECT_DIR, storage: dict[str, str] | None = None
               ) -> None:
    """Run `prefect deploy --all` on prefect.yaml with the run config as parameter (a URL as it is, so every worker
    reads it from the bucket; a path made absolute) and the values of the storage template fields (`storage_values`,
    none by default) in its environment."""
    prefect_file = project_dir / PREFECT_FILE
    if not prefect_file.is_file():
        raise FileNotFoundError(
            f"{prefect_file}: not found; run `latent-steering deploy` from a checkout of the repository"
        )
    if not mirrors.is_url(config_path):
        config_path = Path(config_path).resolve()
        if not config_path.is_file():
            raise FileNotFoundError(f"{config_path}: run config not found; pass --config with an existing YAML file")
    inherited = {k: v for k, v in os.environ.items() if k not in STORAGE_PLACEHOLDERS}  # only --storage sets them
    env = {**inherited, **(storage or {}), CONFIG_ENV: str(config_path), "PREFECT_API_URL": require_api_url()}
    command = [sys.executable, "-m", "prefect", "--no-prompt", "deploy", "--all", "--prefect-file", PREFECT_FILE]
    logger.info("running %s in %s", " ".join(command[2:]), project_dir)
    done = subprocess.run(command, cwd=project_dir, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"`prefect deploy` failed (exit {done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    logger.info("deployments created from %s", prefect_file)


def setup(config_path: str | os.PathLike, gpu_slots: int = 1, project_dir: Path = PROJECT_DIR,
          storage: str | None = None, heartbeat_timeout: float = HEARTBEAT_TIMEOUT) -> str | None:
    """Create pools, the GPU limit and the crash automation (window `heartbeat_timeout` seconds), the result storage
    of `storage` (a URL, checked first), then deploy every flow; return the results' basepath (None without storage)."""
    if not MINIMUM_HEARTBEAT_TIMEOUT <= heartbeat_timeout < math.inf:  # NaN fails every comparison
        raise ValueError(f"--heartbeat-timeout is {heartbeat_timeout:g}, expected a finite number of at least "
                         f"{MINIMUM_HEARTBEAT_TIMEOUT} seconds (three 30-second heartbeats)")
    if storage is not None:
        storage = check_storage(storage)  # before anything changes on the server
    url = require_api_url()
    check_api_answers(url)  # before any client call: Prefect's client retries for minutes, then prints tracebacks
    logger.info("setting up deployments on %s", url)
    ensure_pools()
    set_gpu_limit(gpu_slots)
    ensure_crash_automation(heartbeat_timeout)
    if storage is None:
        deploy_all(config_path, project_dir)
        return None
    basepath = f"{storage}/{RESULTS_FOLDER}"
    deploy_all(config_path, project_dir, storage_values(storage, save_results_block(basepath)))
    return basepath
