"""A LeRobot dataset's metadata checked against itself and against its data, before any run reads it.

`check_dataset` is what every command reading an existing dataset (manifest, concept-map, capture,
evaluate, a pipeline's preflight) calls first. It refuses, in one ValueError naming the file and field:
info.json fields that contradict the episode rows (`fps`, `total_episodes`, `total_frames`), statistics
holding NaN or Inf, episode rows whose task is not in the tasks table, data files whose columns contradict
the feature shapes of info.json, and frames that contradict the episode rows (an episode missing from
the metadata, a duplicated or shifted global `index`, `frame_index` out of order, a `task_index` unknown
to the tasks table or disagreeing with the episode's task), and a video feature whose file for some episode is
missing. It reads metadata, parquet footers and the four integer index columns: never an image.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from steering_core.data import lerobot_v2
from steering_core.data.dataset import (
    EPISODES_DIR,
    INFO_FILE,
    DatasetMeta,
    IndexColumns,
    data_files,
    read_index_columns,
    read_meta,
)
from steering_core.data.parquet_reads import read_schema, read_table
from steering_core.storage.fileio import parse_json, read_json, read_text

STATS_FILE = "meta/stats.json"  # lerobot's dataset-wide statistics (v3.0 and v2.0)
_FRAME_DTYPES = ("image", "video")
_NON_NUMERIC = (*_FRAME_DTYPES, "string")
_SHOWN = 3  # problems named in one message before the rest are counted


def check_dataset(root: str | os.PathLike) -> DatasetMeta:
    """Return the metadata of the dataset at `root` after checking it agrees with itself and its data.

    FileNotFoundError for a missing data file, else one ValueError naming the file and field (module docstring).
    """
    meta = read_meta(root)
    if not meta.episodes:
        raise ValueError(f"{meta.root}: {meta.episodes_source} lists no episodes; nothing to read")
    check_meta(meta)
    check_video_files(meta)
    for path in data_files(meta):
        check_data_schema(meta, path)
    check_frames(meta, read_index_columns(meta.root))
    return meta


def check_meta(meta: DatasetMeta) -> None:
    """Raise one ValueError if info.json, the tasks table, the episode rows or the statistics disagree."""
    info_path = meta.root / INFO_FILE
    fps = meta.info.get("fps")
    if not isinstance(fps, int | float) or isinstance(fps, bool) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"{info_path}: `fps` is {fps!r}, expected a positive number of frames per second")
    declared = {"total_episodes": len(meta.episodes), "total_frames": sum(e.length for e in meta.episodes)}
    for key, found in declared.items():
        if key in meta.info and meta.info[key] != found:
            raise ValueError(f"{info_path}: `{key}` is {meta.info[key]!r}, but {meta.episodes_source} holds "
                             f"{found}; the dataset is inconsistent, re-create it")
    known = set(meta.tasks.values())
    unknown = [(e.episode_index, task) for e in meta.episodes for task in e.tasks if task not in known]
    if unknown:
        raise ValueError(f"{meta.root / meta.episodes_source}: episode {unknown[0][0]} has task {unknown[0][1]!r} "
                         f"in `tasks`, which {meta.tasks_file} does not list ({len(unknown)} such)")
    for where, value in _statistics(meta):
        if not _finite_tree(value):
            raise ValueError(f"{where}: holds NaN or Inf; expected finite statistics, re-create the dataset")


def check_video_files(meta: DatasetMeta) -> None:
    """Raise a FileNotFoundError naming the first episode whose video file of a video feature is missing."""
    for episode in meta.episodes:
        for key, video in episode.video_files:
            if not (meta.root / video).is_file():
                raise FileNotFoundError(f"{meta.root / video}: the video of feature {key!r}, episode "
                                        f"{episode.episode_index}, not found (`video_path` in {meta.root / INFO_FILE}); "
                                        "the dataset is incomplete, re-create it")


def check_data_schema(meta: DatasetMeta, path: Path) -> None:
    """Raise a ValueError if a data file lacks a numeric feature of info.json or stores it with another width."""
    schema = read_schema(path)
    for key, feature in meta.info["features"].items():
        if feature.get("dtype") in _NON_NUMERIC:
            continue
        if key not in schema.names:
            raise ValueError(f"{path}: no column {key!r}, which {meta.root / INFO_FILE} lists in `features`")
        width = int(np.prod(feature.get("shape") or [1]))
        stored = _stored_width(schema.field(key).type)
        if stored is not None and stored != width:
            raise ValueError(f"{path}: column {key!r} holds {stored} value(s) per frame, but {meta.root / INFO_FILE} "
                             f"`features.{key}.shape` is {feature.get('shape')} ({width}); re-create the dataset")


def check_frames(meta: DatasetMeta, columns: IndexColumns) -> None:
    """Raise a ValueError if the data's frames are not exactly the episode rows' frames, in order, with their task.

    Episode e's frames must carry global `index` from_index..to_index-1 and `frame_index` 0..length-1, and a
    `task_index` whose text is one of the episode's `tasks`.
    """
    where = meta.root / meta.episodes_source
    stray = sorted(set(np.unique(columns.episode_index).tolist()) - {e.episode_index for e in meta.episodes})
    if stray:
        raise ValueError(f"{meta.root}: the data files hold frames of episode(s) {stray[:_SHOWN]} "
                         f"({len(stray)} in all), which {where} does not list; re-create the dataset")
    episodes = sorted(meta.episodes, key=lambda e: e.from_index)
    expected = {
        "index": np.concatenate([np.arange(e.from_index, e.to_index) for e in episodes]),
        "episode_index": np.repeat([e.episode_index for e in episodes], [e.length for e in episodes]),
        "frame_index": np.concatenate([np.arange(e.length) for e in episodes]),
    }
    if len(columns) != len(expected["index"]):
        raise ValueError(f"{meta.root}: the data files hold {len(columns)} frames, but {where} lists "
                         f"{len(expected['index'])}; re-create the dataset")
    for name, values in expected.items():
        found = getattr(columns, name)
        if not np.array_equal(found, values):
            at = int(np.flatnonzero(found != values)[0])
            raise ValueError(f"{meta.root}: the frame at position {at} (by `index`) has `{name}` {int(found[at])}, "
                             f"expected {int(values[at])} from {where}; re-create the dataset")
    _check_task_indices(meta, columns)


def _check_task_indices(meta: DatasetMeta, columns: IndexColumns) -> None:
    """Raise a ValueError if a frame's `task_index` is unknown or names a task its episode's row does not list."""
    pairs = np.unique(np.stack([columns.episode_index, columns.task_index], axis=1), axis=0)
    for episode_index, task_index in pairs.tolist():
        text = meta.tasks.get(task_index)
        if text is None:
            raise ValueError(f"{meta.root}: frames of episode {episode_index} have `task_index` {task_index}, which "
                             f"{meta.tasks_file} does not list (task indices {sorted(meta.tasks)})")
        tasks = meta.episode(episode_index).tasks
        if text not in tasks:
            raise ValueError(f"{meta.root}: frames of episode {episode_index} have `task_index` {task_index} "
                             f"({text!r}), but {meta.root / meta.episodes_source} gives its `tasks` as "
                             f"{list(tasks)}; re-create the dataset")


def _stored_width(kind: pa.DataType) -> int | None:
    """Return the values per row of a parquet column type: 1 for scalars, the size of fixed lists, None for lists."""
    if pa.types.is_fixed_size_list(kind):
        return kind.list_size
    return None if pa.types.is_list(kind) or pa.types.is_large_list(kind) else 1


def _statistics(meta: DatasetMeta) -> Iterator[tuple[str, Any]]:
    """Yield (where, value) for every statistics record of the dataset: stats.json, and per episode."""
    stats = meta.root / STATS_FILE
    if stats.is_file():
        yield str(stats), read_json(stats)  # Python's json reads NaN and Infinity: checked after
    if meta.is_v2:
        path = meta.root / lerobot_v2.EPISODES_STATS_JSONL
        if path.is_file():
            for number, line in enumerate(read_text(path, "a JSON lines file").splitlines(), start=1):
                yield f"{path}:{number}", parse_json(line, f"{path}:{number}") if line.strip() else None
        return
    for path in sorted((meta.root / EPISODES_DIR).glob("chunk-*/file-*.parquet")):
        names = [name for name in read_schema(path).names if name.startswith("stats/")]
        table = read_table(path, columns=names)
        for name in names:
            yield f"{path}: column {name!r}", table.column(name).to_pylist()


def _finite_tree(value: Any) -> bool:
    """Return False if a JSON-like value holds a float NaN or Inf anywhere."""
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(_finite_tree(v) for v in value.values())
    if isinstance(value, list | tuple):
        return all(_finite_tree(v) for v in value)
    return True
