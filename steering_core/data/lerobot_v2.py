"""LeRobot v2.0 / v2.1 metadata: the jsonl files of `meta/` and the per-episode file layout.

The facts (docs/PI05_SPEC.md §8.2) are those of the lerobot commit openpi pins: one data parquet
per episode at `data_path.format(episode_chunk=ep // chunks_size, episode_index=ep)`, task texts
in `meta/tasks.jsonl`, episodes (index, tasks, length) in `meta/episodes.jsonl`, global `index`
values assigned in episode order. v2.1 adds `meta/episodes_stats.jsonl`; v2.0 may have
`meta/stats.json` or no statistics at all. Only reading lives here; `v21_writer` writes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from steering_core.storage.fileio import parse_json, read_text

V2_VERSIONS = ("v2.0", "v2.1")
TASKS_JSONL = "meta/tasks.jsonl"
EPISODES_JSONL = "meta/episodes.jsonl"
EPISODES_STATS_JSONL = "meta/episodes_stats.jsonl"  # v2.1 only
STATS_JSON = "meta/stats.json"  # v2.0, optional
# Files that exist in some v2.x datasets and describe their content (hashed by the fingerprint).
OPTIONAL_META_FILES = (EPISODES_STATS_JSONL, STATS_JSON)


def read_jsonl(path: Path, required: tuple[str, ...]) -> list[dict[str, Any]]:
    """Return the objects of a jsonl file, each checked to have the `required` keys."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not found; a LeRobot v2.x dataset needs it")
    rows = []
    for number, line in enumerate(read_text(path, "a JSON lines file").splitlines(), start=1):
        if not line.strip():
            continue
        row = parse_json(line, f"{path}:{number}")
        if not isinstance(row, dict) or any(k not in row for k in required):
            found = sorted(row) if isinstance(row, dict) else type(row).__name__
            raise ValueError(f"{path}:{number}: expected an object with keys {list(required)}, found {found}")
        rows.append(row)
    return rows


def read_tasks(root: Path) -> dict[int, str]:
    """Return task_index -> task text from `meta/tasks.jsonl`."""
    path = root / TASKS_JSONL
    rows = read_jsonl(path, ("task_index", "task"))
    tasks = {int(row["task_index"]): str(row["task"]) for row in rows}
    if len(tasks) != len(rows):
        raise ValueError(f"{path}: `task_index` has duplicates; the tasks file is corrupt")
    return tasks


def episode_data_file(info: dict[str, Any], episode_index: int) -> str:
    """Return the data parquet of one episode, relative to the dataset root."""
    chunk = episode_index // int(info["chunks_size"])
    return info["data_path"].format(episode_chunk=chunk, episode_index=episode_index)


def episode_video_file(info: dict[str, Any], episode_index: int, video_key: str) -> str:
    """Return the mp4 of one episode's camera `video_key`, relative to the dataset root."""
    chunk = episode_index // int(info["chunks_size"])
    return info["video_path"].format(episode_chunk=chunk, video_key=video_key, episode_index=episode_index)


def read_episode_rows(root: Path) -> list[tuple[int, tuple[str, ...], int]]:
    """Return (episode_index, tasks, length) of every line of `meta/episodes.jsonl`, sorted by episode index."""
    rows = read_jsonl(root / EPISODES_JSONL, ("episode_index", "tasks", "length"))
    episodes = [(int(r["episode_index"]), tuple(str(t) for t in r["tasks"] or ()), int(r["length"])) for r in rows]
    return sorted(episodes)
