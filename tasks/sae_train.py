"""SAE training tasks: an SAE trained on one layer of the run's residuals (GPU), its judgement against the borrowed
SAE (GPU: it runs the policy) and its feature page and Neuronpedia export (CPU, after the pairs' directions)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import get_run_logger, task

from steering_core.capture import CaptureSettings, shards
from steering_core.layout import NEURONPEDIA_DIR, layer_dir
from steering_core.sae.training.rows import RowSource
from steering_core.sae.training.settings import TrainSettings
from steering_core.sae.training.trainer import train_sae
from steering_core.sae_quality.feature_run import FeatureJob, write_layer_features
from steering_core.sae_quality.judge_run import JudgeJob, judge_job
from steering_core.storage.digests import file_digest
from steering_core.vectors.directions import SteeringSettings
from tasks.artifacts import ProgressArtifact, artifact_key
from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS
from tasks.capture import GPU_TAG, model_inputs
from tasks.evaluate import folder_digests
from tasks.results import RESULTS
from tasks.retries import GPU_RETRIES, GPU_RETRY_DELAYS, retry_if, transient_gpu
from tasks.sae import sae_inputs

SAE_FILES = ("cfg.json", "sae_weights.safetensors", "sparsity.safetensors", "training.json")
FIDELITY_FILES = ("fidelity.json", "fidelity.md", "fidelity.png")


def layer_rows(inputs: dict[str, Any]) -> Any:
    """Return the run identity and the (file, sha256) of the layer's shards: the rows training may read."""
    metadata = shards.read_run_metadata(inputs["run_dir"])
    return {"run": metadata.run.identity(),
            "shards": [(r.file, r.sha256) for r in metadata.layer_shards(inputs["layer"])]}


@task(
    name="train-sae",
    task_run_name="train SAE layer {layer}",
    tags=[GPU_TAG],
    cache_policy=content_key("steering_core.sae.training.trainer", "steering_core.sae.training.rows", derived={"rows": layer_rows}, ignore=("run_dir",)),
    retries=GPU_RETRIES, retry_delay_seconds=GPU_RETRY_DELAYS, retry_condition_fn=retry_if(transient_gpu),
    **RESULTS,
)
def train_layer_sae(layer: int, run_dir: str, out_dir: str, settings: TrainSettings,
                    heldout_episodes: list[int]) -> dict:
    """Train one layer's SAE on the run's rows, held-out episodes left out (resuming a killed training); return
    its folder."""
    source = RowSource(Path(run_dir), layer, exclude=heldout_episodes)
    progress = ProgressArtifact(artifact_key("train-sae", Path(run_dir).name, layer_dir(layer)), "rows",
                                 f"train the {settings.architecture} SAE of {layer_dir(layer)} on {run_dir}")
    folder = train_sae(source, Path(out_dir), settings, layer=layer, progress=progress)
    progress.finish()
    get_run_logger().info("SAE of %s trained on %d rows of %d episodes (%d held out): %s", layer_dir(layer),
                          source.rows, len(source.episodes), len(heldout_episodes), folder)
    return {OUTPUTS: [str(folder / name) for name in SAE_FILES], "sae": str(folder)}


def judged_inputs(inputs: dict[str, Any]) -> Any:
    """Return what a judgement reads by content: the trained SAE, the layer's shards, the pair's manifest and
    concept map, the borrowed SAE."""
    job: JudgeJob = inputs["job"]
    pair = job.pair
    return {
        "trained": folder_digests(job.trained),
        "rows": layer_rows({"run_dir": job.run_dir, "layer": job.layer}),
        "pair": None if pair is None else [file_digest(pair.manifest), file_digest(pair.concept_map)],
        "borrowed": None if inputs["borrowed"] is None else sae_inputs(inputs["borrowed"]),
    }


@task(
    name="judge-sae",
    task_run_name="judge SAE {job.output_dir.name}",
    tags=[GPU_TAG],
    cache_policy=content_key("steering_core.sae_quality.judge_run", model=model_inputs,
                             derived={"content": judged_inputs}, ignore=("borrowed",)),
    retries=GPU_RETRIES, retry_delay_seconds=GPU_RETRY_DELAYS, retry_condition_fn=retry_if(transient_gpu),
    **RESULTS,
)
def judge_trained_sae(job: JudgeJob, model: CaptureSettings, borrowed: SteeringSettings | None) -> dict:
    """Judge a trained SAE against the borrowed one on held-out rows and frames; return the fidelity files."""
    progress = ProgressArtifact(artifact_key("judge-sae", job.run_dir.name, layer_dir(job.layer)), "policy calls",
                                 f"judge the trained SAE of {layer_dir(job.layer)} on held-out frames")
    folder = judge_job(job, model, borrowed, progress=progress)
    progress.finish()
    return {OUTPUTS: [str(folder / name) for name in FIDELITY_FILES], "folder": str(folder)}


def featured_inputs(inputs: dict[str, Any]) -> Any:
    """Return what a feature page reads by content: the SAE, the layer's shards, the pairs' directions, the
    tokenizer."""
    job: FeatureJob = inputs["job"]
    steering = {folder.name: folder_digests(folder) for folder in sorted(job.steering_layer.iterdir())
                if folder.is_dir()}
    return {"sae": folder_digests(job.sae), "rows": layer_rows({"run_dir": job.run_dir, "layer": job.layer}),
            "directions": steering, "tokenizer": file_digest(job.tokenizer)}


@task(
    name="sae-features",
    task_run_name="features {job.output_dir.name}",
    cache_policy=content_key("steering_core.sae_quality.feature_run", derived={"content": featured_inputs}),
    **RESULTS,
)
def feature_page(job: FeatureJob) -> dict:
    """Write the feature page and the Neuronpedia export of one trained SAE; return their files."""
    progress = ProgressArtifact(artifact_key("features", job.run_dir.name, layer_dir(job.layer)), "rows",
                                 f"feature scan of the trained SAE of {layer_dir(job.layer)}")
    page, _ = write_layer_features(job, progress=progress)
    progress.finish()
    files = sorted(str(p) for p in (job.output_dir / NEURONPEDIA_DIR).rglob("*") if p.is_file())
    return {OUTPUTS: [str(page), *files], "page": str(page)}
