"""`latent-steering deploy`: work pools, the `gpu` concurrency limit, then every deployment of prefect.yaml.

Runs against the server named by PREFECT_API_URL; without it, Prefect would silently deploy to a
throwaway embedded server, so that is refused.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

from prefect.client.orchestration import get_client
from prefect.client.schemas.actions import WorkPoolCreate
from prefect.exceptions import ObjectNotFound
from prefect.settings import PREFECT_API_URL
from prefect.workers.process import ProcessWorker

logger = logging.getLogger(__name__)

PROJECT_DIR = Path(__file__).resolve().parent.parent
PREFECT_FILE = "deployments/prefect.yaml"   # relative to the repository root
CONFIG_ENV = "LATENT_STEERING_CONFIG"        # read by prefect.yaml's `{{ $LATENT_STEERING_CONFIG }}`
GPU_POOL, CPU_POOL, SIM_POOL = "gpu", "cpu", "sim"
GPU_TAG = "gpu"                              # tag of every GPU task; its limit = GPUs across all workers


def require_api_url() -> str:
    """Return PREFECT_API_URL, or raise naming how to set it."""
    url = PREFECT_API_URL.value()
    if not url:
        raise ValueError(
            "PREFECT_API_URL is not set, so Prefect would deploy to a throwaway embedded server; "
            "start a server (`prefect server start`) and export PREFECT_API_URL=http://127.0.0.1:4200/api"
        )
    return url


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


def deploy_all(config_path: str | os.PathLike, project_dir: Path = PROJECT_DIR) -> None:
    """Run `prefect deploy --all` on prefect.yaml with the run config's absolute path as parameter."""
    prefect_file = project_dir / PREFECT_FILE
    if not prefect_file.is_file():
        raise FileNotFoundError(
            f"{prefect_file}: not found; run `latent-steering deploy` from a checkout of the repository"
        )
    config_path = Path(config_path).resolve()
    if not config_path.is_file():
        raise FileNotFoundError(f"{config_path}: run config not found; pass --config with an existing YAML file")
    env = {**os.environ, CONFIG_ENV: str(config_path), "PREFECT_API_URL": require_api_url()}
    command = [sys.executable, "-m", "prefect", "--no-prompt", "deploy", "--all", "--prefect-file", PREFECT_FILE]
    logger.info("running %s in %s", " ".join(command[2:]), project_dir)
    done = subprocess.run(command, cwd=project_dir, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"`prefect deploy` failed (exit {done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    logger.info("deployments created from %s", prefect_file)


def setup(config_path: str | os.PathLike, gpu_slots: int = 1, project_dir: Path = PROJECT_DIR) -> None:
    """Create pools and the GPU limit, then deploy the parent, capture and refresh flows."""
    logger.info("setting up deployments on %s", require_api_url())
    ensure_pools()
    set_gpu_limit(gpu_slots)
    deploy_all(config_path, project_dir)
