"""Phase 4 tasks: the dose-response of one (pair, layer) on the policy (GPU), the per-layer summary and the
comparison of the two pathways (language model vs action expert)."""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

from prefect import get_run_logger, task

from steering_core import layout
from steering_core.capture import CaptureSettings
from steering_core.data.contrast import read_manifest
from steering_core.data.split import read_split
from steering_core.evaluate import report
from steering_core.evaluate import run as evaluate_run
from steering_core.evaluate.settings import EvaluateSettings
from steering_core.identity import code_version, plain
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import read_json, sha256_json
from tasks.artifacts import ProgressArtifact, artifact_key
from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS
from tasks.capture import GPU_TAG, concept_rows, episode_sources, model_inputs
from tasks.results import RESULTS
from tasks.retries import GPU_RETRIES, GPU_RETRY_DELAYS, retry_if, transient_gpu

_PAIR_OUTPUTS = (f"{layout.DOSE_RESPONSE_FILE}.json", f"{layout.DOSE_RESPONSE_FILE}.safetensors",
                 layout.EFFICACY_PLOT, layout.SHIFT_PLOT, layout.TRAJECTORY_PLOT)


def folder_digests(path: Path) -> dict[str, str]:
    """Return {file: sha256} of every file directly in a folder."""
    return {p.name: file_digest(p) for p in sorted(path.iterdir()) if p.is_file()}


def slice_digests(path: Path) -> list[str]:
    """Return the digests of a concept slice's .pt and, when present, of the .safetensors beside it (what is read)."""
    tensors = path.with_suffix(".safetensors")
    return [file_digest(path)] + ([file_digest(tensors)] if tensors.is_file() else [])


def manifest_content(path: Path) -> Any:
    """Return a manifest's axis and segments: not its dataset record, whose fingerprint follows every new demo."""
    manifest = read_manifest(path)
    return {"axis": plain(manifest.axis), "segments": [plain(segment) for segment in manifest.segments]}


def job_inputs(job: evaluate_run.EvaluateJob) -> dict[str, Any]:
    """Return what one evaluation reads, by content: its pair's vectors, slices, windows, split and frames.

    Other pairs' files never enter, so a refreshed vector re-evaluates only its own pair.
    """
    split = read_split(job.split)
    episodes = sorted({e for task in (job.positive, job.negative) for e in split.evaluation_episodes(task)})
    return {
        "job": job.model_dump(mode="json", exclude={"manifest", "concept_map", "split", "positive_slice",
                                                    "negative_slice", "directions", "dataset_root"}),
        # the expert's direction is the mean difference of its slices, digested below
        "directions": folder_digests(job.directions) if job.directions is not None else None,
        "slices": [slice_digests(job.positive_slice), slice_digests(job.negative_slice)],
        "manifest": manifest_content(job.manifest),
        "windows": concept_rows(str(job.concept_map)),
        "split": file_digest(job.split),
        "frames": episode_sources({"dataset_root": str(job.dataset_root), "episodes": episodes}),
    }


def settings_inputs(settings: EvaluateSettings) -> dict[str, Any]:
    """Return the settings that change an evaluation's numbers beyond rounding (not whether the policy runs compiled)."""
    return plain(settings.model_dump(mode="json", exclude={"compiled"}))


def evaluation_identity(job: evaluate_run.EvaluateJob, model: CaptureSettings, settings: EvaluateSettings) -> str:
    """Return the digest of what one evaluation reads and how (the task's cache key without its output folder).

    Recorded with the outputs: a second run that missed the cache (it started before the first one finished)
    waits for the folder's lock, then reuses the folder when it records this identity.
    """
    inputs = job_inputs(job)
    inputs["job"].pop("output_dir")
    return sha256_json({"code": code_version("steering_core.evaluate.run"), "job": inputs, "model": model_inputs(model),
                        "settings": settings_inputs(settings)})


@task(
    name="evaluate-steering",
    task_run_name="evaluate {job.pair} {job.label}",
    tags=[GPU_TAG],
    cache_policy=content_key("steering_core.evaluate.run", job=job_inputs, model=model_inputs,
                             settings=settings_inputs),
    retries=GPU_RETRIES, retry_delay_seconds=GPU_RETRY_DELAYS, retry_condition_fn=retry_if(transient_gpu),
    **RESULTS,
)
def evaluate_pair(job: evaluate_run.EvaluateJob, model: CaptureSettings, settings: EvaluateSettings) -> dict:
    """Run one pair's dose-response on the policy at one layer; return its output files."""
    progress = ProgressArtifact(artifact_key("evaluate", job.pair, job.output_dir.parent.name), "policy calls",
                                f"evaluate {job.pair} at {job.label}")
    folder = evaluate_run.evaluate_job(job, model, settings, progress=progress,
                                       identity=evaluation_identity(job, model, settings))
    progress.finish()
    get_run_logger().info("%s %s: %s", job.pair, job.label, folder)
    return {OUTPUTS: [str(folder / name) for name in _PAIR_OUTPUTS], "folder": str(folder)}


def dose_responses(inputs: dict[str, Any]) -> dict[str, str]:
    """Return the digest of each pair's dose_response.json (all the layer summary reads)."""
    layer_path = Path(inputs["layer_path"])
    return {name: file_digest(layer_path / name / f"{layout.DOSE_RESPONSE_FILE}.json") for name in inputs["pair_names"]}


@task(
    name="evaluation-summary",
    task_run_name="evaluation summary {label}",
    cache_policy=content_key("steering_core.evaluate.report", derived={"pairs": dose_responses}),
    **RESULTS,
)
def evaluation_summary(label: str, layer_path: str, pair_names: list[str]) -> dict:
    """Write summary.md and summary.json of one layer's evaluation (`label`: `layer L`, `expert layer K`)."""
    md_path = report.write_layer_summary(Path(layer_path), pair_names)
    return {OUTPUTS: [str(md_path), str(md_path.with_name(layout.SUMMARY_JSON))], "summary": str(md_path)}


def evaluated_layers(inputs: dict[str, Any]) -> dict[str, str]:
    """Return the digest of every dose_response.json the pathways table reads."""
    root = Path(inputs["eval_root"])
    return {f"{layout.stream_layer_dir(layer, stream)}/{name}": file_digest(
                root / layout.stream_layer_dir(layer, stream) / name / f"{layout.DOSE_RESPONSE_FILE}.json")
            for layer, stream in inputs["layers"] for name in inputs["pair_names"]}


@task(
    name="evaluation-pathways",
    task_run_name="evaluation pathways",
    cache_policy=content_key("steering_core.evaluate.report", derived={"pairs": evaluated_layers}),
    **RESULTS,
)
def evaluation_pathways(eval_root: str, layers: list[tuple[int, str]], pair_names: list[str]) -> dict:
    """Write pathways.md and pathways.json: per pair, the best language-model direction vs the action expert's."""
    md_path = report.write_pathways(Path(eval_root), [(int(layer), stream) for layer, stream in layers], pair_names)
    return {OUTPUTS: [str(md_path), str(md_path.with_suffix(".json"))], "pathways": str(md_path)}


def ui_summary(layer_path: Path) -> str:
    """Return the Prefect artifact of one layer's evaluation: its notes, a five-column table (the full one is in
    summary.md) and each pair's efficacy plot inline as a PNG data URI."""
    summary = read_json(layer_path / layout.SUMMARY_JSON)
    lines = [f"# Steering evaluation, {summary['layer']}", ""] + [f"**{note}**" for note in summary["notes"]]
    lines += ["", "Efficacy: cross-fitted, 1 = reproduces the instruction swap; α in R / in vector units; p: vs the "
                  "random null.", "", "| pair, direction | α | efficacy [95% CI] | −/+ side | p |", "|---|---|---|---|---|"]
    for row in summary["rows"]:
        lines.append(f"| {row['pair']}, {row['direction']} | {report.alpha_text(row)} | "
                     f"{report.with_ci(row['efficacy'], row['efficacy_ci'])} | "
                     f"{report.fmt(row['efficacy_negative'])} / {report.fmt(row['efficacy_positive'])} | "
                     f"{report.fmt(row.get('p_random'))} |")
    for pair, plot in summary["plots"].items():
        encoded = base64.b64encode((layer_path / plot).read_bytes()).decode("ascii")
        lines += ["", f"![{pair}](data:image/png;base64,{encoded})"]
    lines += ["", f"Full table, request entries and shifts: `{layer_path / layout.SUMMARY_MD}`"]
    return "\n".join(lines) + "\n"
