"""Run one chunk of a rollout cell: build the LIBERO scene of the cell's side, reach the policy (in-process or a
`latent-steering serve`), run the chunk's episodes under openpi's protocol and write them as one record."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from pydantic import Field

from steering_core.capture import CaptureSettings
from steering_core.pairs import other_side
from steering_core.reporting.progress import ProgressCallback
from steering_core.rollout.cells import Cell
from steering_core.rollout.settings import LiberoTask, RolloutPair, RolloutSettings
from steering_core.storage.schema import StrictModel

logger = logging.getLogger(__name__)

CHUNK_DIR = "chunk_{chunk:03d}"  # inside a cell's folder: one task run's episodes, merged into the cell's record


class RolloutJob(StrictModel):
    """One task run: a cell's episodes on some initial states, and where its record goes."""

    cell: Cell
    tasks: RolloutPair
    init_states: tuple[int, ...] = Field(min_length=1)
    chunk: int = Field(ge=0)
    vectors_root: Path        # the steer step's output root (layerNN/<pair>/directions.json)
    output_dir: Path          # the cell's folder

    @property
    def scene_task(self) -> LiberoTask:
        """Return the task whose scene, initial states and success (`done`) the episodes use: the side's own."""
        return getattr(self.tasks, self.cell.side)

    @property
    def toward_task(self) -> LiberoTask:
        """Return the other side's task, whose goal is watched on the same state."""
        return getattr(self.tasks, other_side(self.cell.side))


def steering_entries(cell: Cell, settings: RolloutSettings) -> list[dict[str, Any]]:
    """Return the cell's steering as the server's request entries (empty when unsteered)."""
    direction = cell.direction(settings.direction)
    if direction is None:
        return []
    return [{"pair": cell.steering_pair, "layer": cell.layer, "alpha": cell.alpha, "direction": direction,
             "alpha_units": "residual_norm"}]


def make_policy(job: RolloutJob, model: CaptureSettings, settings: RolloutSettings, api_key: str | None) -> Any:
    """Return the cell's `RolloutPolicy`: the served policy with its steering entries, or the in-process one."""
    from steering_core.rollout.client import LocalPolicy, RemotePolicy

    entries = steering_entries(job.cell, settings)
    if settings.policy != "local":
        return RemotePolicy(settings.policy, steering=entries, api_key=api_key)
    from steering_core.evaluate.run import load_policy
    from steering_core.serve import SteeredPi05Policy, SteeringLimits, VectorCatalog, parse_steering

    policy = load_policy(model, settings.device, settings.dtype, settings.compiled)
    catalog = VectorCatalog.scan(job.vectors_root) if entries else VectorCatalog()
    steering = parse_steering(entries, catalog, key="rollout", limits=SteeringLimits(float("inf"), model.arch.depth))
    return LocalPolicy(SteeredPi05Policy(policy, noise_seed=settings.noise_seed), steering)


_open_env: dict[str, Any] = {}  # the last scene's env, kept for the next chunk of this process (one at a time)


def _scene_env(task: Any) -> Any:
    """Return an env of `task`'s scene: the one the previous chunk used when it is the same task (construction takes
    seconds; each episode resets the env anyway), else a new one (closing the old)."""
    from steering_core.rollout import libero_env

    key = f"{task.problem_folder}/{task.bddl_file}"
    if key not in _open_env:
        for old in _open_env.values():
            old.close()
        _open_env.clear()
        _open_env[key] = libero_env.make_env(task)
    return _open_env[key]


def libero_task(task: LiberoTask) -> tuple[int, Any]:
    """Return (index, LIBERO task) of a configured task (by index, instruction or task name)."""
    from steering_core.rollout import libero_env

    index = task.task if isinstance(task.task, int) else libero_env.task_index(task.suite, task.task)
    return index, libero_env.find_task(task.suite, index)


def initial_states(task: LiberoTask, wanted: tuple[int, ...]) -> Any:
    """Return the benchmark's initial states of `task`; raise unless it has every index in `wanted`."""
    from steering_core.rollout import libero_env

    states = libero_env.initial_states(task.suite, libero_task(task)[0])
    if max(wanted) >= len(states):
        raise ValueError(f"{task.describe()}: initial states {wanted[0]}..{wanted[-1]} asked, the task has "
                         f"{len(states)} (0..{len(states) - 1}); lower rollout.episodes or first_init_state")
    return states


def run_chunk(job: RolloutJob, model: CaptureSettings, settings: RolloutSettings, *, api_key: str | None = None,
              progress: ProgressCallback | None = None) -> Path:
    """Run the job's episodes; write them as a cell record of their own in `<cell>/chunk_NNN/` and return it."""
    from steering_core.rollout import episode, libero_env, records
    from steering_core.rollout.assets import resolve_assets
    from steering_core.rollout.predicates import Goal, goal_thresholds
    from steering_core.rollout.protocol import max_steps as suite_max_steps

    libero_env.prepare_libero(resolve_assets(settings.libero_assets))
    scene_index, scene = libero_task(job.scene_task)
    toward_index, toward = libero_task(job.toward_task)
    prompt = (toward if job.cell.prompt_side != job.cell.side else scene).language
    env = _scene_env(scene)
    goal = Goal.from_task(toward)
    goal.check(env)
    thresholds = goal_thresholds([Goal.of_env(env), goal], env)  # drawn on the pair's joint plot
    states = initial_states(job.scene_task, job.init_states)
    max_steps = settings.max_steps or suite_max_steps(job.scene_task.suite)
    policy = make_policy(job, model, settings, api_key)
    done = []
    try:
        for i, index in enumerate(job.init_states):
            done.append(episode.run_episode(
                env, policy, prompt=prompt, init_state=states[index], init_index=index, max_steps=max_steps,
                toward_goal=goal, record_frames=settings.videos and index == settings.first_init_state,
                seed=settings.seed, episode_id=index))
            if progress is not None:
                progress(i + 1, len(job.init_states))
    finally:
        if hasattr(policy, "close"):  # a server connection
            policy.close()
    tasks = records.CellTasks(records.TaskRef(job.scene_task.suite, scene_index, scene.language),
                              records.TaskRef(job.toward_task.suite, toward_index, toward.language))
    run = {"policy": settings.policy, "steering": steering_entries(job.cell, settings), "max_steps": max_steps,
           "noise_seed": settings.noise_seed, "chunk": job.chunk, "thresholds": thresholds}
    folder = chunk_dir(job)
    records.write_cell(folder, job.cell, tasks, done, [settings.seed] * len(done), run)
    return folder


def chunk_dir(job: RolloutJob) -> Path:
    """Return the folder of a job's chunk record inside its cell's folder."""
    return job.output_dir / CHUNK_DIR.format(chunk=job.chunk)
