"""Phase 3 tasks: the seed's pairs config, per-concept SAE statistics, per-pair steering directions."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import task

from steering_core import layout
from steering_core.layout import layer_dir
from steering_core.sae.formats import HOOK_NAME
from steering_core.sae.registry import resolve_release
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import read_json, write_json
from steering_core.vectors import concept_stats, directions
from steering_core.vectors.directions import PairsConfig, PairSpec, SteeringSettings
from steering_core.vectors.methods.supplied import supplied_path
from tasks.artifacts import ProgressArtifact, artifact_key
from tasks.cache_keys import content_key
from tasks.cache_records import OUTPUTS
from tasks.results import RESULTS
from tasks.retries import IO_RETRIES, IO_RETRY_DELAYS, retry_if, transient_io

_SAE_FIELDS = ("layer", "device", "batch_size")  # settings that change concept statistics besides the SAE


def sae_files(source: str | None, sae_id: str | None, local_dir: Path | None) -> dict[str, str] | None:
    """Return {file: sha256} of an SAE given as a path (file or folder) or as a release; None for no SAE."""
    if source is None:
        return None
    path = Path(source).expanduser()
    if not path.exists():
        path = resolve_release(source, sae_id, local_dir=local_dir)
    files = [path] if path.is_file() else sorted(p for p in path.iterdir() if p.is_file())
    return {p.name: file_digest(p) for p in files}


def sae_inputs(settings: SteeringSettings) -> dict[str, Any]:
    """Return what concept statistics depend on: the SAE's files and the numeric settings."""
    sae_id = settings.sae_id or HOOK_NAME.format(layer=settings.layer)
    cfg_from = settings.sae_cfg_from
    return {
        "sae": sae_files(settings.sae, sae_id, settings.sae_dir),
        "sae_id": sae_id,
        "cfg_from": sae_files(cfg_from, sae_id, settings.sae_dir) if cfg_from else None,
        **{name: getattr(settings, name) for name in _SAE_FIELDS},
    }


_METHOD_FIELDS = ("include_decoder_bias", "methods", "top_k", "probe_folds", "probe_c", "effect_min_episodes",
                  "direction_file")


def direction_inputs(settings: SteeringSettings) -> dict[str, Any]:
    """Return what pair directions depend on besides the statistics: the SAE, the method settings and the supplied
    direction files (`file`) of the layer's pairs."""
    supplied = None
    if settings.direction_file and "file" in (settings.methods or ()):
        pairs = directions.read_pairs_config(settings.pairs_config).pairs
        files = [supplied_path(settings.direction_file, pair.name, settings.layer) for pair in pairs]
        supplied = {str(path): file_digest(path) if path.is_file() else None for path in files}
    return {**sae_inputs(settings), **{name: getattr(settings, name) for name in _METHOD_FIELDS},
            "supplied": supplied}


def stats_files(path: str) -> dict[str, str]:
    """Return the digests of a concept statistics file (.json), its tensors (.safetensors) and of the slice's
    safetensors copy it was made from (the rows and episodes the probe and sae_effect methods read)."""
    json_path = Path(path)
    digests = {"json": file_digest(json_path), "tensors": file_digest(json_path.with_suffix(".safetensors"))}
    slice_copy = Path(read_json(json_path)["identity"]["path"]).with_suffix(".safetensors")
    return digests | ({"slice": file_digest(slice_copy)} if slice_copy.is_file() else {})


@task(
    name="write-pairs-config",
    task_run_name="pairs config layer {layer}",
    cache_policy=content_key("steering_core.vectors.directions"),
    retries=IO_RETRIES, retry_delay_seconds=IO_RETRY_DELAYS, retry_condition_fn=retry_if(transient_io),
    **RESULTS,
)
def write_pairs_config(layer: int, pairs: PairsConfig, path: str) -> dict:
    """Write the seed's pairs config (layerNN_pairs.json) for one layer; return its path."""
    write_json(path, pairs.model_dump(mode="json"))
    return {OUTPUTS: [path]}


@task(
    name="encode-concept",
    task_run_name="encode {pair} {side} layer {layer}",
    cache_policy=content_key("steering_core.vectors.concept_stats", slice_path=file_digest, settings=sae_inputs),
    **RESULTS,
)
def encode_concept(pair: str, side: str, layer: int, label: str, slice_path: str, settings: SteeringSettings) -> dict:
    """Stream one concept's residuals through the layer's SAE; return the statistics file."""
    sae = directions.load_steering_sae(settings)
    layer_path = settings.output_root / layer_dir(settings.layer)
    source = concept_stats.ConceptSource(label=label, path=Path(slice_path))
    progress = ProgressArtifact(artifact_key("encode", pair, side, layer_dir(layer)), "rows",
                                 f"SAE statistics of {label!r} ({pair} {side}, {layer_dir(layer)})")
    stats = concept_stats.encode_concept(source, layer_path, sae, batch_size=settings.batch_size, progress=progress)
    progress.finish()
    return {OUTPUTS: [str(stats), str(stats.with_suffix(".safetensors"))], "stats": str(stats)}


@task(
    name="pair-directions",
    task_run_name="directions {pair.name} layer {layer}",
    cache_policy=content_key("steering_core.vectors.directions", positive_stats=stats_files, negative_stats=stats_files,
                             settings=direction_inputs),
    **RESULTS,
)
def pair_directions(pair: PairSpec, layer: int, positive_stats: str, negative_stats: str, settings: SteeringSettings) -> dict:
    """Write one pair's latent and residual directions; return the pair folder's summary file."""
    sae = directions.load_steering_sae(settings)
    layer_path = settings.output_root / layer_dir(settings.layer)
    folder = directions.compute_pair(pair, Path(positive_stats), Path(negative_stats), layer_path, sae, settings)
    summary = folder / layout.PAIR_SUMMARY_FILE
    return {OUTPUTS: [str(summary)], "folder": str(folder)}
