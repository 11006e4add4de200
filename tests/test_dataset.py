"""The LeRobot v3.0 reader against lerobot itself, on a dataset written through lerobot's API."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import PIL
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from helpers_dataset import (
    CLOSE,
    OPEN,
    STOVE,
    brute_force_rows,
    contrast_episodes,
    write_contrast_dataset,
)

from steering_core.data.dataset import (
    dataset_fingerprint,
    read_episode_column,
    read_episode_columns,
    read_episodes,
    read_index_columns,
    read_meta,
    resolve_task,
)

FILE_0 = "data/chunk-000/file-000.parquet"
FILE_1 = "data/chunk-000/file-001.parquet"


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return write_contrast_dataset(tmp_path_factory.mktemp("ds") / "contrast")


@pytest.fixture()
def copy(root, tmp_path):
    """A private copy of the dataset that a test may damage."""
    return shutil.copytree(root, tmp_path / "contrast")


def garble_images(root):
    """Replace every PNG in the data files by bytes no decoder accepts; other columns stay identical."""
    for path in sorted((root / "data").glob("chunk-*/file-*.parquet")):
        table = pq.read_table(path)
        images = table.column("image").combine_chunks()
        garbage = pa.StructArray.from_arrays(
            [pa.array([b"not a png"] * len(table), pa.binary()), images.field("path")], fields=list(images.type)
        )
        column = table.schema.get_field_index("image")
        pq.write_table(table.set_column(column, table.schema.field(column), garbage), path)


def test_episodes_match_lerobot_metadata(root):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    lerobot_meta = LeRobotDatasetMetadata("local/test", root=root)
    episodes = read_episodes(root)
    designed = contrast_episodes()
    assert [e.episode_index for e in episodes] == list(range(len(designed)))
    for episode, (task, states) in zip(episodes, designed, strict=True):
        row = lerobot_meta.episodes[episode.episode_index]
        assert episode.tasks == tuple(row["tasks"]) == (task,)
        assert episode.task == task
        assert episode.length == row["length"] == len(states)
        assert (episode.from_index, episode.to_index) == (row["dataset_from_index"], row["dataset_to_index"])
        assert root / episode.data_file == root / lerobot_meta.get_data_file_path(episode.episode_index)
    # reopen_after=4 put episodes 4.. into a second data file
    assert [e.data_file for e in episodes] == [FILE_0] * 4 + [FILE_1] * 3
    meta = read_meta(root)
    tasks = lerobot_meta.tasks
    assert meta.tasks == {int(i): t for t, i in zip(tasks.index, tasks["task_index"], strict=True)}
    assert [e.episode_index for e in meta.episodes_for_task(OPEN)] == [0, 3, 5]
    assert meta.total_frames == sum(len(s) for _, s in designed)


def test_index_columns_match_a_walk_through_lerobot(root):
    expected = brute_force_rows(root)
    columns = read_index_columns(root)
    assert len(columns) == len(expected["index"])
    for name in ("episode_index", "frame_index", "index", "task_index"):
        values = getattr(columns, name)
        assert values.dtype == np.int64
        np.testing.assert_array_equal(values, expected[name][np.argsort(expected["index"])], err_msg=name)
    tasks = read_meta(root).tasks
    assert [tasks[i] for i in columns.task_index] == list(expected["task"])


def test_episode_columns_round_trip_the_designed_values(root):
    designed = contrast_episodes()
    states = read_episode_columns(root, [5, 0, 4, 0], "state")
    assert list(states) == [5, 0, 4]  # request order, duplicates dropped
    for episode, values in states.items():
        assert values.dtype == np.float64 and values.shape == designed[episode][1].shape
        np.testing.assert_array_equal(values, designed[episode][1].astype(np.float64))
    actions = read_episode_column(root, 6, "actions")
    expected = np.repeat((np.arange(len(designed[6][1])) / 100.0).astype(np.float32)[:, None], 7, axis=1)
    np.testing.assert_array_equal(actions, expected.astype(np.float64))
    timestamps = read_episode_column(root, 2, "timestamp")
    assert timestamps.shape == (len(designed[2][1]), 1)
    np.testing.assert_allclose(timestamps[:, 0], np.arange(len(designed[2][1])) / 10.0, rtol=1e-6)


def test_frames_are_never_read(root, copy, monkeypatch):
    requested = []
    real_read_table = pq.read_table

    def spy(path, *args, columns=None, **kwargs):
        requested.append((str(path), columns))
        return real_read_table(path, *args, columns=columns, **kwargs)

    monkeypatch.setattr(pq, "read_table", spy)  # every parquet read (data.parquet_reads)
    read_index_columns(root)
    read_episode_columns(root, range(7), "state")
    dataset_fingerprint(root)
    data_reads = [columns for path, columns in requested if "/data/" in path]
    assert data_reads and all(columns is not None and "image" not in columns for columns in data_reads)
    monkeypatch.undo()

    # With undecodable images, lerobot fails on the first item; our reader does not notice.
    garble_images(copy)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    with pytest.raises(PIL.UnidentifiedImageError):
        LeRobotDataset("local/test", root=copy)[0]
    for name in ("episode_index", "frame_index", "index"):
        np.testing.assert_array_equal(getattr(read_index_columns(copy), name), getattr(read_index_columns(root), name))
    np.testing.assert_array_equal(read_episode_column(copy, 4, "state"), read_episode_column(root, 4, "state"))


def test_fingerprint_is_stable_and_follows_content(root, copy):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    first = dataset_fingerprint(root)
    assert len(first) == 64
    LeRobotDataset("local/test", root=root)  # loading must not touch the files
    assert dataset_fingerprint(root) == first
    assert dataset_fingerprint(copy) == first  # location-independent

    info = json.loads((copy / "meta/info.json").read_text())
    info["robot_type"] = "ur5"
    (copy / "meta/info.json").write_text(json.dumps(info, indent=4))
    assert dataset_fingerprint(copy) != first


def test_fingerprint_sees_a_changed_data_file(copy, root):
    garble_images(copy)
    assert dataset_fingerprint(copy) != dataset_fingerprint(root)


def test_resolve_task(root):
    meta = read_meta(root)
    assert resolve_task(meta, CLOSE) == CLOSE
    assert resolve_task(meta, "  Turn ON the   stove ") == STOVE
    with pytest.raises(ValueError) as err:
        resolve_task(meta, "open the drawer")
    assert f"{root}/meta/tasks.parquet: task 'open the drawer' is not in the dataset (3 tasks); closest task texts: " \
           f"['{OPEN}', '{CLOSE}', '{STOVE}']" in str(err.value)


def test_bad_column_and_episode_requests(root):
    with pytest.raises(ValueError, match=r"feature 'image' has dtype 'image'; this reader returns numeric columns"):
        read_episode_column(root, 0, "image")
    with pytest.raises(ValueError, match=r"no feature 'joints'; numeric features are \['actions', 'episode_index'"):
        read_episode_column(root, 0, "joints")
    with pytest.raises(ValueError, match=r"no episode 99; the dataset has episodes \[0, 1, 2, 3, 4, 5, 6\]"):
        read_episode_column(root, 99, "state")


def test_missing_pieces_are_named(copy, tmp_path):
    with pytest.raises(FileNotFoundError, match=f"{tmp_path / 'nowhere'}: LeRobot dataset folder not found"):
        read_meta(tmp_path / "nowhere")

    (copy / "data/chunk-000/file-001.parquet").unlink()
    with pytest.raises(FileNotFoundError, match=r"data file\(s\) \['data/chunk-000/file-001.parquet'\] listed in "
                                                r"meta/episodes are missing"):
        read_index_columns(copy)
    with pytest.raises(FileNotFoundError, match="file-001.parquet: data file of episode"):
        read_episode_column(copy, 5, "state")

    shutil.rmtree(copy / "meta/episodes")
    with pytest.raises(FileNotFoundError, match=r"meta/episodes: no episode metadata files; the dataset was not fin"):
        read_meta(copy)
    (copy / "meta/tasks.parquet").unlink()
    with pytest.raises(FileNotFoundError, match=r"meta/tasks.parquet: not found"):
        read_meta(copy)
    (copy / "meta/info.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"meta/info.json: not found; .* is not a LeRobot dataset"):
        read_meta(copy)


def test_corrupt_frames_are_reported(copy):
    path = copy / FILE_1
    table = pq.read_table(path)
    keep = pc.invert(
        pc.and_(pc.equal(table["episode_index"], 4), pc.equal(table["frame_index"], 12))
    )
    pq.write_table(table.filter(keep), path)
    with pytest.raises(ValueError, match=r"episode 4 has frame_index .* expected 0..27 \(length 28 in meta/episodes\)"):
        read_episode_column(copy, 4, "state")


def _legacy_folder(root, version):
    (root / "meta").mkdir(parents=True)
    (root / "meta/info.json").write_text(json.dumps({
        "codebase_version": version, "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "total_chunks": 1, "chunks_size": 1000, "features": {}, "total_frames": 3,
    }))
    (root / "meta/tasks.jsonl").write_text('{"task_index": 0, "task": "open the drawer"}\n')
    (root / "meta/episodes.jsonl").write_text('{"episode_index": 0, "tasks": ["open the drawer"], "length": 3}\n')
    return root


def test_v2_metadata_is_read_from_jsonl(tmp_path):
    old = _legacy_folder(tmp_path / "lab" / "libero_old", "v2.1")
    meta = read_meta(old)
    assert (meta.version, meta.tasks, meta.tasks_file) == ("v2.1", {0: "open the drawer"}, old / "meta/tasks.jsonl")
    assert [(e.episode_index, e.tasks, e.length, e.from_index, e.to_index, e.data_file) for e in meta.episodes] == [
        (0, ("open the drawer",), 3, 0, 3, "data/chunk-000/episode_000000.parquet")]
    with pytest.raises(FileNotFoundError, match=r"\['data/chunk-000/episode_000000.parquet'\] listed in "
                                                r"meta/episodes.jsonl are missing"):
        read_index_columns(old)
    future = _legacy_folder(tmp_path / "future", "v4.0")
    with pytest.raises(ValueError, match=r"'v4.0', expected one of \['v2.0', 'v2.1', 'v3.0'\]; re-create"):
        read_meta(future)


def test_tasks_table_without_task_index(copy):
    pd.DataFrame({"name": ["x"]}).to_parquet(copy / "meta/tasks.parquet")
    with pytest.raises(ValueError, match=r"tasks.parquet: no `task_index` column \(found \['name'\]\)"):
        read_meta(copy)
