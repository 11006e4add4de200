"""Settings of the closed-loop rollouts (phase 5): which LIBERO task each side of a pair runs, the α grid, the
controls, episodes per cell, and how the policy is reached."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from steering_core.pairs import SIDES, Side, same_text
from steering_core.pi05.steering import Mode, check_alpha_grid
from steering_core.rollout.workers import MAX_WORKERS
from steering_core.storage.schema import StrictModel
from steering_core.vectors.methods import MethodNames

SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")
# α toward the other task, in residual_norm units (the evaluation's): the shift is |α| typical residual norms.
DEFAULT_ALPHAS_TOWARD = (0.0, 1.0, 2.0, 4.0)
MAX_ALPHAS = 64  # α values of a grid: each adds a cell per side and condition
MAX_ENVS_PER_WORKER = 64  # LIBERO envs one rollout process holds at once (each a MuJoCo scene and render context)
DEFAULT_ENVS_PER_WORKER = 8  # a policy call on a GPU costs about the same for a batch of 1 and of 8
MIN_RANDOM_DIRECTIONS = 4  # below this the random band is too thin to call a steered rate above it (summary warns)


class LiberoTask(StrictModel):
    """One LIBERO benchmark task: its suite and its index there or its instruction text."""

    suite: Literal[SUITES]  # type: ignore[valid-type]
    task: int | str         # index in the suite, or the task's instruction ("turn on the stove")

    @field_validator("task")
    @classmethod
    def _task(cls, task: int | str) -> int | str:
        if isinstance(task, int) and task < 0:
            raise ValueError(f"task index {task} is negative; LIBERO tasks count from 0")
        if isinstance(task, str) and not task.strip():
            raise ValueError("task is an empty instruction; give an index or the task's instruction text")
        return task

    def describe(self) -> str:
        return f"{self.suite}[{self.task!r}]"


class RolloutPair(StrictModel):
    """The LIBERO tasks of a pair's two concepts; each side's episodes run in its own task's scene and initial
    states, and the other side's goal is evaluated on the same state (its objects must be in that scene)."""

    positive: LiberoTask
    negative: LiberoTask

    @model_validator(mode="after")
    def _two_tasks(self) -> RolloutPair:
        positive, negative = self.positive, self.negative
        if positive.suite == negative.suite and (positive.task == negative.task or (
                isinstance(positive.task, str) and isinstance(negative.task, str)
                and same_text(positive.task, negative.task))):
            raise ValueError(f"positive and negative are both {positive.describe()}; the two sides of a pair need "
                             "two different LIBERO tasks")
        return self


class RolloutSettings(StrictModel):
    """How each (pair, layer) is rolled out; defaults follow openpi's LIBERO evaluation and the issue's grid."""

    alphas: tuple[float, ...] = DEFAULT_ALPHAS_TOWARD  # α toward the other task (residual_norm units; in clamp mode
                                                # the fraction of the way to the other concept's level); must hold 0
    episodes: int = Field(10, gt=0, le=1000)    # episodes per cell (the same initial states for every cell)
    first_init_state: int = Field(0, ge=0, le=10_000)  # episodes use initial states first .. first + episodes - 1
    sides: tuple[Side, ...] = SIDES  # instructions to run under
    methods: MethodNames = ("sae",)         # direction methods steered (steering_core.vectors.methods), each a
                                                # cell per push and mode; phase 3 must have written them
    modes: tuple[Mode, ...] = ("add",)          # add: α × R along the direction; clamp: each steered token's
                                                # projection set to m₋ + α(m₊ − m₋) (negative side; mirrored)
    random_directions: int = Field(MIN_RANDOM_DIRECTIONS, ge=0, le=256)  # norm-matched random controls at each α ≠ 0
                                                # (add mode, shared by every method and mode at that α)
    wrong_concept: bool = True                  # another pair's direction (the first method, add) at the same α
    instruction_swap: bool = True               # the other task's instruction, unsteered: the ceiling
    chunk_episodes: int = Field(5, gt=0, le=1000)  # episodes per task run (the fan-out's unit)
    workers: int | None = None                  # chunks simulated at once in worker processes on this machine;
                                                # None: one per usable core within the memory (at most the chunks)
    envs_per_worker: int | None = None          # envs a task run steps in lockstep, batching their policy calls;
                                                # None: min(8, the chunk's episodes). Outside the identity, like
                                                # device: it moves actions by float32 rounding (a row's batch place)
    max_steps: int | None = Field(None, gt=0, le=10_000)  # None: openpi's per suite
    seed: int = 7                               # the environment seed (openpi's)
    noise_seed: int | None = 0                  # the in-process policy's initial noise (None: fresh per call, as
                                                # openpi; a server draws its own: `serve --noise-seed`)
    videos: bool = True                         # an MP4 of each cell's first episode
    policy: str = "local"                       # "local" (in-process) or ws://host:port of `latent-steering serve`
    api_key_file: Path | None = None            # the server's key (`serve --api-key-file`)
    libero_assets: str = "installed"            # "installed" (PyPI packages, verified), "download", or a folder
    device: str = "auto"
    dtype: str | None = None                    # None: bfloat16 on CUDA, float32 on CPU (as openpi)
    compiled: bool | None = None                # the compiled denoising step (None: on CUDA); rounding only: no identity
    note: str | None = None                     # printed at the top of the summary (e.g. "tiny random model")

    @field_validator("alphas")
    @classmethod
    def _alphas(cls, alphas: tuple[float, ...]) -> tuple[float, ...]:
        if len(alphas) > MAX_ALPHAS:
            raise ValueError(f"alphas: {len(alphas)} values; expected at most {MAX_ALPHAS} (each is a cell per "
                             "condition and side, every one a set of episodes)")
        check_alpha_grid(alphas)
        if not all(a >= 0 for a in alphas):
            raise ValueError(f"alphas {list(alphas)} must be >= 0: each is a push toward the other task "
                             "(the mirror side gets the opposite sign)")
        grid = tuple(sorted(set(alphas)))
        if grid[:1] != (0.0,) or len(grid) < 2:
            raise ValueError(f"alphas {list(alphas)} must hold 0 (the unsteered cell) and at least one push")
        return grid

    @field_validator("modes")
    @classmethod
    def _modes(cls, modes: tuple[str, ...]) -> tuple[str, ...]:
        if not modes or len(set(modes)) != len(modes):
            raise ValueError(f"modes {list(modes)}: give add and/or clamp, each once")
        return modes

    @field_validator("envs_per_worker")
    @classmethod
    def _envs_per_worker(cls, envs: int | None) -> int | None:
        if envs is not None and not 1 <= envs <= MAX_ENVS_PER_WORKER:
            raise ValueError(f"envs_per_worker {envs}: expected a positive integer up to {MAX_ENVS_PER_WORKER} (LIBERO "
                             f"envs in one process), or null for min({DEFAULT_ENVS_PER_WORKER}, the chunk's episodes)")
        return envs

    @field_validator("workers")
    @classmethod
    def _workers(cls, workers: int | None) -> int | None:
        if workers is not None and not 1 <= workers <= MAX_WORKERS:
            raise ValueError(f"workers {workers}: expected 1 to {MAX_WORKERS} simulation processes on this machine, "
                             "or null for one per usable core")
        return workers

    def lockstep_envs(self, episodes: int) -> int:
        """Return how many envs a task run of `episodes` episodes steps in lockstep (no more than it has episodes)."""
        return min(self.envs_per_worker or DEFAULT_ENVS_PER_WORKER, episodes)

    @field_validator("policy")
    @classmethod
    def _policy(cls, policy: str) -> str:
        if policy != "local" and not policy.startswith(("ws://", "wss://")):
            raise ValueError(f"policy {policy!r}: expected \"local\" or the ws:// address of `latent-steering serve`")
        return policy

    @model_validator(mode="after")
    def _unique_sides(self) -> RolloutSettings:
        if not self.sides or len(set(self.sides)) != len(self.sides):
            raise ValueError(f"sides {list(self.sides)}: give positive and/or negative, each once")
        return self

    @property
    def pushes(self) -> tuple[float, ...]:
        """Return the α values above 0."""
        return self.alphas[1:]

    @property
    def init_states(self) -> tuple[int, ...]:
        """Return the initial-state indices every cell runs."""
        return tuple(range(self.first_init_state, self.first_init_state + self.episodes))

