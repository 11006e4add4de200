"""The capture flow `latent-steering-capture`: residuals of groups of episodes, on the `gpu` work pool.

Episodes are captured in fixed runs of `shards_per_capture_run` shard groups (run r holds shard
groups r*S .. r*S+S-1), so the runs of a growing dataset keep their episodes and cached runs stay
cached. With a server, the parent flow starts one deployment run per capture run so several GPU
workers share the work; without one, the parent calls this flow in-process (a subflow) and the
runs go one after another on the local device. With `evaluate.expert_layers`, each capture run also
writes the action expert's `decision` rows of its episodes into `residuals/<name>_decision` (a second
residual run, same episodes and groups), so the GPU flow runs stay as many as without it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, runtime
from prefect.client.orchestration import get_client
from prefect.client.schemas.objects import FlowRun, WorkerStatus
from prefect.deployments import run_deployment
from prefect.states import Cancelled

from steering_core.capture import CaptureSettings, shards
from steering_core.config import RunConfig, load_run_config
from steering_core.data.dataset import read_meta
from tasks import capture as capture_tasks
from tasks.cache import rooted

CAPTURE_FLOW = "latent-steering-capture"


def capture_plan(config: RunConfig, episodes: Sequence[int] | None = None) -> list[list[int]]:
    """Return the episodes of each capture run (all dataset episodes, or only `episodes`), in order."""
    known = [e.episode_index for e in read_meta(config.dataset_root).episodes]
    wanted = known if episodes is None else sorted(set(episodes) & set(known))
    per_run = config.orchestration.shards_per_capture_run
    runs: dict[int, list[int]] = {}
    for key, members in shards.group_episodes(wanted, config.capture.episodes_per_shard).items():
        runs.setdefault(int(key) // per_run, []).extend(members)
    return [runs[r] for r in sorted(runs)]


def run_label(episodes: Sequence[int], expert: bool = False) -> str:
    """Return a capture run's name, e.g. `episodes 0-15` (`decision episodes 0-15` for the expert's rows)."""
    return ("decision " if expert else "") + f"episodes {episodes[0]}-{episodes[-1]}"


def capture_targets(config: RunConfig) -> list[tuple[Path, CaptureSettings, bool]]:
    """Return (run folder, capture settings, is the expert's) of the main capture and, with
    `evaluate.expert_layers`, of the `decision` capture."""
    targets = [(config.run_dir, config.capture_settings(), False)]
    if config.expert_layers:
        targets.append((config.decision_run_dir, config.decision_capture_settings(), True))
    return targets


def capture_mode(config: RunConfig) -> str:
    """Return `deployment` or `local`: `auto` means deployments when this flow run came from a deployment."""
    mode = config.orchestration.capture
    if mode == "auto":
        return "deployment" if runtime.deployment.id else "local"
    return mode


@flow(name=CAPTURE_FLOW)
def capture_flow(config_path: str, episodes: list[int] | None = None, write_metadata: bool = True) -> dict:
    """Capture residuals of the run config's dataset (or of `episodes`), one task per capture run (and per
    residual run: the decision rows too, with `evaluate.expert_layers`)."""
    config = load_run_config(config_path)
    targets = capture_targets(config)
    capture_task = rooted(capture_tasks.capture_episodes, config.output_root)
    plan = capture_plan(config, episodes)
    get_run_logger().info("capturing %d episode(s) in %d run(s) into %s", sum(map(len, plan)), len(plan),
                          ", ".join(str(run_dir) for run_dir, _, _ in targets))
    frames = 0
    for members in plan:  # one after another: they share this worker's device
        for run_dir, settings, expert in targets:
            result = capture_task(run_label(members, expert), str(config.dataset_root), config.repo_id,
                                  str(run_dir), settings, members)
            frames += result["frames"]
    if write_metadata:
        for run_dir, _, _ in targets:
            rooted(capture_tasks.write_run_metadata, config.output_root)(str(run_dir))
    return {"runs": len(plan), "frames": frames}


def capture_on_workers(config: RunConfig, config_path: str) -> list[FlowRun]:
    """Start one capture deployment run per capture run, wait for all, then write the run metadata."""
    logger = get_run_logger()
    deployment = config.orchestration.capture_deployment
    started = [
        run_deployment(deployment, parameters={"config_path": config_path, "episodes": members, "write_metadata": False},
                       flow_run_name=f"capture {run_label(members)}", timeout=0)
        for members in capture_plan(config)
    ]
    logger.info("started %d capture run(s) of %s; waiting", len(started), deployment)
    finished = wait_for_runs(started, config.orchestration.poll_seconds, config.orchestration.worker_wait_seconds)
    failed = [f"{run.name} ({run.state.name if run.state else 'no state'})" for run in finished
              if run.state is None or not run.state.is_completed()]
    if failed:
        raise RuntimeError(f"capture run(s) did not complete: {', '.join(failed)}; see them in the Prefect UI, "
                           "fix the cause and re-run: complete shards are kept")
    for run_dir, _, _ in capture_targets(config):
        rooted(capture_tasks.write_run_metadata, config.output_root)(str(run_dir))
    return finished


def run_deployments(config: RunConfig, deployment: str, config_path: str | Path, targets: Sequence[Sequence[Any]],
                    run_names: Sequence[str], what: str) -> None:
    """Start one run of `deployment` per target (its `targets` parameter) and wait for all; raise naming the runs
    that did not complete, or the pool when no worker polls it (`orchestration.worker_wait_seconds`)."""
    started = [run_deployment(deployment, parameters={"config_path": str(config_path), "targets": [list(target)]},
                              flow_run_name=name, timeout=0) for target, name in zip(targets, run_names, strict=True)]
    get_run_logger().info("started %d %s run(s); waiting", len(started), what)
    orchestration = config.orchestration
    failed = [run.name for run in wait_for_runs(started, orchestration.poll_seconds, orchestration.worker_wait_seconds)
              if run.state is None or not run.state.is_completed()]
    if failed:
        raise RuntimeError(f"{what} run(s) did not complete: {', '.join(failed)}; see them in the Prefect UI")


def wait_for_runs(runs: Sequence[FlowRun], poll_seconds: float, worker_wait_seconds: float | None = None) -> list[FlowRun]:
    """Return `runs` re-read once each has reached a final state (polling the API every `poll_seconds`).

    If after `worker_wait_seconds` none of the runs has started and no worker of their pool is online,
    they are cancelled and a RuntimeError names the pool: nothing would ever run them.
    """
    pending = {run.id: run for run in runs}
    finished: dict[Any, FlowRun] = {}
    deadline = None if worker_wait_seconds is None else time.monotonic() + worker_wait_seconds
    with get_client(sync_client=True) as client:
        while pending:
            for run_id in list(pending):
                run = pending[run_id] = client.read_flow_run(run_id)
                if run.state is not None and run.state.is_final():
                    del pending[run_id]
                    finished[run_id] = run
            if pending and deadline is not None and time.monotonic() > deadline:
                _fail_if_nobody_polls(client, list(pending.values()), worker_wait_seconds)
                deadline = None  # a worker is there: wait as long as the runs take
            if pending:
                time.sleep(poll_seconds)
    return [finished[run.id] for run in runs]


def _fail_if_nobody_polls(client: Any, pending: list[FlowRun], waited: float) -> None:
    """Cancel `pending` and raise if none has started and their work pool has no online worker."""
    if any(run.state is None or not run.state.is_scheduled() for run in pending):
        return  # a worker picked one up
    pools = sorted({run.work_pool_name for run in pending if run.work_pool_name})
    online = [pool for pool in pools
              if any(worker.status == WorkerStatus.ONLINE for worker in client.read_workers_for_work_pool(pool))]
    if online:
        return
    for run in pending:
        client.set_flow_run_state(run.id, Cancelled(message=f"no worker polled pool {', '.join(pools)}"), force=True)
    raise RuntimeError(
        f"no worker is polling pool {', '.join(repr(p) for p in pools) or '(none)'}: {len(pending)} capture run(s) "
        f"still scheduled after {waited:.0f} s were cancelled; start one with "
        f"`prefect worker start --pool {pools[0] if pools else 'gpu'}` and re-run (complete shards are kept)"
    )


def run_capture(config: RunConfig, config_path: str | Path) -> str:
    """Capture the whole dataset on the `gpu` pool or in-process (see `capture_mode`); return the mode used."""
    mode = capture_mode(config)
    if mode == "deployment":
        capture_on_workers(config, str(config_path))
    else:
        capture_flow(str(config_path))
    return mode
