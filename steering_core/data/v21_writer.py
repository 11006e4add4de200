"""Writing a LeRobot v2.1 dataset laid out as openpi's LIBERO conversion writes it, without lerobot.

openpi pins a lerobot that reads v2.x only; this writer produces what that lerobot's
`LeRobotDataset.create` + `add_frame` + `save_episode` write (docs/PI05_SPEC.md §8.2): one
parquet per episode under `data/chunk-000/, chunk-001/, …` (PNG image structs, fixed-size float lists, snappy,
row groups of 100, the `huggingface` schema metadata in datasets-3.x spelling), `meta/info.json`
rewritten after every episode, and one appended line per episode in `meta/episodes.jsonl`,
`meta/episodes_stats.jsonl` and, for new tasks, `meta/tasks.jsonl`. The caller stages the folder
(the writer writes in place).
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from steering_core.data import lerobot_v2
from steering_core.data.dataset import INFO_FILE
from steering_core.storage.fileio import read_json

CODEBASE_VERSION = "v2.1"
CHUNKS_SIZE = 1000  # episodes per data/chunk-NNN folder (lerobot's default)
DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
# openpi never passes use_videos=False, so its datasets carry the video template without any video.
VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"
INDEX_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": (1,), "names": None},
    "frame_index": {"dtype": "int64", "shape": (1,), "names": None},
    "episode_index": {"dtype": "int64", "shape": (1,), "names": None},
    "index": {"dtype": "int64", "shape": (1,), "names": None},
    "task_index": {"dtype": "int64", "shape": (1,), "names": None},
}
ROW_GROUP_SIZE = 100  # what HF datasets uses for image datasets
IMAGE_FRAME_NAME = "frame_{frame_index:06d}.png"  # the `path` lerobot leaves in each image struct
# Image statistics sample frames: all below 100, else max(100, min(L ** 0.75, 10000)) evenly spaced.
_STATS_MIN_SAMPLES, _STATS_MAX_SAMPLES, _STATS_POWER = 100, 10_000, 0.75
_STATS_DOWNSAMPLE_FROM, _STATS_DOWNSAMPLE_TARGET = 300, 150  # frames this large are strided to ~150 px
_IMAGE_STRUCT = pa.struct([("bytes", pa.binary()), ("path", pa.string())])


class V21Writer:
    """Appends episodes to a v2.1 dataset folder; `create` starts one, `open` continues one."""

    def __init__(self, root: Path, info: dict[str, Any], tasks: dict[str, int]):
        self.root, self.info, self.tasks = root, info, tasks

    @classmethod
    def create(
        cls, root: str | os.PathLike, *, fps: int, robot_type: str | None, features: Mapping[str, dict[str, Any]]
    ) -> V21Writer:
        """Return a writer for a new, empty dataset at `root` (info.json written at once, as lerobot does).

        `features` are the user features (dtype "image" or numeric, shape a tuple), in column order.
        """
        root = Path(root)
        info = {
            "codebase_version": CODEBASE_VERSION,
            "robot_type": robot_type,
            "total_episodes": 0,
            "total_frames": 0,
            "total_tasks": 0,
            "total_videos": 0,
            "total_chunks": 0,
            "chunks_size": CHUNKS_SIZE,
            "fps": fps,
            "splits": {},
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH,
            "features": {**{k: _json_feature(v) for k, v in features.items()}, **_json_features(INDEX_FEATURES)},
        }
        writer = cls(root, info, {})
        writer._write_info()
        return writer

    @classmethod
    def open(cls, root: str | os.PathLike) -> V21Writer:
        """Return a writer that appends to the v2.1 dataset this module wrote at `root`."""
        root = Path(root)
        info = read_json(root / INFO_FILE)
        if info.get("codebase_version") != CODEBASE_VERSION:
            raise ValueError(f"{root / INFO_FILE}: codebase_version {info.get('codebase_version')!r}, expected 'v2.1'")
        tasks = {text: index for index, text in lerobot_v2.read_tasks(root).items()}
        return cls(root, info, tasks)

    def add_episode(self, columns: Mapping[str, np.ndarray], task: str) -> None:
        """Write one episode: `columns` maps every user feature to (frames, ...) values.

        Images are (frames, H, W, 3) uint8; numeric features (frames, dim) of their declared dtype.
        """
        info = self.info
        episode = int(info["total_episodes"])
        length = _episode_length(columns, self._user_features())
        if task not in self.tasks:
            self.tasks[task] = len(self.tasks)
            info["total_tasks"] = len(self.tasks)
            _append_jsonl(self.root / lerobot_v2.TASKS_JSONL, {"task_index": self.tasks[task], "task": task})
        frame_index = np.arange(length, dtype=np.int64)
        bookkeeping = {
            "timestamp": frame_index / info["fps"],  # float64 here (the stats use it), float32 in the parquet
            "frame_index": frame_index,
            "episode_index": np.full(length, episode, dtype=np.int64),
            "index": np.arange(info["total_frames"], info["total_frames"] + length, dtype=np.int64),
            "task_index": np.full(length, self.tasks[task], dtype=np.int64),
        }
        values = {**columns, **bookkeeping}
        path = self.root / lerobot_v2.episode_data_file(info, episode)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(self._table(values), path, row_group_size=ROW_GROUP_SIZE, compression="snappy")
        info["total_episodes"] = episode + 1
        info["total_frames"] += length
        info["total_chunks"] = max(info["total_chunks"], episode // info["chunks_size"] + 1)
        info["splits"] = {"train": f"0:{episode + 1}"}
        self._write_info()
        _append_jsonl(self.root / lerobot_v2.EPISODES_JSONL, {"episode_index": episode, "tasks": [task], "length": length})
        stats = {key: _feature_stats(values[key], spec["dtype"]) for key, spec in info["features"].items()}
        _append_jsonl(self.root / lerobot_v2.EPISODES_STATS_JSONL, {"episode_index": episode, "stats": stats})

    def _user_features(self) -> dict[str, dict[str, Any]]:
        return {k: v for k, v in self.info["features"].items() if k not in INDEX_FEATURES}

    def _table(self, values: Mapping[str, np.ndarray]) -> pa.Table:
        """Return the episode's parquet table: columns in feature order, with the HF features metadata."""
        features = self.info["features"]
        arrays, fields = [], []
        for key, spec in features.items():
            array = _arrow_column(values[key], spec)
            arrays.append(array)
            fields.append(pa.field(key, array.type))
        schema = pa.schema(fields, metadata={"huggingface": hf_features_json(features)})
        return pa.Table.from_arrays(arrays, schema=schema)

    def _write_info(self) -> None:
        """Rewrite info.json as lerobot does: indent 4, non-ASCII kept, no trailing newline."""
        path = self.root / INFO_FILE
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.info, indent=4, ensure_ascii=False, allow_nan=False), encoding="utf-8")


def hf_features_json(features: Mapping[str, dict[str, Any]]) -> str:
    """Return the `huggingface` parquet metadata of `features`, spelled as datasets 3.x (openpi's) reads it.

    datasets >= 4 writes `"_type": "List"`, which openpi's datasets 3.6 rejects; so it is built by hand.
    """
    described = {}
    for key, spec in features.items():
        shape = tuple(spec["shape"])
        if spec["dtype"] == "image":
            described[key] = {"_type": "Image"}
        elif shape == (1,):
            described[key] = {"dtype": spec["dtype"], "_type": "Value"}
        elif len(shape) == 1:
            value = {"dtype": spec["dtype"], "_type": "Value"}
            described[key] = {"feature": value, "length": shape[0], "_type": "Sequence"}
        else:
            raise ValueError(f"feature {key!r}: shape {list(shape)} is not supported by the v2.1 writer (1-D only)")
    return json.dumps({"info": {"features": described}})


def _json_feature(spec: dict[str, Any]) -> dict[str, Any]:
    return {**spec, "shape": list(spec["shape"])}


def _json_features(features: Mapping[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {k: _json_feature(v) for k, v in features.items()}


def _episode_length(columns: Mapping[str, np.ndarray], features: Mapping[str, dict[str, Any]]) -> int:
    """Return the frame count shared by every user feature; ValueError naming what is missing or mismatched."""
    if missing := [k for k in features if k not in columns]:
        raise ValueError(f"episode columns lack feature(s) {missing}; expected {list(features)}")
    lengths = {k: len(columns[k]) for k in features}
    if len(set(lengths.values())) != 1 or 0 in lengths.values():
        raise ValueError(f"episode columns have frame counts {lengths}; expected one non-zero count for all")
    return next(iter(lengths.values()))


def _arrow_column(values: np.ndarray, spec: dict[str, Any]) -> pa.Array:
    """Return one parquet column: PNG structs for images, fixed-size lists for vectors, scalars otherwise."""
    if spec["dtype"] == "image":
        structs = [{"bytes": encode_png(frame), "path": IMAGE_FRAME_NAME.format(frame_index=i)}
                   for i, frame in enumerate(values)]
        return pa.array(structs, type=_IMAGE_STRUCT)
    dtype = np.dtype(spec["dtype"])
    shape = tuple(spec["shape"])
    if shape == (1,):
        return pa.array(np.asarray(values).reshape(-1).astype(dtype))
    flat = pa.array(np.ascontiguousarray(values, dtype=dtype).reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, type=pa.list_(pa.field("element", flat.type), shape[0]))


def encode_png(frame: np.ndarray) -> bytes:
    """Return an (H, W, 3) uint8 frame as PNG bytes with Pillow's defaults (what lerobot stores)."""
    buffer = io.BytesIO()
    Image.fromarray(frame).save(buffer, format="PNG")
    return buffer.getvalue()


def _feature_stats(values: np.ndarray, dtype: str) -> dict[str, Any]:
    """Return one feature's episode statistics as lerobot 0.1 writes them: min, max, mean, std, count.

    Images: sampled frames, per channel over (frames, H, W), in [0, 1], shaped (3, 1, 1), count = samples.
    Others: over frames (population std), in the column's own dtype, count = frames.
    """
    if dtype == "image":
        chw = np.ascontiguousarray(_sample_frames(values).transpose(0, 3, 1, 2))  # summation order: as lerobot
        stats = _reduce(chw, axis=(0, 2, 3), keepdims=True)
        stats = {k: v if k == "count" else np.squeeze(v / 255.0, axis=0) for k, v in stats.items()}
    else:
        values = np.asarray(values)
        stats = _reduce(values, axis=0, keepdims=values.ndim == 1)
    return {k: v.tolist() for k, v in stats.items()}


def _reduce(values: np.ndarray, axis: int | tuple[int, ...], keepdims: bool) -> dict[str, np.ndarray]:
    return {
        "min": np.min(values, axis=axis, keepdims=keepdims),
        "max": np.max(values, axis=axis, keepdims=keepdims),
        "mean": np.mean(values, axis=axis, keepdims=keepdims),
        "std": np.std(values, axis=axis, keepdims=keepdims),
        "count": np.array([len(values)]),
    }


def _sample_frames(frames: np.ndarray) -> np.ndarray:
    """Return the evenly spaced frames lerobot's image statistics use, strided when 300 px or larger."""
    length = len(frames)
    count = length if length < _STATS_MIN_SAMPLES else max(
        _STATS_MIN_SAMPLES, min(int(length**_STATS_POWER), _STATS_MAX_SAMPLES))
    chosen = frames[np.round(np.linspace(0, length - 1, count)).astype(int)]
    height, width = chosen.shape[1:3]
    if max(height, width) >= _STATS_DOWNSAMPLE_FROM:
        step = int((width if width > height else height) / _STATS_DOWNSAMPLE_TARGET)
        chosen = chosen[:, ::step, ::step]
    return chosen


def _append_jsonl(path: Path, row: dict[str, Any]) -> None:
    """Append one JSON line, spelled as the `jsonlines` package writes it (non-ASCII kept)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(row, ensure_ascii=False, allow_nan=False) + "\n")
