"""The features of an SAE trained on a run's residuals, as the pipeline writes them: one scan of the layer's rows,
then the static feature page and the Neuronpedia export (`feature_page`, `neuronpedia`)."""

from __future__ import annotations

import os
from collections.abc import Collection, Iterator
from datetime import UTC, datetime
from pathlib import Path

from steering_core.devices import resolve_device
from steering_core.layout import FEATURE_PAGE_FILE, NEURONPEDIA_DIR, layer_dir
from steering_core.reporting.progress import ProgressCallback
from steering_core.sae.model import load_sae
from steering_core.sae.training.rows import RowSource
from steering_core.sae_quality.feature_page import sentencepiece_text, write_feature_page
from steering_core.sae_quality.feature_scan import RowBatch, scan_features
from steering_core.sae_quality.neuronpedia import write_neuronpedia
from steering_core.storage.schema import StrictModel

ROWS_PER_BATCH = 4096


class FeatureJob(StrictModel):
    """What one layer's feature page reads and where it writes."""

    layer: int
    run_dir: Path          # every episode's rows of the layer are scanned
    sae: Path              # the trained SAE's folder
    output_dir: Path       # saes/<run>/layerNN: features.html and neuronpedia/
    steering_layer: Path   # latent_steering/layerNN: the pairs' directions
    dataset_root: Path
    repo_id: str
    tokenizer: Path
    pair_top_k: int = 10
    examples: int = 8
    device: str = "auto"
    video_backend: str | None = None


def export_stamp() -> str:
    """Return the export's `createdAt`: $SOURCE_DATE_EPOCH (the reproducible-builds convention), else the epoch, so
    equal inputs give equal bytes whichever run wrote them."""
    return datetime.fromtimestamp(int(os.environ.get("SOURCE_DATE_EPOCH", "0")), UTC).isoformat()


def write_layer_features(job: FeatureJob, *, progress: ProgressCallback | None = None) -> tuple[Path, Path]:
    """Scan the layer's rows through the trained SAE; write the feature page and the Neuronpedia export.

    Returns (page, export folder).
    """
    sae = load_sae(job.sae, device=resolve_device(job.device))
    source = RowSource(job.run_dir, job.layer)
    scan = scan_features(source.sequential(ROWS_PER_BATCH), sae, top_n=job.examples, total_rows=source.rows,
                         progress=progress)

    def rows(episodes: Collection[int]) -> Iterator[RowBatch]:
        return RowSource(job.run_dir, job.layer, episodes=episodes).sequential(ROWS_PER_BATCH)

    text = sentencepiece_text(job.tokenizer)
    page = write_feature_page(
        job.output_dir / FEATURE_PAGE_FILE, scan, sae, rows, steering_layer=job.steering_layer,
        dataset_root=job.dataset_root, repo_id=job.repo_id, token_text=text, pair_top_k=job.pair_top_k,
        examples=job.examples, title=f"Features of the SAE trained on {layer_dir(job.layer)} of {job.run_dir.name}",
        video_backend=job.video_backend)
    export = write_neuronpedia(job.output_dir / NEURONPEDIA_DIR, scan, sae, rows, layer=job.layer, token_text=text,
                               examples=job.examples, created_at=export_stamp())
    return page, export
