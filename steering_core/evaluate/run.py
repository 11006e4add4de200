"""Evaluate one (pair, layer) from the files of phases 1-3 with the real π0.5 policy.

Frames are read from the LeRobot dataset and preprocessed exactly as capture does (`libero_camera_slots`,
`PromptTokenizer`); the policy is loaded once per process and model (`load_policy`).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from steering_core import layout
from steering_core.capture.settings import CaptureSettings
from steering_core.data.concept_map import read_concept_map
from steering_core.data.contrast import read_manifest
from steering_core.data.split import read_split
from steering_core.evaluate.directions import pair_directions
from steering_core.evaluate.frames import EvalFrame, load_frames
from steering_core.evaluate.pair import PairInputs, evaluate_pair
from steering_core.evaluate.settings import EvaluateSettings
from steering_core.evaluate.sweep import Progress, Prompt
from steering_core.pi05 import PromptFormat, PromptTokenizer
from steering_core.sae.model import Sae
from steering_core.sae.steering import read_pairs_config
from steering_core.schema import StrictModel

if TYPE_CHECKING:
    from steering_core.config import RunConfig

logger = logging.getLogger(__name__)


class EvaluateJob(StrictModel):
    """The files one (pair, layer) evaluation reads, and where it writes."""

    pair: str
    layer: int
    positive: str                # task texts as the manifest spells them
    negative: str
    manifest: Path
    concept_map: Path
    split: Path
    positive_slice: Path         # training slices of the layer (the α unit)
    negative_slice: Path
    directions: Path             # phase 3's latent_steering/layerNN/<pair>/
    dataset_root: Path
    repo_id: str
    output_dir: Path             # steering_eval/layerNN/<pair>/


def pair_job(
    pairs_config: Path, pair: str, layer: int, *, base_dir: Path, data_root: Path, steering_root: Path,
    dataset_root: Path, repo_id: str, output_root: Path,
) -> EvaluateJob:
    """Return the job of one pair of a seed-style pairs config, with the seed's layout under `data_root`.

    Slice paths of the pairs config resolve against `base_dir`; task texts come from the pair's manifest.
    """
    spec = next((p for p in read_pairs_config(pairs_config).pairs if p.name == pair), None)
    if spec is None:
        raise ValueError(f"{pairs_config}: no pair {pair!r}; run the SAE phase for layer {layer} first")
    manifest = data_root / layout.MANIFEST_FILE.format(pair=pair)
    positive, negative = read_manifest(manifest).axis.mean_delta_per_task  # (task A, task B) = (positive, negative)
    return EvaluateJob(
        pair=pair, layer=layer, positive=positive, negative=negative, manifest=manifest,
        concept_map=data_root / layout.CONCEPT_MAP_FILE.format(pair=pair),
        split=data_root / layout.SPLIT_FILE.format(pair=pair),
        positive_slice=base_dir / spec.positive_path, negative_slice=base_dir / spec.negative_path,
        directions=steering_root / layout.layer_dir(layer) / pair, dataset_root=dataset_root, repo_id=repo_id,
        output_dir=output_root / layout.layer_dir(layer) / pair,
    )


def run_config_job(config: RunConfig, pair: str, layer: int) -> EvaluateJob:
    """Return the job of one (pair, layer) of a run config (the files its phases 1-3 wrote)."""
    pairs_config = config.pairs_config_path(layer)
    return pair_job(pairs_config, config.pair(pair).name, layer, base_dir=pairs_config.parent,
                    data_root=config.output_root, steering_root=config.steering_root,
                    dataset_root=config.dataset_root, repo_id=config.repo_id,
                    output_root=config.eval_root)


def check_model(model: CaptureSettings, layer: int) -> None:
    """Raise ValueError for a model the evaluation cannot run: no checkpoint, a layer it lacks, per-frame prompts."""
    if not Path(model.checkpoint_path).exists():
        raise FileNotFoundError(f"{model.checkpoint_path}: policy checkpoint not found; the evaluation runs the "
                                "policy, set model.checkpoint (or --checkpoint-path) to a converted pi0.5 checkpoint")
    if not 0 <= layer < model.arch.depth:
        raise ValueError(f"layer {layer} is not a layer of the policy: it has {model.arch.depth} decoder layers "
                         f"(0..{model.arch.depth - 1})")
    if model.prompt_format is not PromptFormat.LIBERO:
        raise ValueError(f"prompt_format {model.prompt_format.value!r}: the evaluation steers one prompt per task, "
                         "which needs the libero format (the state stays out of the prompt)")


@functools.lru_cache(maxsize=1)
def load_policy(model: CaptureSettings, device: str, dtype: str | None) -> Any:
    """Return the Pi05Policy of `model` (cached: one policy per process and model)."""
    from steering_core.pi05.policy import Pi05Policy

    return Pi05Policy.from_checkpoint(
        model.checkpoint_path, arch=model.arch, device=device, dtype=dtype, tokenizer_path=model.tokenizer_path,
        prompt_format=model.prompt_format, norm_stats_path=model.norm_stats_path, asset_id=model.norm_stats_asset_id,
    )


def task_prompts(tokenizer: PromptTokenizer, positive: str, negative: str) -> dict[str, Prompt]:
    """Return each side's prompt (1, T) tensors with the mask of its instruction tokens (where steering adds)."""
    prompts = {}
    for side, task in (("positive", positive), ("negative", negative)):
        prompt = tokenizer.tokenize(task)
        instruction = torch.zeros(1, len(prompt.ids), dtype=torch.bool)
        instruction[0, prompt.instruction[0] : prompt.instruction[1]] = True
        prompts[side] = Prompt(torch.from_numpy(prompt.ids)[None], torch.from_numpy(prompt.mask)[None], instruction)
    return prompts


def evaluate_job(
    job: EvaluateJob,
    model: CaptureSettings,
    settings: EvaluateSettings,
    sae: Sae | None,
    *,
    policy: Any = None,
    progress: Progress | None = None,
) -> Path:
    """Evaluate one (pair, layer) and return its output folder; `policy` defaults to `load_policy(model, ...)`."""
    check_model(model, job.layer)
    manifest = read_manifest(job.manifest)
    pair = PairInputs(
        name=job.pair, tasks=(job.positive, job.negative), manifest=manifest,
        concept_map=read_concept_map(job.concept_map), split=read_split(job.split),
        slices=(job.positive_slice, job.negative_slice),
    )
    directions = pair_directions(job.directions, sae, top_k=settings.top_k, random_count=settings.random_directions,
                                 seed=settings.seed)
    policy = policy if policy is not None else load_policy(model, settings.device, settings.dtype)
    from steering_core.pi05.steering import Steering

    tokenizer = PromptTokenizer(model.tokenizer_path, model.max_token_len, model.prompt_format)

    def load(frames: Sequence[EvalFrame]) -> dict[str, Any]:
        return load_frames(job.dataset_root, job.repo_id, frames, model.arch.image_size, model.video_backend)

    return evaluate_pair(
        pair, directions, policy, Steering, load, task_prompts(tokenizer, job.positive, job.negative),
        layer=job.layer, width=model.arch.width, settings=settings, output_dir=job.output_dir,
        metadata=policy.metadata, progress=progress,
    )
