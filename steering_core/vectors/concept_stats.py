"""Streaming statistics of one concept's residuals through an SAE: the only pass over a concept's rows.

Rows are read from the concept file's memory map in batches, encoded and decoded, and only sums are
kept (latent sum, firing counts, residual sum, row norms and squared norms, reconstruction error), so memory stays
at one batch of latents whatever the row count. The statistics go to
`<output-root>/layerNN/concepts/<concept>-<hash>.safetensors|.json` and are reused while the concept
file and the SAE are unchanged.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from steering_core.capture.slicing import safe_file_name
from steering_core.devices import SAFETENSORS_DTYPES
from steering_core.remote.locks import output_lock
from steering_core.reporting.progress import Progress, ProgressCallback
from steering_core.sae.model import Sae
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import atomic_files, json_text, read_json, sha256_json
from steering_core.tensor_files import check_safetensors, load_torch_file

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
CONCEPTS_DIR = "concepts"
CONCEPT_STATS = "{stem}-{digest}"  # + .safetensors / .json; digest tells apart concepts sharing a label
RESIDUALS_KEY = "residuals"  # tensor name in the slicer's safetensors copies



@dataclass(frozen=True)
class ConceptSource:
    """A concept tensor file and the label it is reported under."""

    label: str
    path: Path


@dataclass(frozen=True)
class ConceptStats:
    """Streaming statistics of one concept file; latent fields are None without an SAE."""

    label: str
    path: Path
    count: int
    residual_mean: torch.Tensor  # (d_in,) float64
    residual_norm_sum: float | None  # sum of the rows' L2 norms (their mean is the α unit); None: older file
    latent_mean: torch.Tensor | None  # (d_sae,) float64
    firing_rate: torch.Tensor | None  # (d_sae,) float64, fraction of rows with f > 0
    fvu: float | None  # fraction of variance unexplained by the SAE reconstruction
    mean_l0: float | None  # mean number of active latents per row


class ConceptReader:
    """Memory-mapped rows of one concept file: `.pt` (rows, d_in) tensor or `.safetensors` `residuals`."""

    def __init__(self, path: Path) -> None:
        self.path = path
        if path.suffix == ".safetensors":
            check_safetensors(path)
            with safe_open(path, framework="pt", device="cpu") as handle:
                keys = list(handle.keys())
                self._key = RESIDUALS_KEY if RESIDUALS_KEY in keys else keys[0] if len(keys) == 1 else None
                if self._key is None:
                    raise ValueError(f"{path}: no tensor `{RESIDUALS_KEY}` and not a single tensor; found {keys}")
                rows = handle.get_slice(self._key)
                self.shape, self.dtype = tuple(rows.get_shape()), SAFETENSORS_DTYPES.get(rows.get_dtype())
            self._tensor = None
        else:
            tensor = load_torch_file(path, mmap=True)
            if not isinstance(tensor, torch.Tensor):
                raise ValueError(f"{path}: expected a (rows, d_in) tensor, found {type(tensor).__name__}")
            self._tensor, self.shape, self.dtype = tensor, tuple(tensor.shape), tensor.dtype

    @property
    def rows(self) -> int:
        """Return the row count (0 for a malformed shape)."""
        return self.shape[0] if self.valid_shape else 0

    @property
    def width(self) -> int:
        """Return the residual width, the last dimension."""
        return self.shape[-1]

    @property
    def valid_shape(self) -> bool:
        """Return whether the tensor is (rows, d_in), or (rows, 1, d_in) as the seed also accepted."""
        return len(self.shape) == 2 or (len(self.shape) == 3 and self.shape[1] == 1)

    def batches(self, batch_size: int) -> Iterator[torch.Tensor]:
        """Yield (<= batch_size, d_in) row blocks in file order, read from the memory map."""
        with contextlib.ExitStack() as stack:
            rows: Any = self._tensor
            if rows is None:
                rows = stack.enter_context(safe_open(self.path, framework="pt", device="cpu")).get_slice(self._key)
            for start in range(0, self.rows, batch_size):
                stop = min(start + batch_size, self.rows)
                yield rows[start:stop].reshape(stop - start, self.width)


def concept_stats_path(layer_path: Path, source: ConceptSource) -> Path:
    """Return the statistics file stem of one concept file (suffix-less; .safetensors and .json are added).

    The stem carries a digest of where the concept file is: relative to the output root holding `layer_path`
    when it lies there (so equal on every machine and every root), else its absolute path.
    """
    where, root = source.path.resolve(), layer_path.resolve().parent.parent
    digest = sha256_json(where.relative_to(root).as_posix() if root in where.parents else str(where))[:10]
    return layer_path / CONCEPTS_DIR / CONCEPT_STATS.format(stem=safe_file_name(source.label), digest=digest)


def encode_concept(
    source: ConceptSource,
    layer_path: Path,
    sae: Sae | None,
    *,
    batch_size: int = 512,
    reader: ConceptReader | None = None,
    progress: ProgressCallback | None = None,
) -> Path:
    """Stream one concept file through the SAE; write its statistics and return their `.json` path.

    A statistics file whose recorded source (size, mtime) and SAE fingerprint match is reused; the file is
    locked while it is computed, so a second run encoding the same concept waits, then reuses it.
    """
    reader = reader or ConceptReader(source.path)
    stem = concept_stats_path(layer_path, source)
    identity = _concept_identity(source, sae)
    json_path = stem.with_suffix(".json")
    with output_lock(json_path):  # another run encoding this concept: wait, then reuse its statistics
        if json_path.is_file() and _current(read_json(json_path), identity):
            logger.info("%s: statistics are current, reusing %s", source.path, json_path)
            return json_path
        sums = _Sums(sae, min(batch_size, max(reader.rows, 1)))
        with Progress(reader.rows, f"encode {source.label[:40]}", "row", callback=progress, logger=logger) as bar:
            for batch in reader.batches(batch_size):
                sums.add(batch, source.path, start=bar.done)
                bar.update(len(batch))
        stats = sums.finish(source)
        tensors = {"residual_mean": stats.residual_mean}
        if sae is not None:
            tensors |= {"latent_mean": stats.latent_mean, "firing_rate": stats.firing_rate}
        record = json_text({
            "format_version": FORMAT_VERSION,
            "label": source.label,
            "identity": identity,
            "count": stats.count,
            "residual_norm_sum": stats.residual_norm_sum,
            "fvu": stats.fvu,
            "mean_l0": stats.mean_l0,
            "batch_size": batch_size,
            "tensors": stem.with_suffix(".safetensors").name,
        }, json_path)
        with atomic_files(stem.parent) as staging:  # the tensors and their record: both or neither
            save_file({name: tensor.contiguous() for name, tensor in tensors.items()},
                      staging / stem.with_suffix(".safetensors").name)
            (staging / json_path.name).write_text(record, encoding="utf-8")
    fidelity = "" if stats.fvu is None else f", FVU {stats.fvu:.3f}, mean L0 {stats.mean_l0:.1f}"
    logger.info("%s: %d rows%s", source.label, stats.count, fidelity)
    return json_path


def read_concept_stats(json_path: Path) -> ConceptStats:
    """Return the statistics written by `encode_concept`."""
    meta = read_json(json_path)
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{json_path}: format_version {meta.get('format_version')!r}, expected {FORMAT_VERSION}")
    tensors = load_file(json_path.with_name(meta["tensors"]))
    return ConceptStats(
        label=meta["label"],
        path=Path(meta["identity"]["path"]),
        count=meta["count"],
        residual_mean=tensors["residual_mean"],
        residual_norm_sum=meta.get("residual_norm_sum"),
        latent_mean=tensors.get("latent_mean"),
        firing_rate=tensors.get("firing_rate"),
        fvu=meta["fvu"],
        mean_l0=meta["mean_l0"],
    )


class _Sums:
    """Running float64 sums over batches: the only state kept while a concept streams.

    Sums stay on the SAE's device as tensors (no host sync per batch but the finiteness check). Per
    batch, large sums run in the input dtype and are added to float64 totals: a batch of 512 rows
    loses nothing that matters, while a float64 copy of every (n, d_sae) latent batch would cost as
    much as the decode product. Every batch is encoded and decoded into the same two buffers.
    """

    def __init__(self, sae: Sae | None, batch_size: int) -> None:
        self.sae = sae
        self.buffers = None if sae is None else (
            torch.empty(batch_size, sae.cfg.d_in, dtype=sae.dtype, device=sae.device),
            torch.empty(batch_size, sae.cfg.d_sae, dtype=sae.dtype, device=sae.device),
        )
        self.count = 0
        self.residual_sum: torch.Tensor | float = 0.0   # (d_in,) float64
        self.residual_sq: torch.Tensor | float = 0.0    # sum of squared norms, for the total variance
        self.norm_sum: torch.Tensor | float = 0.0       # sum of row norms, for the mean residual norm
        self.latent_sum: torch.Tensor | float = 0.0     # (d_sae,) float64
        self.firing: torch.Tensor | int = 0             # (d_sae,) float64: rows where each latent fired
        self.squared_error: torch.Tensor | float = 0.0  # sum of ||x - x_hat||^2

    def add(self, batch: torch.Tensor, path: Path, *, start: int) -> None:
        """Accumulate one (n <= batch_size, d_in) batch; raise if it holds NaN or inf."""
        sae = self.sae
        if sae is not None:
            batch = batch.to(sae.device)
        column_sum = batch.sum(dim=0, dtype=torch.float64)  # finite iff every value is (no float64 overflow)
        if not torch.isfinite(column_sum).all():
            raise ValueError(f"{path}: rows {start}..{start + len(batch) - 1} hold NaN or inf; re-run capture")
        self.count += len(batch)
        self.residual_sum = self.residual_sum + column_sum
        norms = torch.linalg.vector_norm(batch, dim=-1, dtype=torch.float64)
        self.residual_sq = self.residual_sq + norms.square().sum()
        self.norm_sum = self.norm_sum + norms.sum()
        if sae is None:
            return
        reconstruction, latents = sae.reconstruct(batch, tuple(buffer[: len(batch)] for buffer in self.buffers))
        self.latent_sum = self.latent_sum + latents.sum(dim=0).double()
        self.firing = self.firing + _fired(latents)
        error = reconstruction.sub_(batch)  # the reconstruction is this batch's own: its memory takes the error
        self.squared_error = self.squared_error + torch.linalg.vector_norm(error, dtype=torch.float64).square()

    def finish(self, source: ConceptSource) -> ConceptStats:
        """Return means and fidelity from the sums (all on CPU)."""
        mean = self.residual_sum.cpu() / self.count
        total_variance = float(self.residual_sq) - self.count * float(mean @ mean)
        has_latents = isinstance(self.latent_sum, torch.Tensor)
        firing = self.firing.cpu().double() if has_latents else None
        return ConceptStats(
            label=source.label,
            path=source.path,
            count=self.count,
            residual_mean=mean,
            residual_norm_sum=float(self.norm_sum),
            latent_mean=self.latent_sum.cpu() / self.count if has_latents else None,
            firing_rate=firing / self.count if has_latents else None,
            fvu=float(self.squared_error) / total_variance if has_latents and total_variance > 0 else None,
            mean_l0=float(firing.sum()) / self.count if has_latents else None,
        )


def _fired(latents: torch.Tensor) -> torch.Tensor:
    """Return (d_sae,) float64 counts of rows where each latent fired, overwriting `latents` (n, d_sae).

    Activations are >= 0, so sign() is 1 where a latent fired and 0 elsewhere; a row of ones times
    that matrix counts them (a BLAS product), several times faster than count_nonzero's boolean pass.
    Counts stay exact: at most n per batch, summed in float32 (bf16/fp16 latents are widened first).
    """
    signs = latents.sign_() if latents.dtype in (torch.float32, torch.float64) else latents.sign().float()
    return (torch.ones(len(signs), dtype=signs.dtype, device=signs.device) @ signs).double()


def _current(meta: Any, identity: dict[str, Any]) -> bool:
    """Return whether a statistics file was made from these inputs and holds every statistic read today."""
    return isinstance(meta, dict) and meta.get("identity") == identity and "residual_norm_sum" in meta


def _concept_identity(source: ConceptSource, sae: Sae | None) -> dict[str, Any]:
    """Return what a concept's statistics depend on: the file (path, content) and the SAE.

    The content counts by its sha256 (remembered per file version), not its mtime: outputs are the
    same bytes for the same inputs.
    """
    return {
        "path": str(source.path.resolve()),
        "bytes": source.path.stat().st_size,
        "sha256": file_digest(source.path),
        "sae": sae.fingerprint() if sae is not None else None,
    }
