"""The work a run's counts multiply into, checked against stated limits before the first step.

Each count has its own bound (the settings' `le=`), but their product is what takes days or exhausts memory:
the evaluation samples frames x noise seeds x (directions x α ≠ 0 + the unsteered and swapped references) action
chunks per (pair, layer) and holds them all in memory; the rollouts step cells x episodes x steps. Both are
computed from the settings alone (nothing allocated in proportion to a count) and refused with the estimate, the
limit and the settings that lower it.

The limits sit far above the field's scale. The default evaluation (32 frames, 4 seeds, 9 α, 6 methods x 2 modes
+ 32 random + 8 permuted directions) samples 53,504 chunks per (pair, layer); the limit, 10 million, allows 186
times that (e.g. 1,000 frames x 16 seeds x 52 directions x 12 α). The paper-scale closed-loop study (10 LIBERO tasks as 5 pairs,
50 episodes, 3 pushes with 4 random directions and the controls: 40 cells per (pair, layer), up to 520 steps)
steps about 1 million times per (pair, layer), 5 million per layer; the limit, a billion steps per run, allows
that at 200 layers, or 20 pairs at 10 layers with 200 episodes each.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from steering_core.rollout.grid import cells
from steering_core.rollout.protocol import max_steps

if TYPE_CHECKING:
    from steering_core.config import RunConfig
    from steering_core.evaluate.settings import EvaluateSettings
    from steering_core.rollout.settings import RolloutSettings

MAX_EVALUATION_SAMPLES = 10_000_000  # action chunks sampled per (pair, layer): frames x seeds x entries
MAX_EVALUATION_BYTES = 16 << 30      # the robot actions of those samples, held as float64 until the metrics
MAX_ROLLOUT_STEPS = 1_000_000_000    # simulator steps of a run's rollouts, every (pair, layer) and cell together
NAMED_METHODS = 6                    # every registered method: the most phase 3 gives a pair unless told fewer
ROBOT_DIMS = 7                       # robot action values per step (LIBERO's end-effector delta and gripper)


def evaluation_samples(settings: EvaluateSettings) -> int:
    """Return the action chunks the evaluation of one (pair, layer) samples at most: per frame (`max_frames`) and
    noise seed, the unsteered and instruction-swapped references and every direction at every α ≠ 0."""
    return settings.max_frames * settings.noise_seeds * (2 + evaluated_directions(settings) * (len(settings.alphas) - 1))


def evaluated_directions(settings: EvaluateSettings) -> int:
    """Return the directions of one (pair, layer): each method (`methods`, else every registered one) in each mode,
    and the nulls."""
    methods = len(settings.methods) if settings.methods is not None else NAMED_METHODS
    return methods * len(settings.modes) + settings.random_directions + settings.permutations


def evaluation_problems(settings: EvaluateSettings, action_horizon: int, where: str = "evaluate") -> list[str]:
    """Return the evaluation's work or memory over its limit, one line each naming the settings to lower."""
    samples = evaluation_samples(settings)
    methods = len(settings.methods) if settings.methods is not None else NAMED_METHODS
    product = (f"max_frames {settings.max_frames} x noise_seeds {settings.noise_seeds} x (2 + "
               f"{evaluated_directions(settings)} directions ({methods} methods x {len(settings.modes)} modes + "
               f"random_directions {settings.random_directions} + permutations {settings.permutations}) x "
               f"{len(settings.alphas) - 1} alphas besides 0)")
    lower = "lower max_frames, noise_seeds, alphas, methods, modes, random_directions or permutations"
    problems = []
    if samples > MAX_EVALUATION_SAMPLES:
        problems.append(f"{where}: an estimated {samples:,} action chunks sampled per (pair, layer) = {product}; "
                        f"expected at most {MAX_EVALUATION_SAMPLES:,}: {lower}")
    held = samples * action_horizon * ROBOT_DIMS * 8
    if held > MAX_EVALUATION_BYTES and not problems:
        problems.append(f"{where}: an estimated {held / 2**30:.1f} GiB of actions held per (pair, layer) = {product} "
                        f"x action_horizon {action_horizon} x {ROBOT_DIMS} x 8 bytes; expected at most "
                        f"{MAX_EVALUATION_BYTES >> 30} GiB: {lower}")
    return problems


def rollout_cells(settings: RolloutSettings, other_pairs: bool) -> int:
    """Return the cells of one (pair, layer) (`rollout.grid.cells`; `other_pairs`: the wrong concept has one)."""
    return len(cells("pair", 0, settings, ["other"] if other_pairs else []))


def rollout_problems(config: RunConfig, targets: list[tuple[str, int]] | None = None,
                     where: str = "rollout") -> list[str]:
    """Return the rollouts' simulator steps over their limit (all of `targets`, default the config's), naming the
    settings to lower; the steps of an episode are its suite's budget unless `rollout.max_steps` is set."""
    if config.rollout is None:
        return []
    settings = config.rollout.settings()
    targets = config.rollout_targets() if targets is None else targets
    layers = {layer: sum(at == layer for _, at in config.rollout_targets()) for _, layer in targets}
    steps = 0
    for name, layer in targets:
        tasks = config.rollout.pairs[name]
        budget = settings.max_steps or max(max_steps(tasks.positive.suite), max_steps(tasks.negative.suite))
        steps += rollout_cells(settings, layers[layer] > 1) * settings.episodes * budget
    if steps <= MAX_ROLLOUT_STEPS:
        return []
    return [f"{where}: an estimated {steps:,} simulator steps = {len(targets)} (pair, layer) x cells (sides, α, "
            f"{len(settings.methods)} methods x {len(settings.modes)} modes, random_directions "
            f"{settings.random_directions}, controls) x episodes {settings.episodes} x up to max_steps "
            f"{settings.max_steps or 'of the suite'} each; expected at most {MAX_ROLLOUT_STEPS:,}: lower "
            "rollout.episodes, alphas, methods, modes, random_directions, max_steps, or roll out fewer pairs or layers"]
