"""How well SAEs reconstruct held-out residual rows: FVU, L0, dead and dense latents, in one streaming pass.

FVU (fraction of variance unexplained) = Σ‖x − x̂‖² / Σ‖x − x̄‖², x̄ the mean of all held-out rows. The
denominator comes from float64 sums of rows shifted by the first batch's mean, so a large common offset
(residual streams have one) cancels before squaring instead of after.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import torch

from steering_core.sae.model import Sae

logger = logging.getLogger(__name__)

DENSE_FRACTION = 0.1  # a latent firing on more than this fraction of rows is dense
HISTOGRAM_EDGES = tuple(e / 4 for e in range(-28, 1))  # log10 firing frequency, quarter decades, 1e-7 .. 1

RowBatches = Iterable[Any] | Callable[[], Iterable[Any]]


@dataclass(frozen=True)
class RowFidelity:
    """One SAE's reconstruction of held-out rows."""

    rows: int
    fvu: float | None           # Σ‖x − x̂‖² / Σ‖x − x̄‖²; None when the rows do not vary
    l0: float                   # mean number of non-zero latents per row
    dead: int                   # latents that never fire on these rows
    dense: int                  # latents firing on more than DENSE_FRACTION of the rows
    d_sae: int
    firing_histogram: list[int]  # live latents per log10 firing-frequency bin (HISTOGRAM_EDGES)

    def as_json(self) -> dict[str, Any]:
        return asdict(self)


class _Sums:
    """Running float64 sums of one stream of rows and one SAE's reconstruction of them."""

    def __init__(self, d_sae: int) -> None:
        self.squared_error = 0.0
        self.active = 0         # Σ over rows of the non-zero latents
        self.fired = torch.zeros(d_sae, dtype=torch.int64)

    def add(self, sae: Sae, rows: torch.Tensor, rows64: torch.Tensor) -> None:
        """Add the squared error, active latents and firing counts of the SAE on rows (b, d_in) on any device;
        `rows64` is the same rows in float64 on the CPU."""
        reconstruction, latents = sae.reconstruct(rows)
        self.squared_error += float((rows64 - reconstruction.double().cpu()).square().sum())
        nonzero = latents != 0
        self.active += int(nonzero.sum())
        self.fired += nonzero.sum(dim=0).cpu()

    def finish(self, rows: int, total_variance: float) -> RowFidelity:
        """Return the metrics over `rows` rows whose Σ‖x − x̄‖² is `total_variance`."""
        frequency = self.fired.double() / rows
        live = frequency[frequency > 0].log10().clamp(min=HISTOGRAM_EDGES[0], max=HISTOGRAM_EDGES[-1])
        histogram = torch.histogram(live, bins=torch.tensor(HISTOGRAM_EDGES, dtype=torch.float64)).hist
        return RowFidelity(
            rows=rows,
            fvu=self.squared_error / total_variance if total_variance > 0 else None,
            l0=self.active / rows,
            dead=int((self.fired == 0).sum()),
            dense=int((frequency > DENSE_FRACTION).sum()),
            d_sae=int(self.fired.numel()),
            firing_histogram=[int(c) for c in histogram],
        )


def row_batches(batches: RowBatches) -> Iterable[torch.Tensor]:
    """Return the row tensors of `batches`: an iterable (or a function returning one) of (b, d) float tensors,
    or of (rows, columns) pairs as `RowSource.sequential` yields them."""
    for batch in batches() if callable(batches) else batches:
        yield batch[0] if isinstance(batch, tuple) else batch


def row_fidelity(saes: Mapping[str, Sae], batches: RowBatches, *, where: str = "held-out rows") -> dict[str, RowFidelity]:
    """Return {name: RowFidelity} of every SAE on the same rows, read once.

    `batches`: (b, d_in) float rows (or (rows, columns) pairs), e.g. `RowSource(...).sequential(4096)` of the
    held-out episodes; `where` names them in errors.
    """
    widths = {name: sae.cfg.d_in for name, sae in saes.items()}
    if not saes:
        raise ValueError("row_fidelity: no SAE given")
    sums = {name: _Sums(sae.cfg.d_sae) for name, sae in saes.items()}
    count, shift, total, total_sq = 0, None, None, 0.0
    for rows in row_batches(batches):
        if rows.ndim != 2 or any(rows.shape[1] != w for w in widths.values()):
            raise ValueError(f"{where}: a batch is {tuple(rows.shape)}, expected (rows, d_in) with d_in "
                             f"{sorted(set(widths.values()))} (SAEs: {widths}); judge each SAE on its own layer's rows")
        if not bool(torch.isfinite(rows).all()):
            raise ValueError(f"{where}: rows {count}..{count + len(rows) - 1} hold NaN or Inf; re-capture the run")
        if not len(rows):
            continue
        rows64 = rows.double().cpu()
        if shift is None:
            shift = rows64.mean(dim=0)
            total = torch.zeros_like(shift)
        centred = rows64 - shift
        total += centred.sum(dim=0)
        total_sq += float(centred.square().sum())
        count += len(rows)
        for name, sae in saes.items():
            sums[name].add(sae, rows, rows64)
    if count == 0:
        raise ValueError(f"{where}: no rows; hold out episodes that the run captured")
    # Σ‖x − x̄‖² = Σ‖x − s‖² − n‖x̄ − s‖² for any shift s
    total_variance = total_sq - float(total.square().sum()) / count
    results = {name: s.finish(count, total_variance) for name, s in sums.items()}
    for name, result in results.items():
        logger.info("%s on %d %s: FVU %s, L0 %.1f, %d dead, %d dense", name, count, where, result.fvu, result.l0,
                    result.dead, result.dense)
    return results
