"""Judge an SAE trained on a run's residuals, as the pipeline does it: the held-out rows of its layer, and the policy
on held-out frames of one pair (`steering_core.sae_quality.fidelity_report`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from steering_core.capture import CaptureSettings
from steering_core.data.concept_map import read_concept_map
from steering_core.data.contrast import read_manifest
from steering_core.devices import resolve_device
from steering_core.evaluate.frames import EvalFrame, load_frames, select_frames
from steering_core.evaluate.run import PolicyPrompts, load_policy
from steering_core.pairs import SIDES
from steering_core.reporting.progress import ProgressCallback
from steering_core.sae.model import load_sae
from steering_core.sae.training.heldout import heldout_split
from steering_core.sae.training.rows import RowSource
from steering_core.sae_quality.fidelity_report import ActionInputs, judge_layer
from steering_core.storage.schema import StrictModel
from steering_core.vectors.directions import SteeringSettings, load_steering_sae

ROWS_PER_BATCH = 4096


class JudgedPair(StrictModel):
    """The pair whose held-out frames the policy runs on."""

    name: str
    manifest: Path
    concept_map: Path


class JudgeJob(StrictModel):
    """What one layer's judgement reads and where it writes."""

    layer: int
    run_dir: Path                          # the residual run the SAE was trained on
    trained: Path                          # the trained SAE's folder
    heldout_episodes: tuple[int, ...]      # episodes the SAE never saw: its rows and frames are judged
    output_dir: Path                       # saes/<run>/layerNN: fidelity.json/.md/.png
    pair: JudgedPair | None = None         # None: no action change (row metrics only)
    dataset_root: Path
    repo_id: str
    frames: int = 8
    device: str = "auto"


def judge_job(job: JudgeJob, model: CaptureSettings, borrowed: SteeringSettings | None, *,
              progress: ProgressCallback | None = None) -> Path:
    """Judge the trained SAE of `job` (and the borrowed one of `borrowed`, when given); return the output folder."""
    device = resolve_device(job.device)
    trained = load_sae(job.trained, device=device)
    other = load_steering_sae(borrowed.model_copy(update={"device": job.device})) if borrowed is not None else None

    def rows() -> Any:
        return RowSource(job.run_dir, job.layer, episodes=job.heldout_episodes).sequential(ROWS_PER_BATCH)

    actions = _action_inputs(job, model, str(device)) if job.pair is not None else None
    return judge_layer(job.output_dir, job.layer, trained, rows, borrowed=other, actions=actions, progress=progress)


def _action_inputs(job: JudgeJob, model: CaptureSettings, device: str) -> ActionInputs:
    """Return the policy, the pair's held-out frames, their loader and the pair's prompts."""
    pair = job.pair
    manifest, concept_map = read_manifest(pair.manifest), read_concept_map(pair.concept_map)
    tasks = tuple(manifest.axis.mean_delta_per_task)  # each frame runs under its own task's prompt: order is free
    task_episodes: dict[str, set[int]] = {task: set() for task in tasks}
    for rows in concept_map.concepts.values():
        for row in rows:
            task = manifest.segments[row.segment_id].task
            if task in task_episodes:
                task_episodes[task].add(row.episode_index)
    split = heldout_split({task: sorted(e) for task, e in task_episodes.items()}, job.heldout_episodes)
    frames = select_frames(manifest, concept_map, split, tasks, job.frames)
    policy = load_policy(model.model, device, None)

    def load(batch: Sequence[EvalFrame]) -> dict[str, Any]:
        return load_frames(job.dataset_root, job.repo_id, batch, model.arch.image_size, model.video_backend,
                           policy.cameras)

    return ActionInputs(policy=policy, frames=frames, load=load,
                        prompts=PolicyPrompts(policy, dict(zip(SIDES, tasks, strict=True))))
