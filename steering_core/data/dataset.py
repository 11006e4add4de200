"""Reading a LeRobot dataset (v3.0, v2.1 or v2.0) without decoding a single frame.

Metadata comes from `meta/` (info, tasks, episodes: parquet in v3.0, jsonl in v2.x, see
`lerobot_v2`); frame-level values come from the data parquet files through pyarrow, one
requested column at a time, so image columns (PNG bytes) are never read. Datasets are read
in place and never written. Contrast manifests, concept maps, capture and slicing all read
datasets through this module.
"""

from __future__ import annotations

import difflib
import logging
import os
import string
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
import pyarrow as pa

from steering_core.data import lerobot_v2
from steering_core.data.parquet_reads import read_schema, read_table
from steering_core.storage.fileio import read_json, sha256_file, sha256_json

logger = logging.getLogger(__name__)

CODEBASE_VERSION = "v3.0"
SUPPORTED_VERSIONS = (*lerobot_v2.V2_VERSIONS, CODEBASE_VERSION)
INFO_FILE = "meta/info.json"
TASKS_FILE = "meta/tasks.parquet"
EPISODES_DIR = "meta/episodes"
INDEX_COLUMNS = ("episode_index", "frame_index", "index", "task_index")
_EPISODE_COLUMNS = (
    "episode_index",
    "tasks",
    "length",
    "dataset_from_index",
    "dataset_to_index",
    "data/chunk_index",
    "data/file_index",
)
_FRAME_DTYPES = ("image", "video")  # features stored as encoded frames, never read here
_CLOSEST_TASKS = 5
# info.json's path templates and the fields lerobot formats into them (v3.0 files and chunks, v2.x episodes)
PATH_TEMPLATES = ("data_path", "video_path")
TEMPLATE_FIELDS = frozenset({"chunk_index", "file_index", "episode_chunk", "episode_index", "video_key"})
# The video backend named to lerobot where a dataset has no video to decode: left to choose (lerobot 0.5 and later),
# lerobot loads torchcodec at every dataset open, which without the system FFmpeg logs a 100-line warning each time.
NO_VIDEO_BACKEND = "pyav"


@dataclass(frozen=True)
class EpisodeInfo:
    """One row of `meta/episodes`: where an episode's frames live and what task it shows."""

    episode_index: int
    tasks: tuple[str, ...]
    length: int       # frames in the episode
    from_index: int   # global `index` of its first frame
    to_index: int     # global `index` one past its last frame (exclusive, as in lerobot)
    data_file: str    # data parquet holding its frames, relative to the dataset root (posix)
    video_files: tuple[tuple[str, str], ...] = ()  # (camera, mp4 relative to the root) of each video feature

    @property
    def task(self) -> str:
        """Return the episode's language instruction (the first task; LIBERO has one per episode)."""
        return self.tasks[0]


@dataclass(frozen=True)
class DatasetMeta:
    """A dataset's `meta/` folder, validated: info.json, task texts and episode rows."""

    root: Path
    info: dict[str, Any]
    tasks: dict[int, str]               # task_index -> task text
    episodes: tuple[EpisodeInfo, ...]   # sorted by episode_index

    @property
    def version(self) -> str:
        """Return the codebase version of info.json: "v2.0", "v2.1" or "v3.0"."""
        return str(self.info["codebase_version"])

    @property
    def is_v2(self) -> bool:
        """Return True for a v2.x dataset (one parquet per episode, jsonl metadata)."""
        return self.version in lerobot_v2.V2_VERSIONS

    @property
    def tasks_file(self) -> Path:
        """Return the file the task texts were read from."""
        return self.root / (lerobot_v2.TASKS_JSONL if self.is_v2 else TASKS_FILE)

    @property
    def episodes_source(self) -> str:
        """Return where the episode rows were read from, relative to the root."""
        return lerobot_v2.EPISODES_JSONL if self.is_v2 else EPISODES_DIR

    @property
    def has_videos(self) -> bool:
        """Return True when a feature of info.json is stored as video (what a video backend decodes)."""
        return bool(video_keys(self.info))

    @property
    def total_frames(self) -> int:
        """Return the number of frames declared by info.json."""
        return int(self.info["total_frames"])

    @cached_property
    def _by_index(self) -> dict[int, EpisodeInfo]:
        """Return episode index -> episode, built once."""
        return {e.episode_index: e for e in self.episodes}

    def episode(self, episode_index: int) -> EpisodeInfo:
        """Return the episode with this index; ValueError if the dataset has none."""
        if episode_index in self._by_index:
            return self._by_index[episode_index]
        raise ValueError(
            f"{self.root}: no episode {episode_index}; the dataset has episodes "
            f"{_describe_ints([e.episode_index for e in self.episodes])}"
        )

    def episodes_for_task(self, task: str) -> list[EpisodeInfo]:
        """Return the episodes whose task list contains `task`, by episode index."""
        return [episode for episode in self.episodes if task in episode.tasks]


@dataclass(frozen=True)
class IndexColumns:
    """The integer bookkeeping columns of every frame, ordered by global `index`: each (frames,) int64."""

    episode_index: np.ndarray
    frame_index: np.ndarray
    index: np.ndarray
    task_index: np.ndarray

    def __len__(self) -> int:
        return int(self.index.shape[0])


def read_meta(root: str | os.PathLike) -> DatasetMeta:
    """Return the validated metadata of the LeRobot dataset (v3.0, v2.1 or v2.0) at `root`."""
    root = Path(root)
    info = read_info(root)
    if info["codebase_version"] in lerobot_v2.V2_VERSIONS:
        tasks = lerobot_v2.read_tasks(root)
    else:
        tasks = read_tasks(root)
    return DatasetMeta(root=root, info=info, tasks=tasks, episodes=tuple(_read_episodes(root, info)))


def read_info(root: str | os.PathLike) -> dict[str, Any]:
    """Return `meta/info.json` after checking it describes a dataset of a supported version."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: LeRobot dataset folder not found")
    info_path = root / INFO_FILE
    if not info_path.is_file():
        raise FileNotFoundError(
            f"{info_path}: not found; {root} is not a LeRobot dataset (expected {INFO_FILE}, "
            f"{TASKS_FILE}, {EPISODES_DIR}/ and data/)"
        )
    info = read_json(info_path)
    if not isinstance(info, dict):
        raise ValueError(f"{info_path}: expected a JSON object, found {type(info).__name__}")
    version = info.get("codebase_version")
    if version not in SUPPORTED_VERSIONS:
        raise ValueError(
            f"{info_path}: `codebase_version` is {version!r}, expected one of {list(SUPPORTED_VERSIONS)}; "
            "re-create the dataset with lerobot 0.4.x or openpi's pinned lerobot"
        )
    required = ["data_path", "features", "total_frames"]
    if version in lerobot_v2.V2_VERSIONS:
        required.append("chunks_size")  # v2.x data paths are grouped in chunks of this many episodes
    missing = [key for key in required if key not in info]
    if missing:
        raise ValueError(f"{info_path}: missing field(s) {missing}; the dataset is incomplete, re-create it")
    problems = _field_type_problems(info)
    if problems:
        raise ValueError(f"{info_path}: {'; '.join(problems)}; re-create the dataset")
    templates = {key: info[key] for key in PATH_TEMPLATES if key in info and (key == "data_path" or info[key])}
    problems = [problem for key, template in templates.items() if (problem := _template_problem(key, template))]
    if problems:
        raise ValueError(f"{info_path}: " + "; ".join(problems))
    return info


def _field_type_problems(info: dict[str, Any]) -> list[str]:
    """Return the problems of info.json fields every reader indexes having another JSON type than lerobot writes:
    `features` an object of objects, each with a string `dtype` and a `shape` of positive integers; the counts
    (`total_frames`, `total_episodes`, `chunks_size`) integers; `video_path` a template where a feature is a video."""
    def count(value: Any) -> bool:
        return isinstance(value, int) and not isinstance(value, bool) and value >= 0

    problems = [f"`{key}` is {info[key]!r}, expected an integer"
                for key in ("total_frames", "total_episodes", "chunks_size") if key in info and not count(info[key])]
    features = info["features"]
    if not isinstance(features, dict):
        return [*problems, f"`features` is {type(features).__name__}, expected a JSON object of features"]
    for key, feature in features.items():
        if not isinstance(feature, dict):
            problems.append(f"`features.{key}` is {type(feature).__name__}, expected a JSON object (dtype, shape)")
            continue
        if not isinstance(feature.get("dtype"), str):
            problems.append(f"`features.{key}.dtype` is {feature.get('dtype')!r}, expected a string")
        shape = feature.get("shape")
        if not isinstance(shape, list) or not shape or not all(count(n) and n > 0 for n in shape):
            problems.append(f"`features.{key}.shape` is {shape!r}, expected a list of positive integers")
        if feature.get("dtype") == "video" and not isinstance(info.get("video_path"), str):
            problems.append(f"`features.{key}` is a video, but `video_path` is {info.get('video_path')!r}, expected "
                            "its path template")
    return problems


def _template_problem(key: str, template: Any) -> str | None:
    """Return the problem of a path template that could name a file outside the dataset, else None: it must be a
    relative path without `..`, formatting only lerobot's fields (no attribute or index access)."""
    if not isinstance(template, str):
        return f"`{key}` is {type(template).__name__}, expected a path template string"
    try:
        fields = [field for _, field, _, _ in string.Formatter().parse(template) if field is not None]
    except ValueError as err:
        return f"`{key}` {template!r} is not a format string ({err})"
    unknown = sorted({field for field in fields if field not in TEMPLATE_FIELDS})
    if unknown:
        return f"`{key}` {template!r} formats fields {unknown}; expected only {sorted(TEMPLATE_FIELDS)}"
    if template.startswith("/") or ".." in PurePosixPath(template).parts or "\\" in template:
        return f"`{key}` {template!r} names a path outside the dataset; expected a relative path inside its folder"
    return None


def read_tasks(root: str | os.PathLike) -> dict[int, str]:
    """Return task_index -> task text from a v3.0 dataset's `meta/tasks.parquet`."""
    path = Path(root) / TASKS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found; the dataset is incomplete (was finalize() called?)")
    # lerobot stores the task text as the pandas index; to_pandas() restores it.
    frame = read_table(path).to_pandas()
    if "task_index" not in frame.columns:
        raise ValueError(f"{path}: no `task_index` column (found {list(frame.columns)}); not a v3.0 tasks table")
    tasks = {int(i): str(text) for text, i in zip(frame.index, frame["task_index"], strict=True)}
    if len(tasks) != len(frame):
        raise ValueError(f"{path}: `task_index` has duplicates; the tasks table is corrupt, re-create the dataset")
    return tasks


def read_episodes(root: str | os.PathLike) -> list[EpisodeInfo]:
    """Return every episode (`meta/episodes/**.parquet`, or v2.x `meta/episodes.jsonl`), by episode index."""
    return _read_episodes(Path(root), read_info(root))


def _read_episodes(root: Path, info: dict[str, Any]) -> list[EpisodeInfo]:
    """Return the episode rows of either version."""
    if info["codebase_version"] in lerobot_v2.V2_VERSIONS:
        return _read_v2_episodes(root, info)
    return _read_v3_episodes(root, info)


def video_keys(info: dict[str, Any]) -> list[str]:
    """Return the features of info.json stored as video, in its order."""
    return [key for key, feature in info["features"].items() if feature["dtype"] == "video"]


def _read_v2_episodes(root: Path, info: dict[str, Any]) -> list[EpisodeInfo]:
    """Return the episodes of `meta/episodes.jsonl`; global indices follow episode order, as lerobot assigns them."""
    episodes = []
    start = 0
    for episode_index, tasks, length in lerobot_v2.read_episode_rows(root):
        episodes.append(EpisodeInfo(
            episode_index=episode_index, tasks=tasks, length=length, from_index=start, to_index=start + length,
            data_file=lerobot_v2.episode_data_file(info, episode_index),
            video_files=tuple((key, lerobot_v2.episode_video_file(info, episode_index, key))
                              for key in video_keys(info)),
        ))
        start += length
    _check_episodes(root / lerobot_v2.EPISODES_JSONL, episodes)
    return episodes


def _read_v3_episodes(root: Path, info: dict[str, Any]) -> list[EpisodeInfo]:
    """Return the episode rows, with data file paths from info.json's `data_path` template."""
    files = sorted((root / EPISODES_DIR).glob("chunk-*/file-*.parquet"))
    if not files:
        raise FileNotFoundError(
            f"{root / EPISODES_DIR}: no episode metadata files; the dataset was not finalized "
            "(call LeRobotDataset.finalize() after the last save_episode)"
        )
    videos = video_keys(info)
    columns = [*_EPISODE_COLUMNS, *(f"videos/{key}/{part}" for key in videos for part in ("chunk_index", "file_index"))]
    tables = []
    for path in files:
        names = read_schema(path).names
        missing = [c for c in columns if c not in names]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; not v3.0 episode metadata of info.json's features")
        tables.append(read_table(path, columns=columns))
    rows = pa.concat_tables(tables).to_pylist()
    episodes = [
        EpisodeInfo(
            episode_index=int(row["episode_index"]),
            tasks=tuple(str(t) for t in row["tasks"] or ()),
            length=int(row["length"]),
            from_index=int(row["dataset_from_index"]),
            to_index=int(row["dataset_to_index"]),
            data_file=info["data_path"].format(
                chunk_index=int(row["data/chunk_index"]), file_index=int(row["data/file_index"])
            ),
            video_files=tuple((key, info["video_path"].format(
                video_key=key, chunk_index=int(row[f"videos/{key}/chunk_index"]),
                file_index=int(row[f"videos/{key}/file_index"]))) for key in videos),
        )
        for row in rows
    ]
    episodes.sort(key=lambda e: e.episode_index)
    _check_episodes(root / EPISODES_DIR, episodes)
    return episodes


def _check_episodes(where: Path, episodes: Sequence[EpisodeInfo]) -> None:
    """Raise one ValueError listing every inconsistent episode row."""
    problems = []
    indices = [e.episode_index for e in episodes]
    if len(set(indices)) != len(indices):
        duplicated = sorted({i for i in indices if indices.count(i) > 1})
        problems.append(f"episode index(es) {duplicated} appear more than once")
    for e in episodes:
        if not e.tasks:
            problems.append(f"episode {e.episode_index}: `tasks` is empty")
        if e.to_index - e.from_index != e.length:
            problems.append(
                f"episode {e.episode_index}: dataset_to_index - dataset_from_index = "
                f"{e.to_index - e.from_index}, but `length` is {e.length}"
            )
    if problems:
        raise ValueError(f"{where}: inconsistent episode metadata: " + "; ".join(problems))


def data_files(meta: DatasetMeta) -> list[Path]:
    """Return the absolute paths of the data parquet files the episodes point to, sorted."""
    paths = sorted({meta.root / e.data_file for e in meta.episodes})
    missing = [str(p.relative_to(meta.root)) for p in paths if not p.is_file()]
    if missing:
        raise FileNotFoundError(
            f"{meta.root}: data file(s) {_describe_strings(missing)} listed in {meta.episodes_source} are missing"
        )
    return paths


def _read_data_table(path: Path, columns: Sequence[str], filters: list | None = None) -> pa.Table:
    """Return the named columns of one data file; the single place frame data is read."""
    return read_table(path, columns=list(columns), filters=filters)


def read_index_columns(root: str | os.PathLike) -> IndexColumns:
    """Return `episode_index`, `frame_index`, `index`, `task_index` of every frame, ordered by `index`."""
    meta = read_meta(root)
    tables = []
    for path in data_files(meta):
        names = read_schema(path).names
        missing = [c for c in INDEX_COLUMNS if c not in names]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; not a LeRobot data file")
        tables.append(_read_data_table(path, INDEX_COLUMNS))
    table = pa.concat_tables(tables)
    logger.debug("%s: %d frames in %d data file(s)", meta.root, table.num_rows, len(tables))
    columns = {name: table.column(name).to_numpy().astype(np.int64, copy=False) for name in INDEX_COLUMNS}
    order = np.argsort(columns["index"], kind="stable")
    index = columns["index"][order]
    if index.size and np.any(index[1:] == index[:-1]):
        duplicated = np.unique(index[1:][index[1:] == index[:-1]])
        raise ValueError(
            f"{meta.root}: global `index` value(s) {_describe_ints(duplicated.tolist())} occur in more than one "
            "frame; the data files overlap, re-create the dataset"
        )
    return IndexColumns(**{name: values[order] for name, values in columns.items()})


def read_episode_columns(
    root: str | os.PathLike, episode_indices: Iterable[int], column: str
) -> dict[int, np.ndarray]:
    """Return episode index -> that episode's `column`, (frames, dim) float64 in frame order.

    Only `episode_index`, `frame_index` and `column` are read, one data file at a time,
    with a row filter so other episodes' row groups are skipped.
    """
    meta = read_meta(root)
    feature = _numeric_feature(meta, column)
    dim = int(np.prod(feature.get("shape") or [1]))
    wanted = [meta.episode(int(i)) for i in dict.fromkeys(episode_indices)]
    by_file: dict[str, list[EpisodeInfo]] = {}
    for episode in wanted:
        by_file.setdefault(episode.data_file, []).append(episode)
    result: dict[int, np.ndarray] = {}
    for rel, episodes in by_file.items():
        path = meta.root / rel
        if not path.is_file():
            raise FileNotFoundError(f"{path}: data file of episode(s) {[e.episode_index for e in episodes]} is missing")
        table = _read_data_table(
            path,
            ("episode_index", "frame_index", column),
            filters=[("episode_index", "in", [e.episode_index for e in episodes])],
        )
        values = _column_as_matrix(table.column(column), dim, path, column)
        episode_ids = table.column("episode_index").to_numpy()
        frames = table.column("frame_index").to_numpy()
        for episode in episodes:
            rows = np.flatnonzero(episode_ids == episode.episode_index)
            rows = rows[np.argsort(frames[rows], kind="stable")]
            if not np.array_equal(frames[rows], np.arange(episode.length)):
                raise ValueError(
                    f"{path}: episode {episode.episode_index} has frame_index "
                    f"{_describe_ints(frames[rows].tolist())}, expected 0..{episode.length - 1} "
                    f"(length {episode.length} in {meta.episodes_source}); the dataset is corrupt, re-create it"
                )
            result[episode.episode_index] = _finite_rows(values[rows], path, column, episode.episode_index)
    return {e.episode_index: result[e.episode_index] for e in wanted}


def _finite_rows(values: np.ndarray, path: Path, column: str, episode_index: int) -> np.ndarray:
    """Return an episode's (frames, dim) `values`; ValueError naming the data file, episode, frame and column
    position of the first NaN or Inf (a state or action no step can compute with)."""
    bad = np.argwhere(~np.isfinite(values))
    if len(bad):
        frame, position = (int(i) for i in bad[0])
        raise ValueError(f"{path}: episode {episode_index} frame_index {frame}: `{column}`[{position}] is "
                         f"{values[frame, position]}, expected a finite number ({len(bad)} such value(s) in the "
                         "episode); the dataset is corrupt, re-create it")
    return values


def read_episode_column(root: str | os.PathLike, episode_index: int, column: str) -> np.ndarray:
    """Return one episode's `column` as (frames, dim) float64, in frame order."""
    return read_episode_columns(root, [episode_index], column)[episode_index]


def _numeric_feature(meta: DatasetMeta, column: str) -> dict[str, Any]:
    """Return the info.json feature entry of a numeric column; ValueError for frames or unknown names."""
    features = meta.info["features"]
    if column not in features:
        numeric = sorted(k for k, v in features.items() if v.get("dtype") not in _FRAME_DTYPES)
        raise ValueError(f"{meta.root / INFO_FILE}: no feature {column!r}; numeric features are {numeric}")
    feature = features[column]
    if feature.get("dtype") in _FRAME_DTYPES:
        raise ValueError(
            f"{meta.root / INFO_FILE}: feature {column!r} has dtype {feature.get('dtype')!r}; this reader "
            "returns numeric columns only and never decodes frames (use lerobot's LeRobotDataset for images)"
        )
    return feature


def _column_as_matrix(column: pa.ChunkedArray, dim: int, path: Path, name: str) -> np.ndarray:
    """Return a parquet column of scalars or fixed-length lists as (rows, dim) float64."""
    array = column.combine_chunks()
    if pa.types.is_fixed_size_list(array.type) or pa.types.is_list(array.type):
        flat = array.flatten().to_numpy(zero_copy_only=False)
    else:
        flat = array.to_numpy(zero_copy_only=False)
    if flat.size != len(array) * dim:
        raise ValueError(
            f"{path}: column {name!r} holds {flat.size} values for {len(array)} rows, expected {dim} per row "
            f"(shape in {INFO_FILE}); the dataset is corrupt, re-create it"
        )
    return flat.astype(np.float64).reshape(len(array), dim)


def dataset_fingerprint(root: str | os.PathLike) -> str:
    """Return a sha256 identifying the dataset's content: cheap (no frame data is hashed) and stable.

    Covers the bytes of info.json, the tasks file and every episode metadata file (v2.x: episodes.jsonl
    and, when present, episodes_stats.jsonl or stats.json), plus the name and size of each data file.
    Frame values are not hashed, but the episode metadata holds each episode's per-feature statistics
    (v2.0 without stats: only lengths and tasks), which move with them in practice.
    """
    meta = read_meta(root)
    if meta.is_v2:
        candidates = (lerobot_v2.EPISODES_JSONL, *lerobot_v2.OPTIONAL_META_FILES)
        episode_files = [meta.root / name for name in candidates if (meta.root / name).is_file()]
    else:
        episode_files = sorted((meta.root / EPISODES_DIR).glob("chunk-*/file-*.parquet"))
    record = {
        "info": sha256_file(meta.root / INFO_FILE),
        "tasks": sha256_file(meta.tasks_file),
        "episodes": {p.relative_to(meta.root).as_posix(): sha256_file(p) for p in episode_files},
        "data": {p.relative_to(meta.root).as_posix(): p.stat().st_size for p in data_files(meta)},
    }
    return sha256_json(record)


def resolve_task(meta: DatasetMeta, text: str) -> str:
    """Return the dataset's task text matching `text` exactly, else ignoring case and spacing.

    Raises ValueError naming the closest task texts when nothing (or more than one) matches.
    """
    known = list(dict.fromkeys(meta.tasks.values()))
    if text in known:
        return text
    folded = [t for t in known if _fold(t) == _fold(text)]
    if len(folded) == 1:
        return folded[0]
    if len(folded) > 1:
        raise ValueError(f"{meta.tasks_file}: task {text!r} matches {folded} ignoring case; pass the exact text")
    by_folded = {_fold(t): t for t in known}
    matches = difflib.get_close_matches(_fold(text), list(by_folded), n=_CLOSEST_TASKS, cutoff=0)
    closest = [by_folded[m] for m in matches]
    raise ValueError(
        f"{meta.tasks_file}: task {text!r} is not in the dataset ({len(known)} tasks); "
        f"closest task texts: {closest}"
    )


def _fold(text: str) -> str:
    """Return `text` lower-cased with runs of whitespace collapsed, for forgiving task lookup."""
    return " ".join(text.lower().split())


def _describe_strings(values: Sequence[str]) -> str:
    """Return a short description of a list of names, eliding all but the first few."""
    values = list(values)
    return str(values) if len(values) <= 5 else f"{values[:5]} and {len(values) - 5} more"


def _describe_ints(values: Sequence[int]) -> str:
    """Return a short description of an integer list, eliding the middle of long ones."""
    values = list(values)
    if len(values) <= 12:
        return str(values)
    head = ", ".join(str(v) for v in values[:5])
    tail = ", ".join(str(v) for v in values[-3:])
    return f"[{head}, ... {tail}] ({len(values)} values)"
