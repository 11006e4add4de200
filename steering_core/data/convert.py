"""LIBERO hdf5 demos -> LeRobot v3.0 dataset (lerobot's own `LeRobotDataset`) or v2.1 (`v21_writer`).

v2.1 is the layout openpi's pinned lerobot reads and its LIBERO conversion writes, so openpi can
train or evaluate on the converted demos; v3.0 (default) is what lerobot 0.4 reads.

The schema is that of openpi's `physical-intelligence/libero`, which pi05_libero was
trained on: `image` and `wrist_image` (PNG, image_size^2 x 3 uint8), `state` float32 (8) =
ee_pos (3) + ee_ori axis-angle (3) + gripper finger qpos (2), `actions` float32 (7), the
instruction as the task, robot_type "panda", fps 10.

Frames are oriented and resized by `frames_prep` (openpi's orientation and resize; the seed's with
`orientation="as_stored"`, `resize_filter="bicubic"` and `demo_order="lexicographic"`).

Every episode's source (file name, demo key, file sha256, task, length) goes to
`meta/libero_sources.json`; when every source in that record is still present, a
re-run appends only the new episodes.

The same inputs give the same bytes, wherever the output goes: the `datasets` fingerprint lerobot
stamps into each v3.0 data file (a hash of the staging path) is replaced by one of the file's content
(`parquet_fingerprint`); everything else both writers produce is deterministic already.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import groupby
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import Field, field_validator

from steering_core import layout
from steering_core.data.dataset import NO_VIDEO_BACKEND
from steering_core.data.frames_prep import Orientation, ResizeFilter, prepare_frames
from steering_core.data.libero import LiberoDemo, iter_demos, validate_file
from steering_core.data.parquet_fingerprint import content_fingerprint
from steering_core.data.v21_writer import V21Writer
from steering_core.remote.locks import output_lock
from steering_core.reporting.progress import Progress, ProgressCallback
from steering_core.storage.fileio import atomic_dir, read_json, sha256_file, write_json
from steering_core.storage.schema import StrictModel, read_model

if TYPE_CHECKING:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

logger = logging.getLogger(__name__)

SOURCES_FILE = "meta/libero_sources.json"
STATS_FILE = "meta/stats.json"  # lerobot v3.0's dataset statistics, rewritten in sorted key order
SOURCES_FORMAT_VERSION = 1
DEMO_FILE_GLOB = "*.hdf5"
# Files a complete dataset of each version must have; without them lerobot would try the hub.
REQUIRED_DATASET_FILES = {
    "v3.0": ("meta/info.json", "meta/tasks.parquet", "meta/episodes", "data"),
    "v2.1": ("meta/info.json", "meta/tasks.jsonl", "meta/episodes.jsonl", "meta/episodes_stats.jsonl", "data"),
}
DATA_PARQUET_GLOB = "**/*.parquet"  # v3.0 data files, under data/
# A demo's frames are resized in memory, (T, size, size, 3) uint8 per camera: at 512 px a 500-step demo takes
# 375 MiB, at 20000 px one frame takes 1.1 GiB. LIBERO renders 128 px and pi0.5 reads 224 px.
MAX_IMAGE_SIZE = 512

CodebaseVersion = Literal["v3.0", "v2.1"]
DemoOrder = Literal["numeric", "lexicographic"]
Action = Literal["created", "appended", "rebuilt", "unchanged"]


class ConvertSettings(StrictModel):
    """How LIBERO demos become a LeRobot dataset (defaults: openpi's physical-intelligence/libero)."""

    repo_id: str = Field(min_length=1)
    image_size: int = Field(default=256, ge=8, le=MAX_IMAGE_SIZE)  # physical-intelligence/libero frames are 256x256
    orientation: Orientation = "rotate180"           # what pi05_libero saw in training (frames_prep docstring)
    fps: int = Field(default=10, gt=0)               # openpi declares 10 although LIBERO controls at 20 Hz
    robot_type: str = "panda"
    codebase_version: CodebaseVersion = "v3.0"       # v2.1: openpi's pinned lerobot (module docstring)
    resize_filter: ResizeFilter = "antialiased_bilinear"  # bicubic: the seed's converter
    demo_order: DemoOrder = "numeric"                # lexicographic: the seed's sorted(keys)

    @field_validator("repo_id")
    @classmethod
    def _repo_id_is_a_path(cls, repo_id: str) -> str:
        return layout.check_name(repo_id, "repo_id", nested=True)  # the run config's libero_lerobot/<repo_id>


class EpisodeSource(StrictModel):
    """Where one dataset episode came from."""

    episode_index: int = Field(ge=0)
    file: str          # file name (inputs are sorted by it)
    demo: str          # demo_<k>
    sha256: str        # of the whole source file
    task: str          # the instruction, = the dataset task
    length: int = Field(ge=1)

    def key(self) -> tuple[str, str, str]:
        """Return what identifies the source content: (file, demo, sha256)."""
        return (self.file, self.demo, self.sha256)


class SourcesRecord(StrictModel):
    """The content of `meta/libero_sources.json`."""

    format_version: int = SOURCES_FORMAT_VERSION
    repo_id: str
    orientation: Orientation
    image_size: int
    fps: int
    robot_type: str
    # Defaults: what records written before these settings existed were converted with.
    codebase_version: CodebaseVersion = "v3.0"
    resize_filter: ResizeFilter = "antialiased_bilinear"
    demo_order: DemoOrder = "numeric"
    episodes: tuple[EpisodeSource, ...]


@dataclass(frozen=True)
class ConvertResult:
    """What a conversion did."""

    root: Path
    repo_id: str
    action: Action
    episodes_total: int
    episodes_added: int
    frames_total: int


def lerobot_features(image_size: int) -> dict[str, dict]:
    """Return the LeRobot feature spec of physical-intelligence/libero at `image_size`."""
    camera = {"dtype": "image", "shape": (image_size, image_size, 3), "names": ["height", "width", "channel"]}
    return {
        "image": camera,
        "wrist_image": dict(camera),
        "state": {"dtype": "float32", "shape": (8,), "names": ["state"]},
        "actions": {"dtype": "float32", "shape": (7,), "names": ["actions"]},
    }


def plan_sources(input_dirs: Sequence[str | Path], demo_order: DemoOrder = "numeric") -> list[tuple[Path, EpisodeSource]]:
    """Return every episode to convert, in dataset order: files by name, demos by number (or as strings).

    Every file is validated on the way; problems in several files are reported together.
    """
    files = _input_files(input_dirs)
    planned: list[tuple[Path, EpisodeSource]] = []
    problems: list[str] = []
    for path in files:
        try:
            info = validate_file(path)
        except ValueError as err:
            problems.append(str(err))
            continue
        digest = sha256_file(path)
        keys = sorted(info.demo_lengths) if demo_order == "lexicographic" else info.demo_keys
        for key, length in ((k, info.demo_lengths[k]) for k in keys):
            source = EpisodeSource(
                episode_index=len(planned),
                file=path.name,
                demo=key,
                sha256=digest,
                task=info.instruction,
                length=length,
            )
            planned.append((path, source))
    if problems:
        raise ValueError("\n".join(problems))
    return planned


def read_sources(root: str | Path) -> SourcesRecord:
    """Return the validated `meta/libero_sources.json` of a converted dataset."""
    path = Path(root) / SOURCES_FILE
    record = read_model(path, SourcesRecord, what="sources record",
                        fix="re-run `latent-steering convert --rebuild`", format_version=SOURCES_FORMAT_VERSION)
    indices = [e.episode_index for e in record.episodes]
    if indices != list(range(len(indices))):
        raise ValueError(f"{path}: episode_index values are {indices[:10]}..., expected 0, 1, 2, ... in order")
    return record


def convert_libero(
    input_dirs: Sequence[str | Path],
    output_dir: str | Path,
    settings: ConvertSettings,
    *,
    rebuild: bool = False,
    progress: ProgressCallback | None = None,
) -> ConvertResult:
    """Return what was done after converting every demo under `input_dirs` into `output_dir`.

    Without `rebuild`, an existing dataset written by this function with the same settings
    whose sources are all still present (same file, demo and sha256) keeps its episodes and
    indices, and only the new demos are appended after them, in name order, whatever their
    names; any other existing dataset is rebuilt from scratch. Output is staged in a temporary
    sibling and moved into place only when complete.
    """
    output_dir = Path(output_dir)
    planned = plan_sources(input_dirs, settings.demo_order)
    if not planned:
        raise ValueError(f"no demos found in {', '.join(map(str, input_dirs))}")
    new_sources = [source for _, source in planned]

    with output_lock(output_dir):  # a second conversion into it waits, then finds it unchanged
        existing = _existing_record(output_dir)
        reason = "rebuild requested" if rebuild else _rebuild_reason(output_dir, existing, settings, new_sources)
        if existing is not None and reason is None:
            planned = _existing_first(planned, existing)
            new_sources = [source for _, source in planned]
            done = len(existing.episodes)
            if done == len(new_sources):
                logger.info("%s: all %d episodes already converted; nothing to do", output_dir, done)
                return _result(output_dir, settings, "unchanged", new_sources, added=0)
            logger.info("%s: appending %d new episode(s) after %d", output_dir, len(new_sources) - done, done)
            _append(output_dir, planned, done, settings, progress)
            return _result(output_dir, settings, "appended", new_sources, added=len(new_sources) - done)
        if existing is not None:
            logger.info("%s: rebuilding from scratch (%s)", output_dir, reason)
        _create(output_dir, planned, settings, progress)
        action: Action = "created" if existing is None else "rebuilt"
    return _result(output_dir, settings, action, new_sources, added=len(new_sources))


# ----------------------------------------------------------------------------- internals


def _lerobot_class() -> type[LeRobotDataset]:
    """Return lerobot's LeRobotDataset, imported lazily (about 15 s) with hub access off."""
    # lerobot falls back to the hub when local files look incomplete; this tool only works locally.
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset


def open_for_append(repo_id: str, root: Path) -> LeRobotDataset:
    """Open the finalized LeRobot v3.0 dataset at `root` for appending episodes (then `finalize()` it again).

    lerobot 0.4 appends to a dataset opened with `LeRobotDataset(repo_id, root=...)`; lerobot 0.5 and later open
    those read-only and append only through `LeRobotDataset.resume(repo_id, root=...)`.
    """
    cls = _lerobot_class()
    return getattr(cls, "resume", cls)(repo_id, root=root, video_backend=NO_VIDEO_BACKEND)


def _create(
    output_dir: Path,
    planned: list[tuple[Path, EpisodeSource]],
    settings: ConvertSettings,
    progress: ProgressCallback | None,
) -> None:
    """Write a new dataset of every planned episode in a staging folder, then move it onto `output_dir`."""
    with atomic_dir(output_dir, overwrite=True) as tmp:
        features = lerobot_features(settings.image_size)
        if settings.codebase_version == "v2.1":
            dataset = V21Writer.create(tmp, fps=settings.fps, robot_type=settings.robot_type, features=features)
        else:
            dataset = _lerobot_class().create(
                repo_id=settings.repo_id,
                root=tmp,
                fps=settings.fps,
                robot_type=settings.robot_type,
                features=features,
                use_videos=False,  # PNG frames: lossless, and reading needs no FFmpeg
                video_backend=NO_VIDEO_BACKEND,
            )
        _write_episodes(dataset, planned, settings, progress)
        write_json(tmp / SOURCES_FILE, _record(settings, [s for _, s in planned]).model_dump(mode="json"))


def _append(
    output_dir: Path,
    planned: list[tuple[Path, EpisodeSource]],
    done: int,
    settings: ConvertSettings,
    progress: ProgressCallback | None,
) -> None:
    """Add planned[done:] to a copy of the existing dataset, then swap the copy in."""
    with atomic_dir(output_dir, overwrite=True) as tmp:
        shutil.copytree(output_dir, tmp, symlinks=True)
        if settings.codebase_version == "v2.1":
            dataset = V21Writer.open(tmp)
        else:
            dataset = open_for_append(settings.repo_id, tmp)
        _write_episodes(dataset, planned[done:], settings, progress)
        write_json(tmp / SOURCES_FILE, _record(settings, [s for _, s in planned]).model_dump(mode="json"))


def _input_files(input_dirs: Sequence[str | Path]) -> list[Path]:
    """Return the `*.hdf5` files directly inside `input_dirs`, sorted by name (names must be unique)."""
    if not input_dirs:
        raise ValueError("no input folder given: pass --input-dir at least once")
    by_name: dict[str, Path] = {}
    for folder in map(Path, input_dirs):
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder}: input folder not found")
        for path in folder.glob(DEMO_FILE_GLOB):
            if path.name in by_name and by_name[path.name].resolve() != path.resolve():
                raise ValueError(
                    f"{path.name}: found as {by_name[path.name]} and as {path}; "
                    "episode order follows file names, so names must be unique"
                )
            by_name[path.name] = path
    return [by_name[name] for name in sorted(by_name)]


def _existing_record(output_dir: Path) -> SourcesRecord | None:
    """Return the sources record of an existing output, None if there is no output; refuse foreign folders."""
    if not output_dir.exists():
        return None
    if not (output_dir / SOURCES_FILE).is_file():
        if output_dir.is_dir() and not any(output_dir.iterdir()):
            return None
        raise ValueError(
            f"{output_dir}: exists but has no {SOURCES_FILE}, so it was not written by `latent-steering convert`; "
            "remove it or choose another --output-dir"
        )
    try:
        return read_sources(output_dir)
    except ValueError as err:
        logger.warning("%s", err)
        return _unreadable_record()


def _unreadable_record() -> SourcesRecord:
    """Return an empty record that matches no settings, forcing a rebuild of an unreadable output."""
    return SourcesRecord(repo_id="", orientation="as_stored", image_size=0, fps=0, robot_type="", episodes=())


def _rebuild_reason(
    output_dir: Path, existing: SourcesRecord | None, settings: ConvertSettings, new_sources: list[EpisodeSource]
) -> str | None:
    """Return why an existing output cannot be appended to, or None if it can (or does not exist)."""
    if existing is None:
        return None
    wanted = _record(settings, []).model_dump(exclude={"episodes"})
    found = existing.model_dump(exclude={"episodes"})
    changed = [f"{k} {found[k]!r} -> {wanted[k]!r}" for k in wanted if found[k] != wanted[k]]
    if changed:
        return "settings changed: " + ", ".join(changed)
    required = REQUIRED_DATASET_FILES[settings.codebase_version]
    missing = [name for name in required if not (output_dir / name).exists()]
    if missing:
        return f"dataset files missing: {', '.join(missing)}"
    info = read_json(output_dir / "meta/info.json")
    if info.get("total_episodes") != len(existing.episodes):
        listed = len(existing.episodes)
        return f"meta/info.json has {info.get('total_episodes')} episodes but {SOURCES_FILE} lists {listed}"
    current = {s.key() for s in new_sources}
    current_demos = {key[:2] for key in current}
    for old in existing.episodes:
        if old.key() not in current:
            what = "changed (sha256 differs)" if old.key()[:2] in current_demos else "disappeared"
            return f"source {old.file}:{old.demo} of episode {old.episode_index} {what}"
    return None


def _existing_first(
    planned: list[tuple[Path, EpisodeSource]], existing: SourcesRecord
) -> list[tuple[Path, EpisodeSource]]:
    """Return `planned` with the existing episodes first, at their indices, then the new ones in name order.

    Keeping old indices is what lets later steps (capture shards, caches) reuse their work after an append.
    """
    path_of = {source.key(): path for path, source in planned}
    known = {episode.key() for episode in existing.episodes}
    ordered = [(path_of[episode.key()], episode) for episode in existing.episodes]
    ordered += [(path, source) for path, source in planned if source.key() not in known]
    return [(path, source.model_copy(update={"episode_index": i})) for i, (path, source) in enumerate(ordered)]


def _record(settings: ConvertSettings, sources: list[EpisodeSource]) -> SourcesRecord:
    return SourcesRecord(
        repo_id=settings.repo_id,
        orientation=settings.orientation,
        image_size=settings.image_size,
        fps=settings.fps,
        robot_type=settings.robot_type,
        codebase_version=settings.codebase_version,
        resize_filter=settings.resize_filter,
        demo_order=settings.demo_order,
        episodes=tuple(sources),
    )


def _write_episodes(
    dataset: LeRobotDataset | V21Writer,
    planned: list[tuple[Path, EpisodeSource]],
    settings: ConvertSettings,
    progress: ProgressCallback | None,
) -> None:
    """Add every planned episode to `dataset` in order, then finalize a lerobot one (mandatory in lerobot 0.4)."""
    if isinstance(dataset, V21Writer):
        _add_all(dataset, planned, settings, progress)
        return
    from lerobot.utils.utils import SuppressProgressBars  # lerobot is imported by now

    data = Path(dataset.root) / "data"
    before = {path: _stamp(path) for path in data.glob(DATA_PARQUET_GLOB)}  # an append's copied files
    try:
        # we count episodes; the per-episode `datasets` bars lerobot triggers are noise
        with SuppressProgressBars():
            _add_all(dataset, planned, settings, progress)
    except BaseException:
        with contextlib.suppress(Exception):
            dataset.finalize()  # close the parquet writers; the staging folder is discarded anyway
        raise
    dataset.finalize()
    for path in sorted(data.glob(DATA_PARQUET_GLOB)):
        if before.get(path) != _stamp(path):  # written now: its `datasets` fingerprint hashes the staging path
            content_fingerprint(path)
    # lerobot stages PNGs under images/ before embedding them in the parquet files; only empty folders remain
    shutil.rmtree(Path(dataset.root) / "images", ignore_errors=True)
    _sort_stats(Path(dataset.root))


def _sort_stats(root: Path) -> None:
    """Rewrite `meta/stats.json` with sorted keys (lerobot's layout otherwise): lerobot writes the features in
    the order of a set, which changes from process to process, so the same demos gave other bytes each time."""
    path = root / STATS_FILE
    path.write_text(json.dumps(read_json(path), indent=4, ensure_ascii=False, sort_keys=True), encoding="utf-8")


def _stamp(path: Path) -> tuple[int, int]:
    stat = path.stat()
    return stat.st_size, stat.st_mtime_ns


def _add_all(
    dataset: LeRobotDataset | V21Writer,
    planned: list[tuple[Path, EpisodeSource]],
    settings: ConvertSettings,
    progress: ProgressCallback | None,
) -> None:
    """Add the planned episodes in order, reading each source file once."""
    with Progress(len(planned), "convert", "episode", callback=progress, logger=logger) as bar:
        for path, group in groupby(planned, key=lambda item: item[0]):
            sources = [source for _, source in group]
            for demo, source in zip(iter_demos(path, [s.demo for s in sources]), sources, strict=True):
                _add_episode(dataset, demo, path, source, settings)
                bar.update(1)


def _add_episode(
    dataset: LeRobotDataset | V21Writer, demo: LiberoDemo, path: Path, source: EpisodeSource, settings: ConvertSettings
) -> None:
    """Add one demo (of the file at `path`) as the next episode."""
    written = dataset.info["total_episodes"] if isinstance(dataset, V21Writer) else dataset.meta.total_episodes
    if written != source.episode_index:
        raise ValueError(
            f"{path}:{source.demo}: would become episode {written}, "
            f"expected {source.episode_index}; re-run with --rebuild"
        )
    columns = {
        "image": prepare_frames(demo.agentview_rgb, settings.orientation, settings.image_size, settings.resize_filter),
        "wrist_image": prepare_frames(
            demo.eye_in_hand_rgb, settings.orientation, settings.image_size, settings.resize_filter
        ),
        "state": demo.state8(),
        "actions": demo.actions.astype(np.float32),
    }
    if isinstance(dataset, V21Writer):
        dataset.add_episode(columns, source.task)
        return
    for t in range(demo.num_steps):
        dataset.add_frame({**{key: values[t] for key, values in columns.items()}, "task": source.task})
    dataset.save_episode()


def _result(
    root: Path, settings: ConvertSettings, action: Action, sources: list[EpisodeSource], *, added: int
) -> ConvertResult:
    return ConvertResult(
        root=root,
        repo_id=settings.repo_id,
        action=action,
        episodes_total=len(sources),
        episodes_added=added,
        frames_total=sum(s.length for s in sources),
    )
