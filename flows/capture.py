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

from prefect import flow, get_run_logger

from flows.children import Child, orchestration_mode, run_children, uncached
from steering_core.capture import CaptureSettings, shards
from steering_core.config import RunConfig
from steering_core.data.dataset import read_meta
from steering_core.remote.publish import pulled
from tasks import capture as capture_tasks
from tasks.results import TaskSet
from tasks.run_configs import run_config

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


@flow(name=CAPTURE_FLOW)
def capture_flow(config_path: str, episodes: list[int] | None = None, write_metadata: bool = True) -> dict:
    """Capture residuals of the run config's dataset (or of `episodes`), one task per capture run (and per
    residual run: the decision rows too, with `evaluate.expert_layers`)."""
    config = run_config(config_path)
    targets, tasks = capture_targets(config), TaskSet(config.output_root, capture_tasks)
    plan = capture_plan(config, episodes)
    get_run_logger().info("capturing %d episode(s) in %d run(s) into %s", sum(map(len, plan)), len(plan),
                          ", ".join(str(run_dir) for run_dir, _, _ in targets))
    frames = 0
    for members in plan:  # one after another: they share this worker's device
        for run_dir, settings, expert in targets:
            result = tasks.capture_episodes(run_label(members, expert), str(config.dataset_root), config.repo_id,
                                  str(run_dir), settings, members)
            frames += result["frames"]
    if write_metadata:
        for run_dir, _, _ in targets:
            tasks.write_run_metadata(str(run_dir))
    return {"runs": len(plan), "frames": frames}


def capture_on_workers(config: RunConfig, config_path: str) -> None:
    """Start one capture deployment run per capture run not cached yet, wait for all, then write the run metadata."""
    tasks = TaskSet(config.output_root, capture_tasks)
    wanted = uncached(capture_plan(config), lambda members: capture_cached(config, tasks, members), "capture")
    run_children(config.orchestration.capture_deployment,
                 [Child(f"capture {run_label(members)}",
                        {"config_path": config_path, "episodes": members, "write_metadata": False})
                  for members in wanted], "capture", config.orchestration)
    for run_dir, _, _ in capture_targets(config):
        tasks.write_run_metadata(str(run_dir))


def capture_cached(config: RunConfig, tasks: TaskSet, members: list[int]) -> bool:
    """Return True when every capture task of this capture run (and its decision rows) would be `Cached`."""
    return all(tasks.is_cached("capture_episodes", run_label(members, expert), str(config.dataset_root),
                               config.repo_id, str(run_dir), settings, members)
               for run_dir, settings, expert in capture_targets(config))


def run_capture(config: RunConfig, config_path: str | Path) -> str:
    """Capture the whole dataset on the `gpu` pool or in-process (`flows.children.orchestration_mode`); return the
    mode used. Its child runs take episodes, not targets, and write no run metadata: the parent writes it after."""
    mode = orchestration_mode(config)
    if mode == "deployment":
        capture_on_workers(config, str(config_path))
    else:
        capture_flow(str(config_path))
    return mode
