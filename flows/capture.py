"""The capture flow `latent-steering-capture`: residuals of groups of episodes, on the `gpu` work pool.

Episodes are captured in fixed runs of `shards_per_capture_run` shard groups (run r holds shard
groups r*S .. r*S+S-1), so the runs of a growing dataset keep their episodes and cached runs stay
cached. With a server, the parent flow starts one deployment run per capture run not cached yet (through
`flows.children`: crashed runs started again, deadlines) so several GPU workers share the work; without
one, the parent calls this flow in-process (a subflow) and the runs go one after another on the local device. With `evaluate.expert_layers`, each capture run also
writes the action expert's `decision` rows of its episodes into `residuals/<name>_decision` (a second
residual run, same episodes and groups), so the GPU flow runs stay as many as without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, runtime

from flows.children import Child, run_children
from steering_core.capture import CaptureSettings, shards
from steering_core.config import RunConfig, load_run_config
from steering_core.data.dataset import read_meta
from steering_core.remote.publish import pulled
from tasks import capture as capture_tasks
from tasks.results import is_cached, rooted

CAPTURE_FLOW = "latent-steering-capture"


def capture_plan(config: RunConfig, episodes: Sequence[int] | None = None) -> list[list[int]]:
    """Return the episodes of each capture run (all dataset episodes, or only `episodes`), in order."""
    known = [e.episode_index for e in read_meta(pulled(config.dataset_root)).episodes]
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


def capture_on_workers(config: RunConfig, config_path: str) -> None:
    """Start one capture deployment run per capture run not cached yet, wait for all, then write the run metadata."""
    plan = capture_plan(config)
    wanted = [members for members in plan if not capture_cached(config, members)]
    if len(wanted) < len(plan):
        get_run_logger().info("%d of %d capture run(s) cached: not started", len(plan) - len(wanted), len(plan))
    run_children(config.orchestration.capture_deployment,
                 [Child(f"capture {run_label(members)}",
                        {"config_path": config_path, "episodes": members, "write_metadata": False})
                  for members in wanted], "capture", config.orchestration)
    for run_dir, _, _ in capture_targets(config):
        rooted(capture_tasks.write_run_metadata, config.output_root)(str(run_dir))


def capture_cached(config: RunConfig, members: list[int]) -> bool:
    """Return True when every capture task of this capture run (and its decision rows) would be `Cached`."""
    return all(is_cached(capture_tasks.capture_episodes, config.output_root, run_label(members, expert),
                         str(config.dataset_root), config.repo_id, str(run_dir), settings, members)
               for run_dir, settings, expert in capture_targets(config))


def run_deployments(config: RunConfig, deployment: str, config_path: str | Path, targets: Sequence[Sequence[Any]],
                    run_names: Sequence[str], what: str) -> None:
    """Start one run of `deployment` per target (its `targets` parameter) and wait for all (`flows.children`)."""
    run_children(deployment, [Child(name, {"config_path": str(config_path), "targets": [list(target)]})
                              for target, name in zip(targets, run_names, strict=True)], what, config.orchestration)


def run_capture(config: RunConfig, config_path: str | Path) -> str:
    """Capture the whole dataset on the `gpu` pool or in-process (see `capture_mode`); return the mode used."""
    mode = capture_mode(config)
    if mode == "deployment":
        capture_on_workers(config, str(config_path))
    else:
        capture_flow(str(config_path))
    return mode
