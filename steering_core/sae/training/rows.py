"""Residual rows of one layer of a capture run, streamed from its shards in order or shuffled.

The shuffle is a two-level one, so that memory stays bounded by `buffer_rows` whatever the run's size:
each epoch cuts every shard's selected rows into pieces of `buffer_rows // PIECES_PER_BUFFER` rows,
puts the pieces of all shards in a random order, fills buffers of at most `buffer_rows` rows with
consecutive pieces (so one buffer mixes rows of up to PIECES_PER_BUFFER places in the run), and
yields each buffer's rows in a random order. The piece order comes from a numpy generator seeded with
(seed, epoch), each buffer's row order from a torch generator seeded with (seed, epoch, buffer), so the stream is a pure function of (seed, buffer_rows):
a stream started at sample s skips the whole buffers before s without reading them and yields the
same rows as an uninterrupted one from s on.

Shards absent here under a mounted URL root stay in the bucket: `open_shard` reads them by ranges (each
open checks the object's size and ETag against its publication record, then reads the header, the row
columns and the rows asked for), so a buffer fetches its pieces' rows and never a whole run.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterator
from pathlib import Path

import numpy as np
import torch

from steering_core.capture.shards import METADATA_FILE, ShardRecord, open_shard, read_run_metadata
from steering_core.storage.fileio import sha256_json
from steering_core.storage.schema import describe_ranges

logger = logging.getLogger(__name__)

PIECES_PER_BUFFER = 64  # places of the run one shuffle buffer mixes
EPISODE = "episode_index"


class RowSource:
    """Residual rows of one layer of a capture run (any token type), read from its shards."""

    def __init__(
        self, run_dir: Path, layer: int, *, episodes: Collection[int] | None = None, exclude: Collection[int] = ()
    ) -> None:
        """Select the rows of `layer` in `episodes` (default all captured) minus `exclude`.

        One-line ValueError naming the file: no `metadata.json`, layer not captured, episodes (selected or
        excluded) not captured,
        a shard of another width than the run's, or no rows left after the selection.
        """
        self.run_dir, self.layer = Path(run_dir), int(layer)
        where = self.run_dir / METADATA_FILE
        try:
            metadata = read_run_metadata(self.run_dir)
        except FileNotFoundError as err:
            raise ValueError(str(err)) from None
        self.width, self.token_type = metadata.run.width, metadata.run.token_type
        if self.layer not in metadata.run.layers:
            raise ValueError(f"{where}: `run.layers` is {list(metadata.run.layers)}, layer {self.layer} was not "
                             "captured; choose one of them or capture it")
        records = metadata.layer_shards(self.layer)
        captured = {episode for record in records for episode in record.episodes}
        wanted = captured if episodes is None else {int(e) for e in episodes}
        if missing := sorted((wanted | {int(e) for e in exclude}) - captured):
            raise ValueError(f"{where}: episodes {describe_ranges(missing)} have no rows of layer {self.layer} "
                             f"(captured: {describe_ranges(sorted(captured))}); capture them or leave them out")
        self.episodes = tuple(sorted(wanted - {int(e) for e in exclude}))
        self._run_identity = metadata.run.identity()
        wrong = [f"{self.run_dir / r.file}: `width` is {r.width}, expected {self.width} from run.json"
                 for r in records if r.width != self.width]
        if wrong:
            raise ValueError("; ".join(wrong) + f"; re-run capture for layer {self.layer}")
        # per shard: its record and the (start, stop) row ranges of the selected episodes
        self._shards = [(r, ranges) for r in records if (ranges := self._ranges(r, set(self.episodes)))]
        self.rows = sum(stop - start for _, ranges in self._shards for start, stop in ranges)
        if self.rows == 0:
            raise ValueError(f"{where}: no rows of layer {self.layer} left after the selection (episodes "
                             f"{describe_ranges(list(self.episodes))}); expected at least one, choose other episodes")

    def identity(self) -> str:
        """Return the sha256 of the rows' identity: the run's spec, the layer, the selected episodes and the sha256
        of each shard holding them (shards of other episodes, such as newly captured demos, do not count)."""
        return sha256_json({"run": self._run_identity, "layer": self.layer, "episodes": list(self.episodes),
                            "shards": [(record.file, record.sha256) for record, _ in self._shards]})

    def sequential(self, batch_rows: int) -> Iterator[tuple[torch.Tensor, dict[str, np.ndarray]]]:
        """Yield float32 (b, width) rows with their (b,) int64 columns (index, episode_index, frame_index,
        token_position, token_id; `step` too in action token types), in shard order; b <= batch_rows
        (a batch never spans two shards)."""
        _check_positive(batch_rows=batch_rows)
        for record, ranges in self._shards:
            with self._open(record) as reader:
                columns = reader.columns()
                for start, stop in ranges:
                    for first in range(start, stop, batch_rows):
                        last = min(first + batch_rows, stop)
                        yield (reader.residuals(first, last).to(torch.float32),
                               {name: values[first:last].copy() for name, values in columns.items()})

    def shuffled(self, batch_rows: int, *, seed: int, buffer_rows: int, start_sample: int = 0) -> Iterator[torch.Tensor]:
        """Yield float32 (batch_rows, width) batches without end, in the shuffled order of the module docstring.

        Deterministic given (seed, buffer_rows, batch_rows); `start_sample` (a multiple of batch_rows) gives
        exactly the batches an uninterrupted stream gives from that sample on.
        """
        _check_positive(batch_rows=batch_rows, buffer_rows=buffer_rows)
        if start_sample < 0:
            raise ValueError(f"start_sample is {start_sample}, expected 0 or more")
        pieces = self._pieces(max(1, buffer_rows // PIECES_PER_BUFFER))
        epoch, skip = divmod(start_sample, self.rows)
        carry, buffer = torch.empty(0, self.width), None
        while True:
            for number, chosen in enumerate(_buffers(pieces, np.random.default_rng([seed, epoch]), buffer_rows)):
                size = int((chosen[:, 2] - chosen[:, 1]).sum())
                if skip >= size:  # the whole buffer lies before the start: never read
                    skip -= size
                    continue
                buffer = None  # the previous buffer is freed before the next one is read: one buffer at a time
                buffer = self._fill(chosen, size)
                order = torch.randperm(size, generator=_generator(seed, epoch, number + 1))
                first, skip = skip, 0
                while first < size:
                    take = min(batch_rows - carry.shape[0], size - first)
                    rows = buffer.index_select(0, order[first : first + take])
                    first += take
                    carry = rows if carry.shape[0] == 0 else torch.cat([carry, rows])
                    if carry.shape[0] == batch_rows:
                        yield carry
                        carry = torch.empty(0, self.width)
            epoch += 1

    def _pieces(self, piece_rows: int) -> np.ndarray:
        """Return (pieces, 3) int64 rows (shard number, start, stop): the selected rows cut into runs of piece_rows."""
        pieces = [(number, first, min(first + piece_rows, stop))
                  for number, (_, ranges) in enumerate(self._shards)
                  for start, stop in ranges for first in range(start, stop, piece_rows)]
        return np.asarray(pieces, dtype=np.int64).reshape(-1, 3)

    def _fill(self, chosen: np.ndarray, size: int) -> torch.Tensor:
        """Return float32 (size, width): the rows of `chosen` pieces in their order, each shard opened once."""
        buffer = torch.empty(size, self.width)
        offsets = np.concatenate([[0], np.cumsum(chosen[:, 2] - chosen[:, 1])])
        for number in np.unique(chosen[:, 0]):
            with self._open(self._shards[number][0]) as reader:
                for at in np.flatnonzero(chosen[:, 0] == number):
                    _, start, stop = (int(v) for v in chosen[at])
                    buffer[offsets[at] : offsets[at + 1]] = reader.residuals(start, stop)
        return buffer

    def _open(self, record: ShardRecord):
        """Return `open_shard` of one record, checked against the run's width and the record's rows and dtype."""
        return open_shard(self.run_dir / record.file, width=self.width, dtype=record.dtype, rows=record.rows)

    def _ranges(self, record: ShardRecord, wanted: set[int]) -> list[tuple[int, int]]:
        """Return the (start, stop) row ranges of a shard that belong to `wanted` episodes."""
        chosen = set(record.episodes) & wanted
        if not chosen or record.rows == 0:
            return []
        if chosen == set(record.episodes):
            return [(0, record.rows)]
        with self._open(record) as reader:
            keep = np.isin(reader.columns([EPISODE])[EPISODE], sorted(chosen))
        edges = np.flatnonzero(np.diff(np.concatenate([[0], keep.astype(np.int8), [0]])))
        return [(int(start), int(stop)) for start, stop in zip(edges[::2], edges[1::2])]


def _buffers(pieces: np.ndarray, rng: np.random.Generator, buffer_rows: int) -> Iterator[np.ndarray]:
    """Yield the pieces in a random order, grouped into consecutive runs of at most buffer_rows rows."""
    shuffled = pieces[rng.permutation(len(pieces))]
    ends = np.cumsum(shuffled[:, 2] - shuffled[:, 1])
    first = 0
    while first < len(shuffled):
        base = ends[first - 1] if first else 0
        last = int(np.searchsorted(ends, base + buffer_rows, side="right"))  # pieces ending within the buffer
        yield shuffled[first:last]
        first = last


def _generator(*key: int) -> torch.Generator:
    """Return a torch generator seeded by a hash of `key` (numpy's SeedSequence), so nearby keys give unrelated orders."""
    return torch.Generator().manual_seed(int(np.random.SeedSequence(list(key)).generate_state(1, np.uint64)[0] >> 1))


def _check_positive(**values: int) -> None:
    """Raise a ValueError naming every argument that is not a positive integer."""
    bad = [f"{name} is {value}, expected a positive integer" for name, value in values.items() if value < 1]
    if bad:
        raise ValueError("; ".join(bad))
