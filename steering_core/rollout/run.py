"""Run one chunk of a rollout cell: build the LIBERO scene of the cell's side (`envs_per_worker` envs of it, stepped
in lockstep), reach the policy (in-process or a `latent-steering serve`), run the chunk's episodes under openpi's
protocol and write them as one record."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from pydantic import Field

from steering_core.capture import CaptureSettings
from steering_core.pairs import other_side
from steering_core.reporting.progress import ProgressCallback
from steering_core.rollout.cells import Cell
from steering_core.rollout.renderer import describe_renderer
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
    def label(self) -> str:
        """Return e.g. "chunk 3 of pick_vs_place layer 12 negative_sae_a+2"."""
        return f"chunk {self.chunk} of {self.cell.pair} layer {self.cell.layer} {self.cell.name}"

    @property
    def scene_task(self) -> LiberoTask:
        """Return the task whose scene, initial states and success (`done`) the episodes use: the side's own."""
        return getattr(self.tasks, self.cell.side)

    @property
    def toward_task(self) -> LiberoTask:
        """Return the other side's task, whose goal is watched on the same state."""
        return getattr(self.tasks, other_side(self.cell.side))


def steering_entries(cell: Cell) -> list[dict[str, Any]]:
    """Return the cell's steering as the server's request entries (empty when unsteered).

    Add mode: the signed α in residual_norm units. Clamp mode: α is the absolute level fraction, the projection
    set to t = m₋ + α(m₊ − m₋): a push a toward the other task is α = a on the negative side (from m₋ toward m₊)
    and α = 1 − a on the positive side (t = m₊ + a(m₋ − m₊)).
    """
    if cell.steering_pair is None:
        return []
    entry = {"pair": cell.steering_pair, "layer": cell.layer}
    if cell.mode == "clamp":
        level = cell.alpha_toward if cell.side == "negative" else 1.0 - cell.alpha_toward
        return [entry | {"alpha": level, "direction": cell.direction, "mode": "clamp"}]
    return [entry | {"alpha": cell.alpha, "direction": cell.direction, "alpha_units": "residual_norm"}]


def make_policy(job: RolloutJob, model: CaptureSettings, settings: RolloutSettings, api_key: str | None) -> Any:
    """Return the cell's `RolloutPolicy`: the served policy with its steering entries, or the in-process one."""
    from steering_core.rollout.client import LocalPolicy, RemotePolicy

    entries = steering_entries(job.cell)
    if settings.policy != "local":
        return RemotePolicy(settings.policy, steering=entries, api_key=api_key)
    from steering_core.evaluate.run import load_policy
    from steering_core.serve import SteeredPi05Policy, SteeringLimits, VectorCatalog, parse_steering

    policy = load_policy(model.model, settings.device, settings.dtype, settings.compiled)
    catalog = VectorCatalog.scan(job.vectors_root) if entries else VectorCatalog()
    steering = parse_steering(entries, catalog, key="rollout", limits=SteeringLimits(float("inf"), model.arch.depth))
    return LocalPolicy(SteeredPi05Policy(policy, noise_seed=settings.noise_seed), steering)


_open_envs: dict[str, list[Any]] = {}  # the last scene's envs, kept for the next chunk of this process (one scene)


def _scene_envs(task: Any, count: int) -> list[Any]:
    """Return `count` envs of `task`'s scene: those the previous chunks built when it is the same task
    (construction takes seconds; each episode resets its env anyway), plus new ones as needed; another scene's
    envs are closed first."""
    from steering_core.rollout import libero_env

    key = f"{task.problem_folder}/{task.bddl_file}"
    if key not in _open_envs:
        for old in (env for envs in _open_envs.values() for env in envs):
            old.close()
        _open_envs.clear()
        _open_envs[key] = []
    envs = _open_envs[key]
    while len(envs) < count:
        envs.append(libero_env.make_env(task))
    return envs[:count]


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
    envs = _scene_envs(scene, settings.lockstep_envs(len(job.init_states)))
    logger.info("%s: %s", job.label, describe_renderer())
    goal = Goal.from_task(toward)
    goal.check(envs[0])
    thresholds = goal_thresholds([Goal.of_env(envs[0]), goal], envs[0])  # drawn on the pair's joint plot
    states = initial_states(job.scene_task, job.init_states)
    max_steps = settings.max_steps or suite_max_steps(job.scene_task.suite)
    policy = make_policy(job, model, settings, api_key)
    episodes = [dict(prompt=prompt, init_state=states[index], init_index=index, max_steps=max_steps,
                     toward_goal=goal, record_frames=settings.videos and index == settings.first_init_state,
                     seed=settings.seed, episode_id=index) for index in job.init_states]
    ended = []

    def report(index: int, _: Any) -> None:
        ended.append(index)
        if progress is not None:
            progress(len(ended), len(episodes))

    try:
        done = episode.run_lockstep(envs, policy, episodes, on_record=report)
    finally:
        if hasattr(policy, "close"):  # a server connection
            policy.close()
    tasks = records.CellTasks(records.TaskRef(job.scene_task.suite, scene_index, scene.language),
                              records.TaskRef(job.toward_task.suite, toward_index, toward.language))
    run = {"policy": settings.policy, "steering": steering_entries(job.cell), "max_steps": max_steps,
           "noise_seed": settings.noise_seed, "chunk": job.chunk, "thresholds": thresholds}
    folder = chunk_dir(job)
    records.write_cell(folder, job.cell, tasks, done, [settings.seed] * len(done), run)
    return folder


def chunk_dir(job: RolloutJob) -> Path:
    """Return the folder of a job's chunk record inside its cell's folder."""
    return job.output_dir / CHUNK_DIR.format(chunk=job.chunk)
