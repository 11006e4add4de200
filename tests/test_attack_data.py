"""The bad-input table, round four, area "data": the data a step reads comes from the files the user named, and a
bad frame anywhere in a dataset is one line.

- An HDF5 demo dataset whose values lie in another file (external raw storage, a virtual dataset) is refused like
  an external link, before a byte of it is read.
- A LeRobot dataset whose frame at some later row is empty, declares another size in its PNG header (refused
  from the header, before decoding), or whose video feature has no files; an `info.json` field of the wrong type.

Each refused in one line naming the file and the dataset, episode and frame, or key (`helpers_attack`).
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from helpers_attack import Attack, Case, World, assert_refused, dataset_copy, good, registrar
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.data.image_cells import PNG_SIGNATURE

CASES: list[Attack] = []
case = registrar(CASES)


# ----------------------------------------------------------------------------- HDF5 demos reading another file

def replaced_demo_dataset(world: World, tmp_path: Path, name: str,
                          create: Callable[[h5py.File, str, np.ndarray], None]) -> tuple[Path, Path]:
    """Copy the run's demo folder; in its first file, recreate `data/demo_0/<name>` with `create(file, key, values)`
    (the values it held). Return (folder, file)."""
    folder = tmp_path / "demos"
    shutil.copytree(world.inputs / "inputs" / "demos", folder)
    target = sorted(folder.glob("*.hdf5"))[0]
    with h5py.File(target, "r+") as handle:
        key = f"data/demo_0/{name}"
        values = handle[key][()]
        del handle[key]
        create(handle, key, values)
    return folder, target


def convert_case(folder: Path, tmp_path: Path, *names: str) -> Case:
    return Case(["convert", "--input-dir", folder, "--repo-id", "outside", "--output-dir", tmp_path / "out",
                 "--image-size", "32"], names)


def external_storage(name: str, relative: bool) -> None:
    """`convert` of a demo whose `name` keeps its (good) values in a raw file outside the demo folder."""
    @case(f"convert_demo_{name.replace('/', '_')}_in_external_{'relative' if relative else 'absolute'}_storage")
    def attack(world: World, tmp_path: Path) -> Case:
        outside = tmp_path / "elsewhere" / "values.bin"
        outside.parent.mkdir()

        def create(handle: h5py.File, key: str, values: np.ndarray) -> None:
            values.tofile(outside)
            file = str(Path("..") / "elsewhere" / outside.name) if relative else str(outside)
            handle.create_dataset(key, shape=values.shape, dtype=values.dtype,
                                  external=[(file, 0, values.nbytes)])

        folder, target = replaced_demo_dataset(world, tmp_path, name, create)
        return convert_case(folder, tmp_path, str(target), f"data/demo_0/{name}", outside.name, "external storage")


for _name, _relative in (("actions", False), ("actions", True), ("obs/agentview_rgb", False)):
    external_storage(_name, _relative)


def virtual(name: str, source: str) -> None:
    """`convert` of a demo whose `name` is a virtual dataset mapping another file's dataset, or its own file's."""
    @case(f"convert_demo_{name}_virtual_of_{source}")
    def attack(world: World, tmp_path: Path) -> Case:
        other = tmp_path / "elsewhere.hdf5"

        def create(handle: h5py.File, key: str, values: np.ndarray) -> None:
            if source == "another_file":
                with h5py.File(other, "w") as outside:
                    outside["values"] = values
                file, dataset = str(other), "values"
            else:
                handle[f"{key}_copy"] = values
                file, dataset = ".", f"/{key}_copy"
            layout = h5py.VirtualLayout(shape=values.shape, dtype=values.dtype)
            layout[...] = h5py.VirtualSource(file, dataset, shape=values.shape)
            handle.create_virtual_dataset(key, layout)

        folder, target = replaced_demo_dataset(world, tmp_path, name, create)
        expect = f"{other}:values" if source == "another_file" else "is a virtual dataset"
        return convert_case(folder, tmp_path, str(target), f"data/demo_0/{name}", expect)


for _source in ("another_file", "its_own_file"):
    virtual("states", _source)


# ----------------------------------------------------------------------------- LeRobot frames: a bad one later on

def capture_case(world: World, tmp_path: Path, dataset: Path, *names: str, workers: int = 0) -> Case:
    argv = [str(arg) for arg in good(world, tmp_path)["capture"]]
    argv[argv.index("--lerobot-root") + 1] = str(dataset)
    argv[argv.index("--num-workers") + 1] = str(workers)
    return Case(["capture", *argv], names)


def png(height: int, width: int) -> bytes:
    """A real black RGB PNG of height x width, compressed row by row (a 16000x16000 one is ~750 KB)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    compressor, row = zlib.compressobj(9), b"\0" * (1 + 3 * width)
    pixels = b"".join(compressor.compress(row) for _ in range(height)) + compressor.flush()
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return PNG_SIGNATURE + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b"")


def v21_dataset(world: World, tmp_path: Path) -> Path:
    """The world's demos converted to a LeRobot v2.1 dataset (openpi's layout, read by `V2Frames`) under `tmp_path`."""
    dataset = tmp_path / "dataset"
    good_convert = [str(arg) for arg in good(world, tmp_path)["convert"]]
    good_convert[good_convert.index("--output-dir") + 1] = str(dataset)
    good_convert[good_convert.index("--image-size") + 1] = "64"
    result = CliRunner().invoke(app, ["convert", *good_convert, "--codebase-version", "v2.1"])
    assert result.exit_code == 0, result.output
    return dataset


def with_image_cell(dataset: Path, frame: int, cell: dict) -> tuple[Path, int]:
    """Put `cell` in camera `image` at `frame` of the dataset's first data file; return (the file, its episode)."""
    data_file = sorted((dataset / "data").rglob("*.parquet"))[0]
    table = pq.read_table(data_file)
    assert table.column("frame_index")[frame].as_py() == frame
    cells = table.column("image").to_pylist()
    cells[frame] = cell
    field = table.schema.field("image")
    pq.write_table(table.set_column(table.schema.get_field_index("image"), field, pa.array(cells, type=field.type)),
                   data_file)
    return data_file, table.column("episode_index")[frame].as_py()


def bad_frame(name: str, frame: int, cell: Callable[[], dict], *expect: str, workers: int = 0,
              v21: bool = False) -> None:
    """`capture` of a dataset (v3.0, or v2.1) whose camera `image` at frame `frame` of its first data file is
    `cell()`; the error names the file, episode and frame, and `expect`."""
    @case(name)
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = v21_dataset(world, tmp_path) if v21 else dataset_copy(world, tmp_path)
        data_file, episode = with_image_cell(dataset, frame, cell())
        return capture_case(world, tmp_path, dataset, str(data_file), f"episode {episode} frame {frame}", *expect,
                            workers=workers)


def empty() -> dict:
    return {"bytes": b"", "path": None}


bad_frame("capture_empty_image_cell_at_frame_3", 3, empty, "camera 'image' is not a PNG")
bad_frame("capture_empty_image_cell_at_frame_3_in_a_worker", 3, empty, "camera 'image' is not a PNG", workers=1)
bad_frame("capture_16000x16000_png_at_frame_5", 5, lambda: {"bytes": png(16000, 16000), "path": None},
          "camera 'image' is a 16000x16000 PNG")
bad_frame("capture_v21_16000x16000_png_at_frame_5", 5, lambda: {"bytes": png(16000, 16000), "path": None},
          "camera 'image' is a 16000x16000 PNG", v21=True)
bad_frame("capture_65x64_png_at_frame_4", 4, lambda: {"bytes": png(65, 64), "path": None},
          "camera 'image' is a 65x64 PNG")
bad_frame("capture_truncated_png_at_frame_2", 2, lambda: {"bytes": png(64, 64)[:60], "path": None},
          "cannot be decoded")


def test_evaluation_frames_are_checked_like_capture(attack_world, tmp_path):
    """The evaluation reads its frames through capture's checks: a 65x64 PNG at frame 4 is one ValueError naming
    the data file, episode and frame (a changed dataset never reaches it through the CLI: its fingerprint differs
    from the manifest's)."""
    from steering_core.evaluate.frames import EvalFrame, load_frames

    dataset = dataset_copy(attack_world, tmp_path)
    data_file, episode = with_image_cell(dataset, 4, {"bytes": png(65, 64), "path": None})
    index = pq.read_table(data_file, columns=["index"]).column("index")[4].as_py()
    with pytest.raises(ValueError, match=rf"^{data_file}: episode {episode} frame 4: camera 'image' is a 65x64 PNG"):
        load_frames(dataset, "libero_demo_lerobot", [EvalFrame("positive", episode, 4, index)], 32)


def info_case(name: str, edit: Callable[[dict], None], *expect: str) -> None:
    """`manifest` of a dataset whose info.json was changed by `edit`."""
    @case(name)
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = dataset_copy(world, tmp_path)
        info_path = dataset / "meta" / "info.json"
        info = json.loads(info_path.read_text())
        edit(info)
        info_path.write_text(json.dumps(info))
        return Case(["manifest", "--lerobot-root", dataset, "--task-a-index", "0", "--task-b-index", "1",
                     "--output", tmp_path / "m.json"], (str(info_path), *expect))


info_case("info_features_a_string", lambda info: info.update(features="image"), "`features`", "a JSON object")
info_case("info_features_a_list", lambda info: info.update(features=["image"]), "`features`", "a JSON object")
info_case("info_feature_a_string", lambda info: info["features"].update(image="png"), "`features.image`",
          "a JSON object")
info_case("info_feature_shape_a_string", lambda info: info["features"]["state"].update(shape="8"),
          "`features.state.shape`", "a list of positive integers")
info_case("info_feature_dtype_a_number", lambda info: info["features"]["state"].update(dtype=32),
          "`features.state.dtype`", "a string")
info_case("info_total_frames_a_string", lambda info: info.update(total_frames="207"), "`total_frames`",
          "an integer")


def video_feature(files_named: bool) -> None:
    """`capture` of a dataset whose camera `image` is a video feature (its column gone from the data files) without
    any video file: declared in full (`video_path`, each episode's video chunk and file), or without `video_path`."""
    @case(f"capture_video_feature_without_files{'' if files_named else '_or_video_path'}")
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = dataset_copy(world, tmp_path)
        info_path = dataset / "meta" / "info.json"
        info = json.loads(info_path.read_text())
        info["features"]["image"]["dtype"] = "video"
        if files_named:
            info["video_path"] = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
        info_path.write_text(json.dumps(info))
        for data_file in (dataset / "data").rglob("*.parquet"):
            pq.write_table(pq.read_table(data_file).drop_columns(["image"]), data_file)
        for episodes in (dataset / "meta" / "episodes").rglob("*.parquet"):
            table = pq.read_table(episodes)
            zeros = pa.array([0] * table.num_rows, pa.int64())
            pq.write_table(table.append_column("videos/image/chunk_index", zeros)
                           .append_column("videos/image/file_index", zeros), episodes)
        if files_named:
            return capture_case(world, tmp_path, dataset, str(dataset / "videos/image/chunk-000/file-000.mp4"),
                                "feature 'image', episode 0", "not found")
        return capture_case(world, tmp_path, dataset, str(info_path), "`features.image` is a video",
                            "`video_path` is None")


video_feature(True)
video_feature(False)


@pytest.mark.parametrize("attack", CASES, ids=lambda f: f.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)
