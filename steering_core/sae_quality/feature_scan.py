"""What each SAE latent responds to: one streaming pass over a layer's residual rows, in bounded memory.

Per latent, `scan_features` keeps the top-N activating *frames* (a frame is the rows sharing a dataset
`index`; its activation is the largest over its tokens, and the row where it peaks is kept with its
columns: index, episode_index, frame_index, token_position, token_id), an activation histogram of the rows
where it fires, its firing count and its activation sum. Memory is O(d_sae * (top_n + bins)) plus one batch,
whatever the number of rows. Ties between frames go to the lower `index`, so the result does not depend
on how the rows are batched.

Rows arrive as `(rows (b, d_in) float, columns)` batches (`RowSource.sequential` yields them), the rows of a
frame next to each other (shards are sorted by (index, token_position)); the trailing frame of a batch is
held back until the next batch shows it complete.

Histogram: latent l's `bins` equal bins cover [0, 2**e_l), e_l the smallest exponent with every activation
seen below 2**e_l. A larger activation doubles the range (as often as needed) and merges adjacent pairs of
bins, which is exact: with power-of-two ranges, bin(a, e + 1) = bin(a, e) // 2.

`frame_contexts` is the second, narrow pass: every token's activation of chosen latents in chosen frames,
for displaying and exporting the examples.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from steering_core.capture.shards import ROW_COLUMNS
from steering_core.reporting.progress import ProgressCallback
from steering_core.sae.model import Sae
from steering_core.storage.fileio import atomic_path
from steering_core.tensor_files import load_safetensors, save_safetensors

logger = logging.getLogger(__name__)

SCAN_FORMAT_VERSION = 1
RowBatch = tuple[torch.Tensor, dict[str, np.ndarray]]  # (rows (b, d_in) float, column -> (b,) int64)
EMPTY = -1  # column value of an unused top-N slot (its value is 0)
_NEVER = -(1 << 20)  # histogram exponent of a latent that never fired


@dataclass
class FeatureScan:
    """Per-latent statistics of one SAE over a set of residual rows; arrays indexed by latent first."""

    top_values: np.ndarray  # (d_sae, top_n) float32, descending per latent; 0 in unused slots
    top_columns: dict[str, np.ndarray]  # ROW_COLUMNS name -> (d_sae, top_n) int64 of the peak row; EMPTY if unused
    hist_counts: np.ndarray  # (d_sae, bins) int64: firing rows per bin
    hist_exponent: np.ndarray  # (d_sae,) int64: the bins cover [0, 2**e); _NEVER for latents that never fired
    firing: np.ndarray  # (d_sae,) int64: rows where the latent is > 0
    activation_sum: np.ndarray  # (d_sae,) float64: sum of the latent over all rows
    rows: int
    frames: int
    sae: str  # the SAE's name (release/id or folder)

    @property
    def d_sae(self) -> int:
        return int(self.top_values.shape[0])

    @property
    def top_n(self) -> int:
        return int(self.top_values.shape[1])

    @property
    def bins(self) -> int:
        return int(self.hist_counts.shape[1])

    def frequency(self) -> np.ndarray:
        """Return (d_sae,) float64: the fraction of rows where each latent fires."""
        return self.firing / max(self.rows, 1)

    def mean_activation(self) -> np.ndarray:
        """Return (d_sae,) float64: each latent's mean over all rows (zeros included)."""
        return self.activation_sum / max(self.rows, 1)

    def most_active(self, count: int) -> list[int]:
        """Return the `count` latents with the largest mean activation (firing ones only), largest first."""
        order = np.argsort(-self.activation_sum, kind="stable")
        return [int(latent) for latent in order[:count] if self.firing[latent] > 0]

    def histogram(self, latent: int) -> tuple[np.ndarray, np.ndarray]:
        """Return (edges (bins + 1,), counts (bins,)) of a latent's activations where it fires."""
        top = 0.0 if self.firing[latent] == 0 else float(np.ldexp(1.0, int(self.hist_exponent[latent])))
        return np.linspace(0.0, top, self.bins + 1), self.hist_counts[latent]

    def examples(self, latent: int) -> list[dict[str, Any]]:
        """Return a latent's top frames, strongest first: {"value", and every ROW_COLUMNS name} each."""
        used = self.top_columns["index"][latent] != EMPTY
        return [
            {"value": float(self.top_values[latent, slot]),
             **{name: int(self.top_columns[name][latent, slot]) for name in ROW_COLUMNS}}
            for slot in np.flatnonzero(used)
        ]

    def write(self, path: str | Path) -> Path:
        """Write the scan as one safetensors file (atomically); return its path."""
        tensors = {
            "top_values": self.top_values, "hist_counts": self.hist_counts, "hist_exponent": self.hist_exponent,
            "firing": self.firing, "activation_sum": self.activation_sum,
            **{f"top_{name}": values for name, values in self.top_columns.items()},
        }
        meta = {"format_version": SCAN_FORMAT_VERSION, "rows": self.rows, "frames": self.frames, "sae": self.sae}
        with atomic_path(path) as tmp:
            save_safetensors({k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in tensors.items()}, tmp,
                             metadata={"feature_scan": json.dumps(meta)})
        return Path(path)


def read_feature_scan(path: str | Path) -> FeatureScan:
    """Return the scan written by `FeatureScan.write`."""
    from safetensors import safe_open

    tensors = {name: tensor.numpy() for name, tensor in load_safetensors(path).items()}
    with safe_open(str(path), "pt") as handle:
        meta = json.loads((handle.metadata() or {}).get("feature_scan", "{}"))
    if meta.get("format_version") != SCAN_FORMAT_VERSION:
        raise ValueError(f"{path}: `format_version` is {meta.get('format_version')}, expected "
                         f"{SCAN_FORMAT_VERSION}; re-run the feature scan")
    return FeatureScan(
        top_values=tensors["top_values"], hist_counts=tensors["hist_counts"], hist_exponent=tensors["hist_exponent"],
        firing=tensors["firing"], activation_sum=tensors["activation_sum"],
        top_columns={name: tensors[f"top_{name}"] for name in ROW_COLUMNS},
        rows=int(meta["rows"]), frames=int(meta["frames"]), sae=str(meta["sae"]),
    )


def scan_features(
    batches: Iterable[RowBatch], sae: Sae, *, top_n: int = 16, bins: int = 32, total_rows: int | None = None,
    progress: ProgressCallback | None = None,
) -> FeatureScan:
    """Return the per-latent top-N frames, histograms and firing counts of `sae` over every row of `batches`.

    `bins` must be a power of two (exact histogram merging). `progress(rows done, total_rows)` after each batch.
    """
    if top_n < 1:
        raise ValueError(f"top_n is {top_n}, expected at least 1")
    if bins < 2 or bins & (bins - 1):
        raise ValueError(f"bins is {bins}, expected a power of two >= 2 (the histogram merges pairs of bins)")
    state = _ScanState(sae.cfg.d_sae, top_n, bins)
    held: RowBatch | None = None  # the trailing frame of the last batch, possibly incomplete
    for number, (rows, columns) in enumerate(batches):
        columns = _check_batch(rows, columns, sae, number)
        if held is not None:
            rows = torch.cat([held[0], rows.to(held[0].dtype)])
            columns = {name: np.concatenate([held[1][name], columns[name]]) for name in ROW_COLUMNS}
        cut = _last_frame_start(columns["index"])
        if cut:
            state.add(*_firing(sae, rows[:cut]), {name: values[:cut] for name, values in columns.items()})
        held = (rows[cut:], {name: values[cut:] for name, values in columns.items()})
        if progress is not None:
            progress(state.rows + len(held[0]), total_rows or 0)
    if held is not None and len(held[0]):
        state.add(*_firing(sae, held[0]), held[1])
    logger.info("feature scan of %s: %d rows, %d frames", sae.name, state.rows, state.frames)
    return state.result(sae.name)


@dataclass(frozen=True)
class FrameContext:
    """Every token of one frame: positions and ids (tokens,), and some latents' activations at each."""

    token_position: np.ndarray  # (tokens,) int64, ascending
    token_id: np.ndarray  # (tokens,) int64
    activations: dict[int, np.ndarray]  # latent -> (tokens,) float32

    def values(self, latent: int) -> np.ndarray:
        """Return (tokens,) float32: one latent's activation at every token of the frame."""
        return self.activations[latent]


def example_frames(scan: FeatureScan, latents: Iterable[int], count: int) -> dict[int, list[int]]:
    """Return dataset index -> the latents (of `latents`) having that frame among their first `count` examples."""
    wanted: dict[int, list[int]] = {}
    for latent in latents:
        for example in scan.examples(latent)[:count]:
            wanted.setdefault(example["index"], []).append(int(latent))
    return wanted


def frame_contexts(
    batches: Iterable[RowBatch], sae: Sae, wanted: Mapping[int, Collection[int]]
) -> dict[int, FrameContext]:
    """Return dataset index -> FrameContext for each frame of `wanted` (index -> latents) found in `batches`.

    Only rows of the wanted frames are encoded; give batches of just their episodes to read little.
    """
    frames = np.asarray(sorted(wanted), dtype=np.int64)
    parts: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    for number, (rows, columns) in enumerate(batches):
        columns = _check_batch(rows, columns, sae, number)
        keep = np.flatnonzero(np.isin(columns["index"], frames))
        if not keep.size:
            continue
        acts, index = _latents(sae, rows[torch.from_numpy(keep)]), columns["index"][keep]
        for frame in np.unique(index):
            mine = index == frame
            latents = sorted(wanted[int(frame)])
            parts.setdefault(int(frame), []).append(
                (columns["token_position"][keep][mine], columns["token_id"][keep][mine], acts[mine][:, latents]))
    contexts = {}
    for frame, pieces in parts.items():
        position = np.concatenate([piece[0] for piece in pieces])
        order = np.argsort(position, kind="stable")
        acts = np.concatenate([piece[2] for piece in pieces])[order]
        contexts[frame] = FrameContext(
            token_position=position[order], token_id=np.concatenate([piece[1] for piece in pieces])[order],
            activations={latent: acts[:, j] for j, latent in enumerate(sorted(wanted[frame]))})
    return contexts


class _ScanState:
    """The running statistics of `scan_features`; `add` takes the latents of whole frames."""

    def __init__(self, d_sae: int, top_n: int, bins: int):
        self.d_sae, self.top_n, self.bins, self.log2_bins = d_sae, top_n, bins, bins.bit_length() - 1
        self.top_values = np.zeros((d_sae, top_n), dtype=np.float32)
        self.top_columns = {name: np.full((d_sae, top_n), EMPTY, dtype=np.int64) for name in ROW_COLUMNS}
        self.hist_counts = np.zeros((d_sae, bins), dtype=np.int64)
        self.hist_exponent = np.full(d_sae, _NEVER, dtype=np.int64)
        self.firing = np.zeros(d_sae, dtype=np.int64)
        self.activation_sum = np.zeros(d_sae, dtype=np.float64)
        self.rows = self.frames = 0

    def add(self, row: np.ndarray, latent: np.ndarray, value: np.ndarray, columns: dict[str, np.ndarray]) -> None:
        """Fold in the firing (row, latent, value) triplets of complete frames, and the frames' (rows,) columns."""
        index = columns["index"]
        frame = np.concatenate([[0], np.cumsum(index[1:] != index[:-1])])  # (rows,) frame number in this batch
        self.rows += len(index)
        self.frames += int(frame[-1]) + 1
        self.firing += np.bincount(latent, minlength=self.d_sae)
        self.activation_sum += np.bincount(latent, weights=value.astype(np.float64), minlength=self.d_sae)
        self._add_histogram(latent, value)
        # only a row at least as strong as its latent's current N-th frame can enter the top-N
        strong = np.flatnonzero(value >= self.top_values[latent, -1])
        row, latent, value = row[strong], latent[strong], value[strong]
        if not strong.size:
            return
        # per (frame, latent): the row where the latent peaks (ties: the frame's first such row)
        key = frame[row] * self.d_sae + latent
        order = np.lexsort((row, -value, key))
        first = order[np.concatenate([[True], key[order][1:] != key[order][:-1]])]
        self._add_top(latent[first], value[first], {name: values[row[first]] for name, values in columns.items()})

    def _add_histogram(self, latent: np.ndarray, value: np.ndarray) -> None:
        """Widen each latent's range to cover its new activations (merging bins), then count them."""
        peak = np.zeros(self.d_sae, dtype=np.float64)
        np.maximum.at(peak, latent, value.astype(np.float64))
        exponent = np.where(peak > 0, np.frexp(peak)[1], _NEVER)  # peak < 2**exponent
        grown = np.maximum(self.hist_exponent, exponent)
        shift = np.minimum(grown - self.hist_exponent, self.log2_bins)
        for step in np.unique(shift[(shift > 0) & (self.hist_exponent != _NEVER)]):
            rows = np.flatnonzero((shift == step) & (self.hist_exponent != _NEVER))
            merged = self.hist_counts[rows].reshape(len(rows), self.bins >> step, 1 << step).sum(axis=2)
            self.hist_counts[rows] = 0
            self.hist_counts[rows, : self.bins >> step] = merged
        self.hist_exponent = grown
        slot = np.floor(np.ldexp(value.astype(np.float64), self.log2_bins - grown[latent])).astype(np.int64)
        self.hist_counts += np.bincount(latent * self.bins + slot, minlength=self.d_sae * self.bins).reshape(
            self.d_sae, self.bins)

    def _add_top(self, latent: np.ndarray, value: np.ndarray, columns: dict[str, np.ndarray]) -> None:
        """Merge candidate frames into the top-N of the latents they touch: (value desc, index asc)."""
        touched = np.unique(latent)
        n = self.top_n
        all_latent = np.concatenate([np.repeat(touched, n), latent])
        all_value = np.concatenate([self.top_values[touched].ravel(), value])
        all_columns = {name: np.concatenate([self.top_columns[name][touched].ravel(), columns[name]])
                       for name in ROW_COLUMNS}
        # an unused slot (value 0) sorts after every candidate (value > 0)
        order = np.lexsort((all_columns["index"], -all_value, all_latent))
        start = np.searchsorted(all_latent[order], touched)
        kept = order[(start[:, None] + np.arange(n)[None, :]).ravel()]  # every touched latent has >= n entries
        self.top_values[touched] = all_value[kept].reshape(-1, n)
        for name in ROW_COLUMNS:
            self.top_columns[name][touched] = all_columns[name][kept].reshape(-1, n)

    def result(self, sae_name: str) -> FeatureScan:
        return FeatureScan(
            top_values=self.top_values, top_columns=self.top_columns, hist_counts=self.hist_counts,
            hist_exponent=self.hist_exponent, firing=self.firing, activation_sum=self.activation_sum,
            rows=self.rows, frames=self.frames, sae=sae_name)


def _firing(sae: Sae, rows: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the (row, latent, value) of every activation > 0, each (firing,); found on the SAE's device.

    Only the firing entries leave the device: on a GPU the dense (rows, d_sae) activations never reach the CPU.
    """
    acts = sae.encode(rows).flatten()
    where = (acts > 0).nonzero().squeeze(1)
    value = acts[where].float().cpu().numpy()
    row, latent = np.divmod(where.cpu().numpy(), sae.cfg.d_sae)
    return row, latent, value


def _latents(sae: Sae, rows: torch.Tensor) -> np.ndarray:
    """Return (rows, d_sae) float32 activations on the CPU."""
    return sae.encode(rows).float().cpu().numpy()


def _last_frame_start(index: np.ndarray) -> int:
    """Return where the last run of equal `index` values starts (0 when the batch is one frame)."""
    changes = np.flatnonzero(index[1:] != index[:-1])
    return int(changes[-1]) + 1 if changes.size else 0


def _check_batch(rows: torch.Tensor, columns: dict[str, Any], sae: Sae, number: int) -> dict[str, np.ndarray]:
    """Return the batch's ROW_COLUMNS as int64 arrays after checking names and shapes against the rows."""
    problems = [f"column `{name}` is missing" for name in ROW_COLUMNS if name not in columns]
    if rows.ndim != 2 or rows.shape[1] != sae.cfg.d_in:
        problems.append(f"rows are {tuple(rows.shape)}, SAE {sae.name} expects (*, {sae.cfg.d_in})")
    out = {name: np.asarray(columns[name], dtype=np.int64) for name in ROW_COLUMNS if name in columns}
    problems += [f"column `{name}` is {values.shape}, expected ({len(rows)},)"
                 for name, values in out.items() if values.shape != (len(rows),)]
    if problems:
        raise ValueError(f"row batch {number}: " + "; ".join(problems))
    return out
