"""LIBERO -> LeRobot conversion, checked by reading back through lerobot's own LeRobotDataset."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import numpy as np
import pytest
from helpers_libero import TINY, edit_file, sha256_bytes, write_tiny
from helpers_locks import hold_output_lock, start_waiting
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.data import convert as convert_module
from steering_core.data.convert import ConvertSettings, convert_libero, read_sources
from steering_core.data.frames_prep import prepare_frames
from steering_core.data.libero import iter_demos
from steering_core.synthetic.libero import SyntheticSettings

OPEN = "open the top drawer of the cabinet"
CLOSE = "close the top drawer of the cabinet"
STOVE_ON = "turn on the stove"
SETTINGS = ConvertSettings(repo_id="local/libero_test", image_size=16)  # sources are 16 px: no resize


# ----------------------------------------------------------------------------- references


def reference_resize(frames: np.ndarray, size: int) -> np.ndarray:
    """Return frames resized with a separable triangle filter (bilinear, antialiased when shrinking).

    Written from the definition: output pixel i samples input coordinate (i + 0.5) * scale;
    each input pixel centre j + 0.5 weighs max(0, 1 - |j + 0.5 - c| / support) with
    support = max(scale, 1); weights are renormalised at the borders.
    """

    def weights(n_in: int, n_out: int) -> np.ndarray:
        scale = n_in / n_out
        support = max(scale, 1.0)
        centres = (np.arange(n_out) + 0.5) * scale
        w = np.maximum(0.0, 1.0 - np.abs(np.arange(n_in)[None, :] + 0.5 - centres[:, None]) / support)
        return w / w.sum(axis=1, keepdims=True)

    rows, cols = weights(frames.shape[1], size), weights(frames.shape[2], size)
    out = np.einsum("ih,thwc->tiwc", rows, frames.astype(np.float64))  # rows first,
    out = np.einsum("jw,tiwc->tijc", cols, out)                         # then columns
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def read_back(root, repo_id=SETTINGS.repo_id):
    """Return every frame of a dataset as read by lerobot: lists per column, images as HWC uint8."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset(repo_id, root=root)
    frames = [dataset[i] for i in range(len(dataset))]

    def to_uint8(img):
        return np.rint(img.numpy().transpose(1, 2, 0) * 255).astype(np.uint8)

    return {
        "image": np.stack([to_uint8(f["image"]) for f in frames]),
        "wrist_image": np.stack([to_uint8(f["wrist_image"]) for f in frames]),
        "state": np.stack([f["state"].numpy() for f in frames]),
        "actions": np.stack([f["actions"].numpy() for f in frames]),
        "task": [f["task"] for f in frames],
        "episode_index": [int(f["episode_index"]) for f in frames],
        "frame_index": [int(f["frame_index"]) for f in frames],
        "index": [int(f["index"]) for f in frames],
        "episodes": [
            (int(e["episode_index"]), int(e["dataset_from_index"]), int(e["dataset_to_index"]), list(e["tasks"]))
            for e in dataset.meta.episodes
        ],
        "tasks": dict(zip(dataset.meta.tasks.index, dataset.meta.tasks["task_index"].tolist())),
        "info": json.loads((root / "meta" / "info.json").read_text()),  # as written on disk
    }


def assert_same_content(a, b):
    for key in ("image", "wrist_image", "state", "actions"):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    for key in ("task", "episode_index", "frame_index", "index", "episodes", "tasks"):
        assert a[key] == b[key], key


def expected_rows(paths, orientation="rotate180", size=16):
    """Return the frames we expect, built straight from the hdf5 files in dataset order."""
    rows = {"image": [], "wrist_image": [], "state": [], "actions": [], "task": [], "lengths": []}
    for path, task in paths:
        for demo in iter_demos(path):
            for camera, name in (("image", "agentview_rgb"), ("wrist_image", "eye_in_hand_rgb")):
                frames = getattr(demo, name)
                if orientation == "rotate180":
                    frames = np.flip(frames, axis=(1, 2))
                if frames.shape[1] != size:
                    frames = reference_resize(frames, size)
                rows[camera].append(frames)
            rows["state"].append(np.hstack([demo.ee_pos, demo.ee_ori, demo.gripper_states]).astype(np.float32))
            rows["actions"].append(demo.actions.astype(np.float32))
            rows["task"] += [task] * demo.num_steps
            rows["lengths"].append(demo.num_steps)
    return {k: (np.concatenate(v) if k not in ("task", "lengths") else v) for k, v in rows.items()}


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture
def raw(tmp_path):
    """A folder with two drawer files (one with gapped demo keys) and a stove file."""
    folder = tmp_path / "raw"
    settings = TINY.model_copy(update={"length_jitter": 3})
    close = write_tiny(folder, CLOSE, "KITCHEN_SCENE10", num_demos=2, settings=settings).path
    opened = write_tiny(folder, OPEN, "KITCHEN_SCENE1", settings=settings, demo_indices=[0, 2, 10]).path
    stove = write_tiny(folder, STOVE_ON, "KITCHEN_SCENE3", settings=settings).path
    # dataset order: file names sorted ("SCENE10" < "SCENE1_" < "SCENE3"), demos by number
    return folder, [(close, CLOSE), (opened, OPEN), (stove, STOVE_ON)]


# ----------------------------------------------------------------------------- tests


def test_round_trip_through_lerobot(raw, tmp_path):
    folder, files = raw
    out = tmp_path / "lerobot" / "ds"
    seen = []
    result = convert_libero([folder], out, SETTINGS, progress=lambda done, total: seen.append((done, total)))
    expected = expected_rows(files)

    assert result.action == "created" and result.root == out
    assert (result.episodes_total, result.episodes_added) == (6, 6)
    assert result.frames_total == sum(expected["lengths"])
    assert seen == [(i, 6) for i in range(1, 7)]
    assert os.environ["HF_HUB_OFFLINE"] == "1"

    back = read_back(out)
    np.testing.assert_array_equal(back["state"], expected["state"])
    np.testing.assert_array_equal(back["actions"], expected["actions"])
    np.testing.assert_array_equal(back["image"], expected["image"])          # = source flipped along H and W
    np.testing.assert_array_equal(back["wrist_image"], expected["wrist_image"])
    assert back["task"] == expected["task"]
    bounds = np.cumsum([0, *expected["lengths"]])
    assert [(e[0], e[1], e[2]) for e in back["episodes"]] == [(i, bounds[i], bounds[i + 1]) for i in range(6)]
    assert back["index"] == list(range(bounds[-1]))
    assert back["frame_index"] == [t for n in expected["lengths"] for t in range(n)]

    info = back["info"]
    assert (info["fps"], info["robot_type"], info["codebase_version"]) == (10, "panda", "v3.0")
    assert info["features"]["image"]["dtype"] == "image" and info["features"]["image"]["shape"] == [16, 16, 3]
    assert info["features"]["state"]["shape"] == [8] and info["features"]["actions"]["shape"] == [7]
    assert not (out / "images").exists()  # lerobot's PNG staging folder is gone
    assert sorted(p.name for p in out.parent.iterdir()) == [".ds.lock", "ds"]  # only its lock beside the output


def test_sources_record_traces_every_episode(raw, tmp_path):
    folder, files = raw
    out = tmp_path / "ds"
    convert_libero([folder], out, SETTINGS)
    record = json.loads((out / "meta" / "libero_sources.json").read_text())
    assert record["format_version"] == 1
    assert (record["orientation"], record["image_size"], record["fps"]) == ("rotate180", 16, 10)
    episodes = record["episodes"]
    assert [(e["episode_index"], e["file"], e["demo"], e["task"]) for e in episodes] == [
        (0, files[0][0].name, "demo_0", CLOSE),
        (1, files[0][0].name, "demo_1", CLOSE),
        (2, files[1][0].name, "demo_0", OPEN),
        (3, files[1][0].name, "demo_2", OPEN),
        (4, files[1][0].name, "demo_10", OPEN),  # numeric, not lexicographic, order
        (5, files[2][0].name, "demo_0", STOVE_ON),
    ]
    for entry in episodes:
        assert entry["sha256"] == sha256_bytes(folder / entry["file"])
        assert entry["length"] == next(iter_demos(folder / entry["file"], [entry["demo"]])).num_steps
    assert read_sources(out).episodes[4].demo == "demo_10"


def test_as_stored_orientation_keeps_raw_frames(raw, tmp_path):
    folder, files = raw
    out = tmp_path / "ds"
    convert_libero([folder], out, SETTINGS.model_copy(update={"orientation": "as_stored"}))
    back = read_back(out)
    expected = expected_rows(files, orientation="as_stored")
    np.testing.assert_array_equal(back["image"], expected["image"])
    np.testing.assert_array_equal(back["wrist_image"], expected["wrist_image"])


def test_prepare_frames_matches_reference_resize():
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, size=(3, 32, 32, 3), dtype=np.uint8)
    np.testing.assert_array_equal(prepare_frames(frames, "rotate180", 32), frames[:, ::-1, ::-1])
    np.testing.assert_array_equal(prepare_frames(frames, "as_stored", 32), frames)
    for size in (16, 20, 48, 64):  # shrink (antialiased) and grow, integer and fractional ratios
        got = prepare_frames(frames, "rotate180", size).astype(int)
        want = reference_resize(np.flip(frames, axis=(1, 2)), size).astype(int)
        assert got.shape == (3, size, size, 3)
        assert np.abs(got - want).max() <= 1, size


def test_real_size_path_128_to_256(tmp_path):
    """One tiny episode at LIBERO's real 128 px, converted with the default 256 px settings."""
    folder = tmp_path / "raw"
    path = write_tiny(folder, STOVE_ON, "KITCHEN_SCENE3", settings=SyntheticSettings(num_steps=8, state_dim=12)).path
    out = tmp_path / "ds"
    convert_libero([folder], out, ConvertSettings(repo_id="local/libero_256"))
    back = read_back(out, "local/libero_256")
    (demo,) = iter_demos(path)
    assert demo.agentview_rgb.shape[1:] == (128, 128, 3)
    assert back["image"].shape == (8, 256, 256, 3)
    for camera, name in (("image", "agentview_rgb"), ("wrist_image", "eye_in_hand_rgb")):
        want = reference_resize(np.flip(getattr(demo, name), axis=(1, 2)), 256).astype(int)
        assert np.abs(back[camera].astype(int) - want).max() <= 1
    # upright after rotate180: the synthetic scene's bright wall is at the top
    assert back["image"][:, :64, :, 0].mean() > back["image"][:, -64:, :, 0].mean() + 50
    assert back["info"]["features"]["image"]["shape"] == [256, 256, 3]


def assert_same_bytes(one, two, expected_file):
    """Every file under `one` and `two` has the same bytes, and `expected_file` is among them."""
    ours, theirs = ({str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
                    for root in (one, two))
    assert expected_file in ours
    assert ours.keys() == theirs.keys()
    assert [name for name in ours if ours[name] != theirs[name]] == []


def test_converting_twice_gives_equal_data(raw, tmp_path):
    folder, _ = raw
    first = convert_libero([folder], tmp_path / "one", SETTINGS)
    second = convert_libero([folder], tmp_path / "elsewhere" / "two", SETTINGS)
    assert first.frames_total == second.frames_total
    assert_same_content(read_back(tmp_path / "one"), read_back(tmp_path / "elsewhere" / "two"))
    assert read_sources(tmp_path / "one") == read_sources(tmp_path / "elsewhere" / "two")
    # the same bytes, every file, although lerobot staged each in another (randomly named) folder
    assert_same_bytes(tmp_path / "one", tmp_path / "elsewhere" / "two", "data/chunk-000/file-000.parquet")


@pytest.mark.slow
def test_converts_in_two_processes_write_equal_bytes(raw, tmp_path):
    """Two `convert` processes with different string hashing (set orders differ) write the same bytes, every file:
    lerobot writes meta/stats.json's features in a set's order, which convert sorts."""
    folder, _ = raw
    for seed, name in (("1", "one"), ("2", "two")):
        subprocess.run([sys.executable, "-c", "from latent_steering_cli import app; app()", "convert", "--input-dir",
                        str(folder), "--repo-id", "local/libero_test", "--output-dir", str(tmp_path / name),
                        "--image-size", "16"],
                       env={**os.environ, "PYTHONHASHSEED": seed}, check=True, capture_output=True)
    assert_same_bytes(tmp_path / "one", tmp_path / "two", "meta/stats.json")


def test_append_is_byte_deterministic(raw, tmp_path):
    """Two identical append sequences write the same bytes; the appended data file gets a content fingerprint."""
    folder, _ = raw
    extra = tmp_path / "extra"
    write_tiny(extra, "turn off the stove", "KITCHEN_SCENE8", num_demos=2)
    for name in ("one", "two"):
        convert_libero([folder], tmp_path / name, SETTINGS)
        assert convert_libero([folder, extra], tmp_path / name, SETTINGS).action == "appended"
    assert_same_bytes(tmp_path / "one", tmp_path / "two", "data/chunk-000/file-001.parquet")  # a file per call


def test_v21_conversion_is_byte_deterministic(raw, tmp_path):
    folder, _ = raw
    settings = SETTINGS.model_copy(update={"codebase_version": "v2.1"})
    convert_libero([folder], tmp_path / "one", settings)
    convert_libero([folder], tmp_path / "elsewhere" / "two", settings)
    assert_same_bytes(tmp_path / "one", tmp_path / "elsewhere" / "two", "data/chunk-000/episode_000005.parquet")


def test_incremental_append_equals_full_conversion(raw, tmp_path):
    folder, _ = raw
    out = tmp_path / "ds"
    convert_libero([folder], out, SETTINGS)
    before = (out / "meta" / "libero_sources.json").stat().st_mtime_ns
    assert convert_libero([folder], out, SETTINGS).action == "unchanged"
    assert (out / "meta" / "libero_sources.json").stat().st_mtime_ns == before

    # new files sorting after the existing ones, in a second input folder
    extra = tmp_path / "extra"
    write_tiny(extra, "turn off the stove", "KITCHEN_SCENE8", num_demos=2)
    write_tiny(extra, "pick up the milk and put it in the basket", "LIVING_ROOM_SCENE2")
    seen = []
    result = convert_libero([folder, extra], out, SETTINGS, progress=lambda d, t: seen.append((d, t)))
    assert result.action == "appended"
    assert (result.episodes_total, result.episodes_added) == (9, 3)
    assert seen == [(1, 3), (2, 3), (3, 3)]

    scratch = convert_libero([folder, extra], tmp_path / "scratch", SETTINGS)
    assert scratch.action == "created" and scratch.frames_total == result.frames_total
    appended, full = read_back(out), read_back(tmp_path / "scratch")
    assert_same_content(appended, full)
    assert read_sources(out) == read_sources(tmp_path / "scratch")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".ds.lock", ".scratch.lock", "ds", "extra", "raw", "scratch"]


def test_append_keeps_old_indices_when_a_new_file_sorts_first(raw, tmp_path):
    folder, files = raw
    out = tmp_path / "ds"
    convert_libero([folder], out, SETTINGS)
    before, record_before = read_back(out), read_sources(out)
    early = tmp_path / "early"
    added = write_tiny(early, "turn off the stove", "KITCHEN_SCENE0", num_demos=2).path  # sorts before all
    result = convert_libero([early, folder], out, SETTINGS)
    assert (result.action, result.episodes_added, result.episodes_total) == ("appended", 2, 8)

    after = read_back(out)
    n_old = len(before["task"])
    for key in ("image", "state", "actions"):
        np.testing.assert_array_equal(after[key][:n_old], before[key], err_msg=key)
    assert after["episodes"][: len(before["episodes"])] == before["episodes"]
    expected_new = expected_rows([(added, "turn off the stove")])
    np.testing.assert_array_equal(after["state"][n_old:], expected_new["state"])
    np.testing.assert_array_equal(after["image"][n_old:], expected_new["image"])
    record = read_sources(out)
    assert [(e.episode_index, e.file) for e in record.episodes[-2:]] == [(6, added.name), (7, added.name)]
    assert record.episodes[:6] == record_before.episodes


def test_changed_or_missing_sources_trigger_rebuild(raw, tmp_path, caplog):
    folder, files = raw
    out = tmp_path / "ds"
    convert_libero([folder], out, SETTINGS)
    caplog.set_level(logging.INFO, logger="steering_core.data.convert")

    stove = files[2][0]
    edit_file(stove, lambda h: h["data/demo_0/actions"].__setitem__((0, 0), 0.5))
    result = convert_libero([folder], out, SETTINGS)
    assert result.action == "rebuilt"
    assert f"source {stove.name}:demo_0 of episode 5 changed (sha256 differs)" in caplog.text
    assert read_back(out)["actions"][-stove_len(stove), 0] == pytest.approx(0.5)

    files[0][0].unlink()  # the first file disappears: every later episode shifts
    result = convert_libero([folder], out, SETTINGS)
    assert result.action == "rebuilt" and result.episodes_total == 4
    assert f"source {files[0][0].name}:demo_0 of episode 0 disappeared" in caplog.text

    result = convert_libero([folder], out, SETTINGS.model_copy(update={"image_size": 24}))
    assert result.action == "rebuilt" and "settings changed: image_size 16 -> 24" in caplog.text
    assert read_back(out)["image"].shape[1:] == (24, 24, 3)

    result = convert_libero([folder], out, SETTINGS.model_copy(update={"image_size": 24}), rebuild=True)
    assert result.action == "rebuilt" and "rebuild requested" in caplog.text


def stove_len(path):
    return next(iter_demos(path)).num_steps


def test_failure_midway_leaves_nothing_behind(raw, tmp_path, monkeypatch):
    folder, _ = raw
    real_add = convert_module._add_episode
    calls = []

    def flaky(dataset, demo, path, source, settings):
        calls.append(source.episode_index)
        if len(calls) == 3:
            raise RuntimeError("disk full")
        real_add(dataset, demo, path, source, settings)

    parent = tmp_path / "lerobot"
    parent.mkdir()
    monkeypatch.setattr(convert_module, "_add_episode", flaky)
    with pytest.raises(RuntimeError, match="disk full"):
        convert_libero([folder], parent / "ds", SETTINGS)
    assert list(parent.iterdir()) == []

    # an append that fails leaves the existing dataset exactly as it was
    monkeypatch.setattr(convert_module, "_add_episode", real_add)
    convert_libero([folder], parent / "ds", SETTINGS)
    record_before = (parent / "ds" / "meta" / "libero_sources.json").read_bytes()
    write_tiny(tmp_path / "extra", "turn off the stove", "KITCHEN_SCENE8", num_demos=3)
    calls.clear()
    monkeypatch.setattr(convert_module, "_add_episode", flaky)
    with pytest.raises(RuntimeError, match="disk full"):
        convert_libero([folder, tmp_path / "extra"], parent / "ds", SETTINGS)
    assert sorted(p.name for p in parent.iterdir()) == [".ds.lock", "ds"]
    assert (parent / "ds" / "meta" / "libero_sources.json").read_bytes() == record_before
    assert read_back(parent / "ds")["episodes"][-1][0] == 5


def test_bad_inputs(raw, tmp_path):
    folder, files = raw
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="no meta/libero_sources.json, so it was not written by `latent-steering"):
        convert_libero([folder], foreign, SETTINGS)
    assert (foreign / "keep.txt").exists()
    with pytest.raises(FileNotFoundError, match="input folder not found"):
        convert_libero([tmp_path / "nope"], tmp_path / "ds", SETTINGS)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no demos found"):
        convert_libero([empty], tmp_path / "ds", SETTINGS)
    edit_file(files[1][0], lambda h: h["data/demo_2/obs"].__delitem__("ee_ori"))
    edit_file(files[2][0], lambda h: h["data/demo_0/obs"].__delitem__("gripper_states"))
    with pytest.raises(ValueError) as err:
        convert_libero([folder], tmp_path / "ds", SETTINGS)
    assert "data/demo_2/obs/ee_ori is missing" in str(err.value)           # both bad files named at once
    assert "data/demo_0/obs/gripper_states is missing" in str(err.value)
    assert not (tmp_path / "ds").exists()
    with pytest.raises(ValueError):
        ConvertSettings(repo_id="x", orientation="upside_down")


def test_cli_convert(raw, tmp_path):
    folder, _ = raw
    out = tmp_path / "ds"
    runner = CliRunner()
    args = ["convert", "--input-dir", str(folder), "--repo-id", "local/cli", "--output-dir", str(out)]
    args += ["--image-size", "16"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "created" in result.output and "6 episodes" in result.output
    assert read_back(out, "local/cli")["image"].shape[1:] == (16, 16, 3)
    result = runner.invoke(app, [*args, "--rebuild", "--orientation", "as_stored"])
    assert result.exit_code == 0, result.output
    assert "rebuilt" in result.output and read_sources(out).orientation == "as_stored"
    result = runner.invoke(app, [*args, "--orientation", "sideways"])
    assert result.exit_code == 2


def test_a_second_conversion_waits_for_another_process_then_finds_the_dataset_done(raw, tmp_path, monkeypatch):
    import shutil

    folder, _ = raw
    convert_libero([folder], tmp_path / "reference", SETTINGS)
    creates = []
    real_create = convert_module._create
    monkeypatch.setattr(convert_module, "_create", lambda *a, **k: creates.append(1) or real_create(*a, **k))
    out = tmp_path / "shared" / "ds"
    holder = hold_output_lock(out)
    worker, outcome = start_waiting(lambda: convert_libero([folder], out, SETTINGS))
    assert not out.exists() and creates == []  # waiting, nothing written
    shutil.copytree(tmp_path / "reference", out)  # the other process finishes the dataset
    holder.communicate("done\n", timeout=30)
    worker.join(timeout=120)
    assert outcome["result"].action == "unchanged" and creates == []  # converted once, by the other process
    assert_same_content(read_back(out), read_back(tmp_path / "reference"))
