"""The episodes an SAE trained on the run's residuals never sees, and the split its judgement reads frames from."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from steering_core.data.split import HoldoutSplit, TaskSplit


def sae_heldout_episodes(task_episodes: Mapping[str, Sequence[int]], splits: Sequence[HoldoutSplit],
                         fraction: float) -> tuple[int, ...]:
    """Return the episodes kept out of SAE training, from `task_episodes` (task -> the run's episodes of it).

    The pairs' held-out episodes when their splits hold any (the evaluation's frames must stay unseen);
    otherwise every k-th episode of each task with two or more (k = round(1 / fraction), the first included),
    so the SAE is still judged on rows it was not trained on.
    """
    present = {e for episodes in task_episodes.values() for e in episodes}
    held = sorted({e for split in splits for e in split.holdout_episodes} & present)
    if held:
        return tuple(held)
    step = max(2, round(1 / fraction))
    held = sorted(e for episodes in task_episodes.values() if len(episodes) >= 2 for e in sorted(episodes)[::step])
    if not held:
        raise ValueError(f"no task of the residual run has two episodes ({len(present)} episode(s) in all): training "
                         "an SAE and judging it on held-out rows needs a task with at least 2")
    return tuple(held)


def heldout_split(task_episodes: Mapping[str, Sequence[int]], heldout: Sequence[int]) -> HoldoutSplit:
    """Return the split whose held-out side is `heldout`: the frames an SAE's judgement runs the policy on.

    A task with none of its episodes held out (or all of them) is refused: its frames would be ones the SAE was
    trained on (or it has no training side).
    """
    held = set(heldout)
    sides = {task: (tuple(sorted(e for e in episodes if e not in held)), tuple(sorted(e for e in episodes if e in held)))
             for task, episodes in task_episodes.items()}
    if unusable := sorted(task for task, (train, out) in sides.items() if not train or not out):
        raise ValueError(f"tasks {unusable} need episodes on both sides of the SAE's held-out split (training and "
                         "judging); give them more episodes or change the held-out fraction")
    return HoldoutSplit(holdout_fraction=0.0,
                        tasks={task: TaskSplit(train=train, holdout=out) for task, (train, out) in sides.items()})
