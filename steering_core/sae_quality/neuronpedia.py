"""Export an SAE's scanned features in Neuronpedia's export layout (gzipped JSONL batches), for its tooling.

The layout and record fields follow Neuronpedia's own exporter, `utils/neuronpedia-utils/neuronpedia_utils/
convert-saedashboard-to-neuronpedia-export.py` and the dataclasses of `neuronpedia_utils/db_models/`
(`feature.py`, `activation.py`, `source.py`, `source_set.py`, `model.py`) in github.com/hijohnnylin/neuronpedia
(read at the fork zazer0/neuronpedia, commits 4d6d6c6 and ab1e24c):

    <out>/<model_id>/<layer>-<source_set>/model.jsonl, sourceset.jsonl, source.jsonl   one record each
    <out>/<model_id>/<layer>-<source_set>/features/batch-<n>.jsonl.gz      one Feature record per latent
    <out>/<model_id>/<layer>-<source_set>/activations/batch-<n>.jsonl.gz   one Activation record per example

A Feature carries `frac_nonzero` (firing frequency), `maxActApprox` and the activation histogram
(`freq_hist_data_bar_values`: bin centres, `freq_hist_data_bar_heights`: counts); an Activation carries one
frame's prompt tokens (`tokens`) with the latent's value at each (`values`, `maxValue`, `maxValueTokenIndex`),
and `dataIndex` = the frame's dataset index. Fields that describe a language model's output vocabulary
(`pos_str`, `neg_str`, logit histograms) stay empty: π0.5's steered output is an action, not a token. The
exporter names ids with random cuids; here an activation's id is `<source>-<latent>-<rank>`, so equal inputs
give equal files.
"""

from __future__ import annotations

import gzip
import json
import logging
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from steering_core.sae.model import Sae
from steering_core.sae_quality.feature_page import RowsOfEpisodes, TokenText, token_strings
from steering_core.sae_quality.feature_scan import FeatureScan, FrameContext, example_frames, frame_contexts
from steering_core.storage.fileio import atomic_dir
from steering_core.storage.mirrors import portable

logger = logging.getLogger(__name__)

SOURCE_ID = "{layer}-{source_set}"  # Neuronpedia's source (layer) id
BATCH_FILE = "batch-{number}.jsonl.gz"
FEATURES_DIR, ACTIVATIONS_DIR = "features", "activations"
# Feature fields of Neuronpedia's dataclass that describe a language model (its vocabulary, neurons, other
# features' correlations): written empty, as its dataclass defaults them
UNUSED_FEATURE_LISTS = (
    "topkCosSimIndices", "topkCosSimValues", "neuron_alignment_indices", "neuron_alignment_values",
    "neuron_alignment_l1", "correlated_neurons_indices", "correlated_neurons_pearson", "correlated_neurons_l1",
    "correlated_features_indices", "correlated_features_pearson", "correlated_features_l1", "neg_str", "neg_values",
    "pos_str", "pos_values", "logits_hist_data_bar_heights", "logits_hist_data_bar_values", "decoder_weights_dist",
)


def write_neuronpedia(
    out_dir: Path,
    scan: FeatureScan,
    sae: Sae,
    rows: RowsOfEpisodes,
    *,
    layer: int,
    model_id: str = "pi05",
    source_set: str = "res-pi05",
    source_description: str = "Residual stream",
    token_text: TokenText | None = None,
    latents: Sequence[int] | None = None,
    examples: int | None = None,
    features_per_batch: int = 128,
    creator_id: str | None = None,
    dataset: str | None = None,
    created_at: str | None = None,
) -> Path:
    """Write the Neuronpedia export of `latents` (default: every latent that fired); return the source folder.

    Args:
        rows: episodes -> row batches of those episodes (a second pass reads only the examples' episodes).
        examples: activation records per latent (default all of the scan's top-N).
        creator_id: the Neuronpedia user id its importer files the records under (None: set on import).
        dataset: where the rows came from (the LeRobot repo id), recorded as the source's `dataset`.
        created_at: ISO timestamp of every record (default now, UTC).
    """
    if features_per_batch < 1:
        raise ValueError(f"features_per_batch is {features_per_batch}, expected at least 1")
    chosen = [int(i) for i in np.flatnonzero(scan.firing > 0)] if latents is None else [int(i) for i in latents]
    count = scan.top_n if examples is None else examples
    wanted = example_frames(scan, chosen, count)
    episodes = sorted({e["episode_index"] for latent in chosen for e in scan.examples(latent)[:count]})
    contexts = frame_contexts(rows(episodes), sae, wanted) if wanted else {}
    stamp = created_at or datetime.now(UTC).isoformat()
    source_id = SOURCE_ID.format(layer=layer, source_set=source_set)
    common = {"modelId": model_id, "layer": source_id, "creatorId": creator_id, "createdAt": stamp}
    target = Path(out_dir) / model_id / source_id
    with atomic_dir(target, overwrite=True) as staging:
        (staging / FEATURES_DIR).mkdir(parents=True)
        (staging / ACTIVATIONS_DIR).mkdir()
        _write_jsonl(staging / "model.jsonl", [_model(model_id, sae, common)])
        _write_jsonl(staging / "sourceset.jsonl", [_source_set(model_id, source_set, source_description, common)])
        _write_jsonl(staging / "source.jsonl", [_source(source_id, source_set, sae, scan, dataset, common)])
        for number, start in enumerate(range(0, len(chosen), features_per_batch)):
            batch = chosen[start : start + features_per_batch]
            name = BATCH_FILE.format(number=number)
            activations = [record for latent in batch
                           for record in _activations(scan, latent, count, contexts, token_text, source_id, common)]
            _write_jsonl(staging / ACTIVATIONS_DIR / name, activations)
            _write_jsonl(staging / FEATURES_DIR / name, [_feature(scan, latent, activations, common) for latent in batch])
    logger.info("Neuronpedia export of %d latents written to %s", len(chosen), target)
    return target


def read_jsonl_gz(path: Path) -> list[dict[str, Any]]:
    """Return the records of a gzipped JSONL file."""
    with gzip.open(path, "rt", encoding="utf-8") as handle:
        return [json.loads(line) for line in handle if line.strip()]


def _feature(scan: FeatureScan, latent: int, activations: list[dict[str, Any]], common: dict) -> dict[str, Any]:
    edges, counts = scan.histogram(latent)
    mine = [record["maxValue"] for record in activations if record["index"] == str(latent)]
    return {
        **common,
        "index": str(latent),
        "maxActApprox": max(mine, default=float(scan.top_values[latent, 0])),
        "hasVector": False,
        "vector": [],
        "vectorLabel": None,
        "vectorDefaultSteerStrength": 10,  # the Feature dataclass's default; used only by vector sources
        "hookName": None,
        **dict.fromkeys(UNUSED_FEATURE_LISTS, []),
        "frac_nonzero": float(scan.frequency()[latent]),
        "freq_hist_data_bar_values": [float(v) for v in (edges[:-1] + edges[1:]) / 2],
        "freq_hist_data_bar_heights": [int(c) for c in counts],
    }


def _activations(
    scan: FeatureScan, latent: int, count: int, contexts: dict[int, FrameContext], token_text: TokenText | None,
    source_id: str, common: dict,
) -> list[dict[str, Any]]:
    records = []
    for rank, example in enumerate(scan.examples(latent)[:count]):
        context = contexts.get(example["index"])
        if context is None:  # its rows were not in the second pass: the peak token alone
            ids, values = np.array([example["token_id"]]), np.array([example["value"]], dtype=np.float32)
        else:
            ids, values = context.token_id, context.values(latent)
        peak = int(np.argmax(values))
        records.append({
            **common,
            "id": f"{source_id}-{latent}-{rank}",
            "index": str(latent),
            "tokens": token_strings(ids, token_text),
            "values": [float(v) for v in values],
            "maxValue": float(values[peak]),
            "maxValueTokenIndex": peak,
            "minValue": float(values.min()),
            "dataIndex": str(example["index"]),
            "dataSource": f"episode {example['episode_index']} frame {example['frame_index']}",
            "dfaValues": [], "dfaTargetIndex": None, "dfaMaxValue": None, "lossValues": [],
            "logitContributions": None, "binMin": None, "binMax": None, "binContains": None,
            "qualifyingTokenIndex": None,
        })
    return records


def _model(model_id: str, sae: Sae, common: dict) -> dict[str, Any]:
    return {"id": model_id, "instruct": False, "creatorId": common["creatorId"], "displayNameShort": model_id,
            "displayName": model_id, "dimension": sae.cfg.d_in, "visibility": "PUBLIC", "inferenceEnabled": False,
            "createdAt": common["createdAt"], "updatedAt": common["createdAt"]}


def _source_set(model_id: str, source_set: str, description: str, common: dict) -> dict[str, Any]:
    return {"modelId": model_id, "name": source_set, "creatorId": common["creatorId"], "hasDashboards": True,
            "visibility": "PUBLIC", "description": description, "createdAt": common["createdAt"]}


def _source(source_id: str, source_set: str, sae: Sae, scan: FeatureScan, dataset: str | None,
            common: dict) -> dict[str, Any]:
    return {"id": source_id, "modelId": common["modelId"], "setName": source_set, "creatorId": common["creatorId"],
            "hasDashboards": True, "inferenceEnabled": False, "saelensConfig": json.dumps(portable(sae.cfg.model_dump(mode="json"))),
            "visibility": "PUBLIC", "num_prompts": scan.frames, "dataset": dataset, "createdAt": common["createdAt"]}


def _write_jsonl(path: Path, records: list[dict[str, Any]]) -> None:
    """Write records one JSON object a line; gzip (mtime 0, so equal records give equal bytes) for `.gz` names."""
    text = "".join(json.dumps(record, sort_keys=True, allow_nan=False) + "\n" for record in records).encode("utf-8")
    path.write_bytes(gzip.compress(text, compresslevel=5, mtime=0) if path.suffix == ".gz" else text)
