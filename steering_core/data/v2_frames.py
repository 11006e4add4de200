"""Frames of a LeRobot v2.x dataset, returned as lerobot's `LeRobotDataset` returns them, read in place.

lerobot 0.4 refuses v2.x datasets, so capture reads them here: the numeric columns of the chosen
episodes' parquet files are read once; a frame's cameras are decoded on access, from the PNG bytes
of the parquet's image structs (Pillow, as HF datasets' `Image` feature does) or, for video
features, from the episode's mp4 at the frame's timestamp with lerobot's own decoder. Cameras come
back as float32 (3, H, W) in [0, 1] (uint8 / 255, as torchvision's `ToTensor`), so residuals
captured from a v2.x dataset equal those from its v3.0 conversion. Nothing is ever written.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from PIL import Image

from steering_core.data import lerobot_v2
from steering_core.data.dataset import DatasetMeta
from steering_core.data.parquet_reads import read_table

FRAME_DTYPES = ("image", "video")
_NON_NUMERIC = (*FRAME_DTYPES, "string")
VIDEO_TOLERANCE_S = 1e-4  # LeRobotDataset's default tolerance between a timestamp and the decoded frame


class V2Frames:
    """The frames of `episodes` (by episode, then frame) of a v2.x dataset; item = {feature: tensor, "task": str}."""

    def __init__(self, meta: DatasetMeta, episodes: Sequence[int], video_backend: str | None = None):
        if not meta.is_v2:
            raise ValueError(f"{meta.root}: codebase_version {meta.version!r}; V2Frames reads v2.0/v2.1 datasets only")
        self.meta, self.video_backend = meta, video_backend
        features = meta.info["features"]
        self.image_keys = [k for k, v in features.items() if v.get("dtype") == "image"]
        self.video_keys = [k for k, v in features.items() if v.get("dtype") == "video"]
        self.episodes = [meta.episode(int(e)) for e in sorted(set(episodes))]
        numeric = [k for k, v in features.items() if v.get("dtype") not in _NON_NUMERIC]
        parts: dict[str, list[np.ndarray]] = {k: [] for k in numeric}
        for episode in self.episodes:
            table = read_table(meta.root / episode.data_file, columns=numeric)
            if table.num_rows != episode.length:
                raise ValueError(
                    f"{meta.root / episode.data_file}: {table.num_rows} rows, but episode {episode.episode_index} "
                    f"has length {episode.length} in {lerobot_v2.EPISODES_JSONL}; the dataset is corrupt"
                )
            for key in numeric:
                parts[key].append(_column_values(table.column(key).combine_chunks(), features[key]))
        self.columns: dict[str, np.ndarray] = {k: np.concatenate(v) if v else np.empty(0) for k, v in parts.items()}
        self.row = np.concatenate([np.arange(e.length) for e in self.episodes]) if self.episodes else np.empty(0, int)
        self.slot = np.repeat(np.arange(len(self.episodes)), [e.length for e in self.episodes])
        self._images: tuple[int, dict[str, list[bytes | None]]] | None = None  # one episode's PNGs, per worker

    @property
    def episode_index(self) -> np.ndarray:
        """Return the (frames,) int64 episode of every position."""
        return self.columns["episode_index"].astype(np.int64)

    @property
    def index(self) -> np.ndarray:
        """Return the (frames,) int64 global `index` of every position."""
        return self.columns["index"].astype(np.int64)

    def __len__(self) -> int:
        return int(self.row.shape[0])

    def __getitem__(self, position: int) -> dict[str, Any]:
        item: dict[str, Any] = {key: torch.from_numpy(np.array(values[position])) for key, values in self.columns.items()}
        slot, row = int(self.slot[position]), int(self.row[position])
        for key, png in self._episode_images(slot).items():
            item[key] = _decode_png(png[row], self.meta.root / self.episodes[slot].data_file, key, row)
        for key in self.video_keys:
            item[key] = self._video_frame(slot, key, float(self.columns["timestamp"][position]))
        item["task"] = self.meta.tasks[int(self.columns["task_index"][position])]
        return item

    def stored_png(self, position: int, key: str) -> bytes:
        """Return the stored PNG bytes of image feature `key` at `position` (b"" where the cell holds none)."""
        return self._episode_images(int(self.slot[position]))[key][int(self.row[position])] or b""

    def _episode_images(self, slot: int) -> dict[str, list[bytes | None]]:
        """Return the PNG bytes of the episode's image features, reading its parquet once per episode."""
        if not self.image_keys:
            return {}
        if self._images is None or self._images[0] != slot:
            path = self.meta.root / self.episodes[slot].data_file
            table = read_table(path, columns=self.image_keys)
            self._images = (slot, {k: table.column(k).combine_chunks().field("bytes").to_pylist()
                                   for k in self.image_keys})
        return self._images[1]

    def _video_frame(self, slot: int, key: str, timestamp: float) -> torch.Tensor:
        """Return the frame of camera `key` at `timestamp` in the episode's mp4, as (3, H, W) float32."""
        from lerobot.datasets.video_utils import decode_video_frames  # slow import, video datasets only

        episode = self.episodes[slot].episode_index
        path = self.meta.root / lerobot_v2.episode_video_file(self.meta.info, episode, key)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: video of camera {key!r}, episode {episode} not found")
        return decode_video_frames(path, [timestamp], VIDEO_TOLERANCE_S, self.video_backend).squeeze(0)


def _column_values(array: Any, feature: dict[str, Any]) -> np.ndarray:
    """Return a numeric parquet column as (rows,) scalars or (rows, dim) vectors in the feature's dtype."""
    dtype = np.dtype(feature["dtype"])
    shape = tuple(feature.get("shape") or (1,))
    if shape == (1,):
        return array.to_numpy(zero_copy_only=False).astype(dtype, copy=False)
    flat = array.flatten().to_numpy(zero_copy_only=False).astype(dtype, copy=False)
    return flat.reshape(len(array), *shape)


def _decode_png(data: bytes | None, path: Any, key: str, row: int) -> torch.Tensor:
    """Return one stored image as (3, H, W) float32 in [0, 1]."""
    if data is None:
        raise ValueError(f"{path}: row {row} of {key!r} has no embedded image bytes; this reader needs them")
    pixels = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    return torch.from_numpy(pixels.copy()).permute(2, 0, 1).to(torch.float32).div(255)
