"""Evaluate one (pair, layer) from the files of phases 1-3 with the real π0.5 policy.

A job steers the language model (`stream="lm"`, phase 3's directions of layer L) or the action expert
(`stream="expert"`, the mean difference of the pair's `decision` slices at expert layer K). Frames are
read from the LeRobot dataset and preprocessed exactly as capture does (the checkpoint's cameras and prompt, the
state in it where the checkpoint's prompt carries it); the policy is loaded once per process and model (`load_policy`).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from steering_core import layout
from steering_core.capture.settings import CaptureSettings
from steering_core.capture.shards import read_run_metadata
from steering_core.data.concept_map import read_concept_map
from steering_core.data.contrast import read_manifest
from steering_core.data.split import read_split
from steering_core.evaluate.directions import decision_directions, pair_directions
from steering_core.evaluate.frames import EvalFrame, load_frames
from steering_core.evaluate.pair import PairInputs, evaluate_pair
from steering_core.evaluate.report import layer_label
from steering_core.evaluate.settings import EvaluateSettings
from steering_core.evaluate.sweep import Prompt, TaskPrompts
from steering_core.pairs import SIDES
from steering_core.pi05 import PromptTokenizer
from steering_core.pi05.spec import ModelSpec
from steering_core.pi05.steering import LAST_LM_LAYER, Stream
from steering_core.remote.locks import output_lock
from steering_core.reporting.progress import ProgressCallback
from steering_core.storage.fileio import read_json
from steering_core.storage.schema import StrictModel
from steering_core.vectors.directions import PathsRelativeTo, read_pairs_config, resolve_concept_path
from steering_core.vectors.pair_order import check_pair_order, manifest_concepts, task_concepts
from steering_core.vectors.pair_slices import check_pair_slices

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
    positive_slice: Path         # training slices of the layer (the α unit; expert: also the direction)
    negative_slice: Path
    directions: Path | None      # phase 3's latent_steering/layerNN/<pair>/; None for the expert
    dataset_root: Path
    repo_id: str
    output_dir: Path             # steering_eval/layerNN/<pair>/ or steering_eval/expert_layerKK/<pair>/
    stream: Stream = "lm"        # "expert": the action expert's layer `layer`, steered at every action token

    @property
    def label(self) -> str:
        """Return `layer L` or `expert layer K` (task run names, logs)."""
        return layer_label(self.layer, self.stream)


def pair_job(
    pairs_config: Path, pair: str, layer: int, *, relative_to: PathsRelativeTo = "auto", data_root: Path,
    steering_root: Path, dataset_root: Path, repo_id: str, output_root: Path,
) -> EvaluateJob:
    """Return the job of one pair of a seed-style pairs config, with the seed's layout under `data_root`.

    Slice paths of the pairs config resolve as the steer step resolves them (`resolve_concept_path`: `relative_to`
    cwd, config or auto); task texts come from the pair's manifest.
    """
    spec = next((p for p in read_pairs_config(pairs_config).pairs if p.name == pair), None)
    if spec is None:
        raise ValueError(f"{pairs_config}: no pair {pair!r}; run the SAE phase for layer {layer} first")
    job = _job(
        pair, layer, "lm", data_root, dataset_root, repo_id, output_root,
        slices=tuple(resolve_concept_path(path, pairs_config, relative_to)
                     for path in (spec.positive_path, spec.negative_path)),
        directions=steering_root / layout.layer_dir(layer) / pair,
    )
    labels = spec.positive_label, spec.negative_label
    check_pair_slices([(pair, labels, (job.positive_slice, job.negative_slice))], layer, pairs_config)
    check_pair_order(pair, labels, manifest_concepts(job.manifest, job.concept_map), job.manifest, pairs_config)
    return job


def expert_job(
    pair: str, layer: int, *, data_root: Path, slices_root: Path, dataset_root: Path, repo_id: str, output_root: Path,
) -> EvaluateJob:
    """Return the action-expert job of one pair at expert layer `layer`, with the seed's layout under `data_root`.

    `slices_root` is the pair's decision slices folder (`residuals/<pair>_decision_slices`, holding layerKK/).
    """
    return _job(pair, layer, "expert", data_root, dataset_root, repo_id, output_root,
                slices=lambda concepts: slice_files(slices_root / layout.layer_dir(layer), concepts), directions=None)


def _job(
    pair: str, layer: int, stream: Stream, data_root: Path, dataset_root: Path, repo_id: str, output_root: Path,
    *, slices: tuple[Path, Path] | Callable[[tuple[str, ...]], list[Path]], directions: Path | None,
) -> EvaluateJob:
    """Return a pair's job: its manifest, concept map and split under `data_root`, and its two slices
    (given, or found from the concepts of the manifest's two tasks)."""
    manifest_path = data_root / layout.MANIFEST_FILE.format(pair=pair)
    concept_map = data_root / layout.CONCEPT_MAP_FILE.format(pair=pair)
    manifest = read_manifest(manifest_path)
    if manifest.dataset is not None and (mismatch := manifest.dataset.mismatch(dataset_root)):
        raise ValueError(f"{manifest_path} does not match the dataset {dataset_root}: {mismatch}; evaluate on the "
                         "dataset the pair's manifest, concept map and slices were built from")
    tasks = tuple(manifest.axis.mean_delta_per_task)  # (task A, task B) = (positive, negative)
    if callable(slices):
        slices = tuple(slices(task_concepts(read_concept_map(concept_map), manifest, tasks, concept_map)))
    return EvaluateJob(
        pair=pair, layer=layer, positive=tasks[0], negative=tasks[1], manifest=manifest_path,
        concept_map=concept_map, split=data_root / layout.SPLIT_FILE.format(pair=pair),
        positive_slice=slices[0], negative_slice=slices[1], directions=directions, dataset_root=dataset_root,
        repo_id=repo_id, output_dir=output_root / layout.stream_layer_dir(layer, stream) / pair, stream=stream,
    )


def slice_files(folder: Path, concepts: tuple[str, ...]) -> list[Path]:
    """Return the .pt slice of each concept (task text) in one layer folder of slices, from its index.json."""
    index_path = folder / layout.SLICE_INDEX_FILE
    if not index_path.is_file():
        raise FileNotFoundError(f"{index_path}: no slices here; slice the decision run first")
    entries = read_json(index_path)["concepts"]
    missing = [c for c in concepts if c not in entries]
    if missing:
        raise ValueError(f"{index_path}: no slice of concept(s) {missing}; it holds {sorted(entries)}")
    return [folder / entries[c]["pt"] for c in concepts]


def run_config_job(config: RunConfig, pair: str, layer: int, stream: Stream = "lm") -> EvaluateJob:
    """Return the job of one (pair, layer) of a run config (the files its phases 1-3 wrote)."""
    if stream == "expert":
        return expert_job(config.pair(pair).name, layer, data_root=config.output_root,
                          slices_root=config.decision_slices_dir(config.pair(pair)),
                          dataset_root=config.dataset_root, repo_id=config.repo_id, output_root=config.eval_root)
    pairs_config = config.pairs_config_path(layer)
    return pair_job(pairs_config, config.pair(pair).name, layer, relative_to="config",
                    data_root=config.output_root, steering_root=config.steering_root,
                    dataset_root=config.dataset_root, repo_id=config.repo_id,
                    output_root=config.eval_root)


def check_model(model: CaptureSettings, layer: int, stream: Stream = "lm") -> None:
    """Raise ValueError for a model the evaluation cannot run: no checkpoint, a layer it lacks (or the last
    language-model layer, whose steering cannot change actions).

    The action expert has as many layers as the language model (spec 10.1).
    """
    if not Path(model.model.checkpoint).exists():
        raise FileNotFoundError(f"{model.model.checkpoint}: policy checkpoint not found; the evaluation runs the "
                                "policy, set model.checkpoint (or --checkpoint-path) to a converted pi0.5 checkpoint")
    if not 0 <= layer < model.arch.depth:
        what = "action-expert layer" if stream == "expert" else "layer"
        raise ValueError(f"{what} {layer} is not a layer of the policy: it has {model.arch.depth} decoder layers "
                         f"(0..{model.arch.depth - 1})")
    if stream == "lm" and layer == model.arch.depth - 1:
        raise ValueError(f"layer {layer}: {LAST_LM_LAYER}; evaluate layers 0..{layer - 1}")





def check_slices_split(slices: Sequence[Path], holdout: Sequence[int], split_path: Path) -> None:
    """Raise (one line naming both lists) unless each slice's index.json records the split's held-out episodes.

    Slices cut without the split (or before a new one) hold evaluation frames: they would enter d and R.
    """
    for path in slices:
        index_path = path.parent / layout.SLICE_INDEX_FILE
        index = read_json(index_path) if index_path.is_file() else {}
        recorded = index.get("settings", {}).get("holdout_episodes") if isinstance(index, dict) else None
        if recorded is None and holdout:
            raise ValueError(f"{path}: its slices record no held-out episodes (no {index_path}), but the split "
                             f"{split_path} holds out episodes {list(holdout)}; re-slice with `slice --split {split_path}`")
        if recorded is not None and sorted(recorded) != list(holdout):
            raise ValueError(f"{index_path}: slices cut holding out episodes {sorted(recorded)}, but the split "
                             f"{split_path} holds out episodes {list(holdout)}; re-slice with `slice --split {split_path}`")


def check_decision_run(run_dir: Path, layers: Sequence[int], model: CaptureSettings, num_steps: int,
                       where: str = "--decision-run") -> None:
    """Raise ValueError (one line naming `where`) unless `run_dir` holds `decision` rows of `layers` whose
    width is the checkpoint's action-expert width and whose sampler had `num_steps` steps. Reads headers only."""
    from steering_core.pi05.checkpoint import expert_arch_from_checkpoint

    run = read_run_metadata(run_dir).run
    expert = expert_arch_from_checkpoint(model.model.resolve(), model.arch)
    problems = []
    if run.token_type != "decision":
        problems.append(f"it holds `{run.token_type}` rows, expected `decision` rows (capture --token-type decision)")
    if missing := [layer for layer in layers if layer not in run.layers]:
        problems.append(f"it has expert layers {list(run.layers)}, not {missing}")
    if run.width != expert.width:
        problems.append(f"its rows are {run.width} wide, the checkpoint's action expert is {expert.width} wide "
                        "(an expert direction of the wrong width); capture the decision run with this checkpoint")
    if run.token_type == "decision" and run.inputs.get("num_steps") != num_steps:
        problems.append(f"it was captured with num_steps {run.inputs.get('num_steps')}, the evaluation samples "
                        f"with {num_steps}")
    if problems:
        raise ValueError(f"{where} {run_dir}: " + "; ".join(problems))


def slice_decision_run(run_dir: Path, pair: str, layers: Sequence[int], *, data_root: Path) -> Path:
    """Slice a `decision` run for one pair at expert `layers`, its held-out episodes left out (the pair's split
    under `data_root`); return the slices folder `residuals/<pair>_decision_slices` under `data_root`."""
    from steering_core.capture.slicing import SliceSettings, slice_concepts

    output = data_root / layout.DECISION_SLICES_DIR.format(pair=pair)
    split = read_split(data_root / layout.SPLIT_FILE.format(pair=pair))
    settings = SliceSettings(layers=tuple(layers), token_type="decision", holdout_episodes=split.holdout_episodes)
    slice_concepts(run_dir, data_root / layout.CONCEPT_MAP_FILE.format(pair=pair), output, settings)
    return output


@functools.lru_cache(maxsize=1)
def load_policy(model: ModelSpec, device: str, dtype: str | None, compiled: bool | None = None) -> Any:
    """Return the Pi05Policy of `model` (cached: one policy per process and model); `compiled`: its denoising step's
    setting (`Pi05Policy.from_checkpoint`)."""
    return model.load_policy(device, dtype, compiled)


def task_prompts(tokenizer: PromptTokenizer, positive: str, negative: str) -> TaskPrompts:
    """Return each side's prompt (1, T) tensors with the mask of its instruction tokens (where steering adds)."""
    prompts = {}
    for side, task in zip(SIDES, (positive, negative), strict=True):
        prompt = tokenizer.tokenize(task)
        prompts[side] = Prompt(*(torch.from_numpy(a)[None] for a in (prompt.ids, prompt.mask, prompt.instruction_mask())))
    return TaskPrompts(prompts)


@dataclass(frozen=True)
class PolicyPrompts:
    """Each side's task tokenised by the policy for a batch of frames: with each frame's state where the checkpoint's
    prompt carries it (lerobot's pi0.5), else the same prompt for every frame."""

    policy: Any  # Pi05Policy: `prompt_rows`
    tasks: dict[str, str]  # side -> task text

    def of(self, side: str, states: np.ndarray | None, count: int) -> Prompt:
        return Prompt(*self.policy.prompt_rows([self.tasks[side]] * count, states))


def evaluate_job(
    job: EvaluateJob,
    model: CaptureSettings,
    settings: EvaluateSettings,
    *,
    policy: Any = None,
    progress: ProgressCallback | None = None,
    identity: str | None = None,
) -> Path:
    """Evaluate one (pair, layer) and return its output folder; `policy` defaults to `load_policy(model, ...)`.

    The output folder is locked while it is written. `identity` (a digest of everything the job reads) is
    recorded in dose_response.json, and a folder recording the same one is kept: a second run waits, then reuses it.
    """
    check_model(model, job.layer, job.stream)
    with output_lock(job.output_dir):
        if identity is not None and evaluated_identity(job.output_dir) == identity:
            logger.info("%s %s: %s already holds this evaluation; reused", job.pair, job.label, job.output_dir)
            return job.output_dir
        return _evaluate(job, model, settings, policy, progress, identity)


def evaluated_identity(folder: Path) -> str | None:
    """Return the identity recorded by the evaluation in `folder`, or None (no finished evaluation there)."""
    try:
        record = read_json(folder / f"{layout.DOSE_RESPONSE_FILE}.json")
    except (OSError, ValueError):  # none yet, or damaged: evaluate again
        return None
    model = record.get("model") if isinstance(record, dict) else None
    return model.get("inputs") if isinstance(model, dict) else None


def _evaluate(
    job: EvaluateJob, model: CaptureSettings, settings: EvaluateSettings, policy: Any,
    progress: ProgressCallback | None, identity: str | None,
) -> Path:
    """Run the evaluation of `job` and write its output folder (`evaluate_job`, under its lock)."""
    manifest = read_manifest(job.manifest)
    pair = PairInputs(
        name=job.pair, tasks=(job.positive, job.negative), manifest=manifest,
        concept_map=read_concept_map(job.concept_map), split=read_split(job.split),
        slices=(job.positive_slice, job.negative_slice),
    )
    check_slices_split(pair.slices, pair.split.holdout_episodes, job.split)
    if job.stream == "expert":
        directions = decision_directions(pair.slices, job.pair, job.layer)
    else:
        directions = pair_directions(job.directions, settings.methods)
    policy = policy if policy is not None else load_policy(model.model, settings.device, settings.dtype,
                                                           settings.compiled)
    width = policy.expert_arch.width if job.stream == "expert" else model.arch.width
    from steering_core.pi05.steering import Steering

    def load(frames: Sequence[EvalFrame]) -> dict[str, Any]:
        return load_frames(job.dataset_root, job.repo_id, frames, model.arch.image_size, model.video_backend,
                           policy.cameras)

    return evaluate_pair(
        pair, {name: d.direction for name, d in directions.items()}, policy, Steering, load,
        PolicyPrompts(policy, dict(zip(SIDES, pair.tasks, strict=True))),
        layer=job.layer, width=width, settings=settings, output_dir=job.output_dir,
        metadata=policy.metadata if identity is None else {**policy.metadata, "inputs": identity},
        progress=progress, stream=job.stream,
        include_decoder_bias=job.stream == "lm" and bool(
            read_json(job.directions / layout.PAIR_SUMMARY_FILE).get("include_decoder_bias")),
        levels={name: d.levels for name, d in directions.items()},
    )
