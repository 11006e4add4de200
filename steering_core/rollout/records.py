"""One rollout cell's files: `rollouts.json` (identity, per-episode outcomes, success counts) and
`rollouts.safetensors` (per-episode trajectories), plus an MP4 of each episode that recorded frames.

The record names its cell (`cells.Cell`, with its kind, method and mode) and the two LIBERO tasks: `instructed`
(the side's own) and `toward` (the other). An episode's outcome is the first goal reached: "instructed", "toward"
or "neither" by the step limit.

Tensors (E episodes, T the longest episode's steps; shorter episodes padded with NaN): `lengths` (E,) int64 steps,
`actions` (E, T, 7) float32, `robot_qpos` (E, T + 1, 7) float64, `joints/<name>` (E, T + 1) float64 per joint a
goal tests. The JSON is written last, so a folder with it is complete.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from steering_core.layout import ROLLOUT_FILE, rollout_video_file
from steering_core.rollout.cells import Cell
from steering_core.rollout.stats import proportion
from steering_core.rollout.video import DEFAULT_FPS, write_video
from steering_core.storage.fileio import atomic_files, json_text, read_json
from steering_core.tensor_files import load_safetensors, save_safetensors

if TYPE_CHECKING:
    from steering_core.rollout.episode import EpisodeRecord

ROLLOUT_FORMAT_VERSION = 2  # 2: conditions name their method and mode (`sae`, `probe+clamp`); records carry both
OUTCOMES = ("instructed", "toward", "neither")
JOINT_KEY = "joints/"  # tensor name prefix of the goal-tested joints
ADD_UNITS = "residual_norm: × R, the mean residual norm at the steered positions (the evaluation's unit)"
CLAMP_UNITS = ("clamp level: the fraction of the way from this side's concept level (its mean projection on the "
               "direction) to the other concept's")


@dataclass(frozen=True)
class TaskRef:
    """One LIBERO task: its suite, index in the suite and instruction."""

    suite: str
    index: int
    instruction: str


@dataclass(frozen=True)
class CellTasks:
    """A cell's two LIBERO tasks: `instructed`, the side's own, and `toward`, the other side's."""

    instructed: TaskRef
    toward: TaskRef


def _finite(value: float | None) -> float | None:
    """Return a float, or None for a missing or non-finite one (JSON has no NaN)."""
    return None if value is None or not math.isfinite(value) else float(value)


def _step(value: int | None) -> int | None:
    return None if value is None else int(value)


def episode_facts(episode: EpisodeRecord) -> dict[str, Any]:
    """Return the JSON-ready scalar facts of one episode (numpy scalars as Python ones, NaN jerk as None)."""
    return {"init_index": int(episode.init_index), "outcome": episode.outcome, "steps": int(episode.steps),
            "success_step": _step(episode.success_step), "toward_step": _step(episode.toward_step),
            "jerk": _finite(episode.jerk), "joint_limit_hits": int(episode.joint_limit_hits),
            "policy_calls": int(episode.policy_calls), "toward_at_start": bool(episode.toward_at_start)}


def _check_episodes(cell: Cell, episodes: Sequence[EpisodeRecord], seeds: Sequence[int]) -> None:
    """Raise one ValueError listing every episode whose facts or arrays do not fit together."""
    problems = [] if episodes else ["no episodes"]
    if len(seeds) != len(episodes):
        problems.append(f"{len(seeds)} seeds for {len(episodes)} episodes")
    if len({e.prompt for e in episodes}) > 1:
        problems.append(f"episodes saw different prompts {sorted({e.prompt for e in episodes})}")
    if len({tuple(sorted(e.joints)) for e in episodes}) > 1:
        problems.append("episodes record different joints")
    for i, e in enumerate(episodes):
        shapes = {"actions": (e.steps, 7), "robot_qpos": (e.steps + 1, 7)}
        shapes |= {f"joints[{name!r}]": (e.steps + 1,) for name in e.joints}
        arrays = {"actions": e.actions, "robot_qpos": e.robot_qpos} | {f"joints[{n!r}]": v for n, v in e.joints.items()}
        wrong = [f"{key} is {np.shape(arrays[key])}, expected {shape}" for key, shape in shapes.items()
                 if np.shape(arrays[key]) != shape]
        if e.outcome not in OUTCOMES:
            wrong.append(f"outcome {e.outcome!r} is not one of {list(OUTCOMES)}")
        problems += [f"episode {i}: {w}" for w in wrong]
    if problems:
        raise ValueError(f"cell {cell.pair}/{cell.name}: " + "; ".join(problems))


def padded(rows: Sequence[np.ndarray], length: int, dtype: type) -> np.ndarray:
    """Return (E, length, ...) of `rows` (each (t, ...), t <= length) padded with NaN after each row's end."""
    out = np.full((len(rows), length, *np.shape(rows[0])[1:]), np.nan, dtype=dtype)
    for i, row in enumerate(rows):
        out[i, : len(row)] = row
    return out


def cell_arrays(episodes: Sequence[EpisodeRecord]) -> dict[str, np.ndarray]:
    """Return the cell's tensors (module docstring) as numpy arrays."""
    longest = max(e.steps for e in episodes)
    arrays = {
        "lengths": np.array([e.steps for e in episodes], dtype=np.int64),
        "actions": padded([e.actions for e in episodes], longest, np.float32),
        "robot_qpos": padded([e.robot_qpos for e in episodes], longest + 1, np.float64),
    }
    for name in episodes[0].joints:
        arrays[JOINT_KEY + name] = padded([e.joints[name] for e in episodes], longest + 1, np.float64)
    return arrays


def cell_record(cell: Cell, tasks: CellTasks, episodes: Sequence[EpisodeRecord], seeds: Sequence[int],
                run: Mapping[str, Any], videos: Mapping[int, str]) -> dict[str, Any]:
    """Return the JSON of one cell: identity, `run` facts, per-episode facts, outcome counts with Wilson intervals."""
    rows = [{"episode": i, "seed": int(seed), **episode_facts(e), "video": videos.get(i)}
            for i, (e, seed) in enumerate(zip(episodes, seeds, strict=True))]
    n = len(episodes)
    jerks = [row["jerk"] for row in rows if row["jerk"] is not None]
    return {
        "format_version": ROLLOUT_FORMAT_VERSION,
        "cell": cell.name,
        **asdict(cell),
        **asdict(tasks),
        "kind": cell.kind,
        "method": cell.method,
        "mode": cell.mode,
        "alpha_toward": cell.alpha_toward,
        "alpha_units": CLAMP_UNITS if cell.mode == "clamp" else ADD_UNITS,
        "prompt": episodes[0].prompt,
        "joints": sorted(episodes[0].joints),
        "run": dict(run),
        "episodes": rows,
        "success": {outcome: proportion(sum(e.outcome == outcome for e in episodes), n).to_json()
                    for outcome in OUTCOMES},
        "mean_steps": sum(e.steps for e in episodes) / n,
        "mean_jerk": sum(jerks) / len(jerks) if jerks else None,
        "joint_limit_hits": sum(row["joint_limit_hits"] for row in rows),
        "toward_at_start": sum(row["toward_at_start"] for row in rows),
    }


def write_cell(folder: str | Path, cell: Cell, tasks: CellTasks, episodes: Sequence[EpisodeRecord], seeds: Sequence[int],
               run: Mapping[str, Any], fps: float = DEFAULT_FPS, recorded: Mapping[int, Path] | None = None
               ) -> dict[str, Any]:
    """Write one cell's files into `folder` (the cell's own folder, named `cell.name`) and return its record.

    `seeds` are the episodes' env seeds; `run` the run-identity facts (JSON-ready) stored as they are. Each
    episode with frames gets an MP4 named with its cell, index and outcome; `recorded` maps episodes whose MP4 is
    already written (a chunk's) to that file, copied in under the same naming.
    """
    folder = Path(folder)
    _check_episodes(cell, episodes, seeds)
    recorded = recorded or {}
    videos = {i: rollout_video_file(cell.name, i, e.outcome) for i, e in enumerate(episodes)
              if len(e.frames) or i in recorded}
    tensors = {key: torch.from_numpy(value) for key, value in cell_arrays(episodes).items()}
    record = cell_record(cell, tasks, episodes, seeds, run, videos)
    text = json_text(record, folder / f"{ROLLOUT_FILE}.json")
    with atomic_files(folder) as staging:  # the cell's files: all of them, or (on a failure) none
        for i, name in videos.items():
            if i in recorded:
                shutil.copyfile(recorded[i], staging / name)
            else:
                write_video(staging / name, episodes[i].frames, fps=fps)
        save_safetensors(tensors, staging / f"{ROLLOUT_FILE}.safetensors",
                         metadata={"format_version": str(ROLLOUT_FORMAT_VERSION)})
        (staging / f"{ROLLOUT_FILE}.json").write_text(text, encoding="utf-8")
    return record


def read_cell(folder: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Return a cell's record (rollouts.json) and its arrays (rollouts.safetensors, as numpy)."""
    folder = Path(folder)
    json_path = folder / f"{ROLLOUT_FILE}.json"
    record = read_json(json_path)
    if record.get("format_version") != ROLLOUT_FORMAT_VERSION:
        raise ValueError(f"{json_path}: format_version {record.get('format_version')!r}, expected "
                         f"{ROLLOUT_FORMAT_VERSION}; re-run the rollouts of this cell")
    arrays = {key: value.numpy() for key, value in load_safetensors(folder / f"{ROLLOUT_FILE}.safetensors").items()}
    if len(arrays["lengths"]) != len(record["episodes"]):
        raise ValueError(f"{folder}: {len(arrays['lengths'])} episodes in {ROLLOUT_FILE}.safetensors, "
                         f"{len(record['episodes'])} in {ROLLOUT_FILE}.json; re-run the rollouts of this cell")
    return record, arrays


def stored_episodes(record: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> list[EpisodeRecord]:
    """Return the episodes of a cell record (read_cell), their arrays cut back to each episode's length (no frames:
    the videos are files)."""
    from steering_core.rollout.episode import EpisodeRecord

    episodes = []
    for i, row in enumerate(record["episodes"]):
        steps = int(arrays["lengths"][i])
        joints = {name: arrays[JOINT_KEY + name][i, : steps + 1] for name in record["joints"]}
        episodes.append(EpisodeRecord(
            prompt=record["prompt"], init_index=row["init_index"], outcome=row["outcome"], steps=steps,
            success_step=row["success_step"], toward_step=row["toward_step"],
            jerk=math.nan if row["jerk"] is None else row["jerk"], joint_limit_hits=row["joint_limit_hits"],
            policy_calls=row["policy_calls"], joints=joints, robot_qpos=arrays["robot_qpos"][i, : steps + 1],
            actions=arrays["actions"][i, :steps], toward_at_start=row["toward_at_start"]))
    return episodes


def merge_chunks(folder: str | Path, chunk_folders: Sequence[Path], fps: float = DEFAULT_FPS) -> dict[str, Any]:
    """Write the cell of `folder` from its chunks' records (each a cell record of some of its episodes, in order):
    one record over all episodes, the chunks' MP4s copied in under the cell's episode numbers."""
    episodes, seeds, recorded, cell, tasks, run = [], [], {}, None, None, None
    for chunk in chunk_folders:
        record, arrays = read_cell(chunk)
        identity = Cell(**{key: record[key] for key in ("pair", "layer", "side", "condition", "alpha")})
        named = CellTasks(TaskRef(**record["instructed"]), TaskRef(**record["toward"]))
        if cell is not None and (identity, named) != (cell, tasks):
            raise ValueError(f"{chunk}: holds cell {identity.name} of {identity.pair}, not {cell.name}")
        cell, tasks, run = identity, named, record["run"]
        for row in record["episodes"]:
            if row["video"]:
                recorded[len(episodes) + row["episode"]] = Path(chunk) / row["video"]
        episodes += stored_episodes(record, arrays)
        seeds += [row["seed"] for row in record["episodes"]]
    if cell is None:
        raise ValueError(f"{folder}: no chunks to merge")
    return write_cell(folder, cell, tasks, episodes, seeds, {k: v for k, v in run.items() if k != "chunk"}, fps=fps,
                      recorded=recorded)
