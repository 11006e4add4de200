"""Per-layer tasks: pairwise statistics of every two pairs' directions, and the report (summary + plots)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import task

from steering_core import layout
from steering_core.sae.fidelity_table import FIDELITY_JSON
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import read_json
from steering_core.vectors import directions, report
from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS
from tasks.results import RESULTS


def pair_folders(inputs: dict[str, Any]) -> dict[str, dict[str, str]]:
    """Return the digests of every file in each pair folder of the layer (the directions the stats read)."""
    layer_path = Path(inputs["layer_path"])
    return {name: {p.name: file_digest(p) for p in sorted((layer_path / name).iterdir()) if p.is_file()}
            for name in inputs["pair_names"]}


def pairwise_digest(inputs: dict[str, Any]) -> str:
    """Return the digest of the layer's pairwise_stats.json."""
    return file_digest(Path(inputs["layer_path"]) / f"{layout.PAIRWISE_STATS_FILE}.json")


@task(
    name="pairwise-stats",
    task_run_name="pairwise stats layer {layer}",
    cache_policy=content_key("steering_core.vectors.directions", derived={"pairs": pair_folders}),
    **RESULTS,
)
def pairwise_stats(layer: int, layer_path: str, pair_names: list[str]) -> dict:
    """Write cosines and norms between every two pairs' directions of one layer; return the files."""
    pt_path = directions.compute_pairwise_stats(Path(layer_path), pair_names)
    return {OUTPUTS: [str(pt_path), str(pt_path.with_suffix(".json"))]}


def judgement_digest(inputs: dict[str, Any]) -> str | None:
    """Return the digest of the trained SAE's fidelity.json (None: the layer's SAE is not trained by the run)."""
    folder = inputs.get("trained_sae")
    return file_digest(Path(folder) / FIDELITY_JSON) if folder is not None else None


@task(
    name="write-report",
    task_run_name="report layer {layer}",
    cache_policy=content_key("steering_core.vectors.report", derived={"pairs": pair_folders, "pairwise": pairwise_digest,
                                                                  "judgement": judgement_digest}),
    **RESULTS,
)
def write_report(layer: int, layer_path: str, pair_names: list[str], top_k: int, trained_sae: str | None = None) -> dict:
    """Write summary.md, summary.json and the plots of one layer (with the judgement of its trained SAE, if any);
    return their paths."""
    md_path = report.write_report(Path(layer_path), top_k=top_k,
                                  trained_sae=Path(trained_sae) if trained_sae is not None else None)
    plots = [str(md_path.parent / name) for name in read_json(md_path.with_name(layout.SUMMARY_JSON))["plots"].values()]
    return {OUTPUTS: [str(md_path), str(md_path.with_name(layout.SUMMARY_JSON)), *plots]}
