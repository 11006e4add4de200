"""The bad-input table, round four: metadata that disagrees with the data is refused, not silently used.

A LeRobot dataset whose info.json, tasks table, episode rows or statistics contradict each other or its frames
(`manifest` and `capture` on a copy of the world's dataset), a LIBERO demo file with stray groups or values that
overflow float32 (`filter`), a manifest listing a demo twice (`concept-map`), a concept map whose concepts share
rows (`slice`): each refused in one line naming the file and field (`helpers_attack`).
"""

from __future__ import annotations

import io
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
from helpers_attack import Attack, Case, World, assert_refused, dataset_copy, good, named
from PIL import Image

from steering_core.data.libero import MAX_ABS_VALUE


def command(name: str, world: World, tmp_path: Path, dataset: Path) -> list:
    """The world's working `name` command line, reading `dataset` instead of the world's."""
    argv = good(world, tmp_path)[name]
    at = argv.index("--lerobot-root")
    return [name, *argv[:at + 1], dataset, *argv[at + 2:]]


def edit_table(path: Path, edit: Callable[[pa.Table], pa.Table]) -> None:
    pq.write_table(edit(pq.read_table(path)), path)


def set_column(table: pa.Table, name: str, values: list) -> pa.Table:
    return table.set_column(table.schema.get_field_index(name), name, pa.array(values, table.schema.field(name).type))


def data_file(dataset: Path) -> Path:
    return sorted((dataset / "data").rglob("*.parquet"))[0]


def episodes_file(dataset: Path) -> Path:
    return sorted((dataset / "meta" / "episodes").rglob("*.parquet"))[0]


def dataset_attack(name: str, step: str, edit: Callable[[Path], tuple[Path, str]], *shown: str) -> Attack:
    """`step` on a copy of the world's dataset after `edit(dataset)`, which returns the file and field to name."""
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = dataset_copy(world, tmp_path)
        path, field = edit(dataset)
        return Case(command(step, world, tmp_path, dataset), (str(path), field, *shown))
    return named(name, attack)


def info_value(key: str, value: object) -> Callable[[Path], tuple[Path, str]]:
    def edit(dataset: Path) -> tuple[Path, str]:
        path = dataset / "meta" / "info.json"
        info = json.loads(path.read_text())
        info[key] = value
        path.write_text(json.dumps(info))
        return path, f"`{key}`"
    return edit


def feature_shape(key: str, shape: list[int]) -> Callable[[Path], tuple[Path, str]]:
    def edit(dataset: Path) -> tuple[Path, str]:
        path = dataset / "meta" / "info.json"
        info = json.loads(path.read_text())
        info["features"][key]["shape"] = shape
        path.write_text(json.dumps(info))
        return data_file(dataset) if key == "actions" else path, f"`features.{key}.shape`"
    return edit


def episode_task(dataset: Path) -> tuple[Path, str]:
    """Episode 0's row names the task of another episode: its frames say otherwise."""
    path = episodes_file(dataset)
    def edit(table: pa.Table) -> pa.Table:
        tasks = table.column("tasks").to_pylist()
        other = next(t for t in tasks if t != tasks[0])
        return set_column(table, "tasks", [other, *tasks[1:]])
    edit_table(path, edit)
    return dataset, "`task_index`"


def episode_dropped(dataset: Path) -> tuple[Path, str]:
    """The last episode's row removed and info.json's totals made to agree: its frames are still in the data."""
    path = episodes_file(dataset)
    table = pq.read_table(path)
    last = table.slice(table.num_rows - 1).to_pylist()[0]
    pq.write_table(table.slice(0, table.num_rows - 1), path)
    info_path = dataset / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["total_episodes"] -= 1
    info["total_frames"] -= last["length"]
    info_path.write_text(json.dumps(info))
    return dataset, f"episode(s) [{last['episode_index']}]"


def index_column(name: str, change: Callable[[list], list]) -> Callable[[Path], tuple[Path, str]]:
    def edit(dataset: Path) -> tuple[Path, str]:
        edit_table(data_file(dataset), lambda table: set_column(table, name, change(table.column(name).to_pylist())))
        return dataset, f"`{name}`"
    return edit


def duplicate_first(values: list) -> list:
    return [values[0], values[0], *values[2:]]


def swap_first(values: list) -> list:
    return [values[1], values[0], *values[2:]]


def task_row_dropped(dataset: Path) -> tuple[Path, str]:
    """tasks.parquet loses the last task the episodes (and their frames) use."""
    path = dataset / "meta" / "tasks.parquet"
    frame = pq.read_table(path).to_pandas()
    frame.iloc[:-1].to_parquet(path)
    return path, repr(str(frame.index[-1]))


def task_renumbered(dataset: Path) -> tuple[Path, str]:
    """tasks.parquet gives its last task another index: the texts agree, the frames' `task_index` names nothing."""
    path = dataset / "meta" / "tasks.parquet"
    frame = pq.read_table(path).to_pandas()
    last = int(frame["task_index"].iloc[-1])
    frame.loc[frame.index[-1], "task_index"] = 99
    frame.to_parquet(path)
    return path, f"`task_index` {last}"


def stats_nan(dataset: Path) -> tuple[Path, str]:
    path = dataset / "meta" / "stats.json"
    stats = json.loads(path.read_text())
    stats["actions"]["mean"][0] = float("nan")
    path.write_text(json.dumps(stats))  # Python writes NaN, which Python's json reads back
    return path, "NaN or Inf"


def episode_stats_inf(dataset: Path) -> tuple[Path, str]:
    path = episodes_file(dataset)
    edit_table(path, lambda table: set_column(
        table, "stats/actions/max", [[float("inf"), *row[1:]] for row in table.column("stats/actions/max").to_pylist()]))
    return path, "'stats/actions/max'"


def png_header(width: int, height: int, colour: int) -> bytes:
    """The signature and IHDR chunk of an 8-bit PNG (what the header check reads), with no pixels after it:
    a 12000x12000 image declared in 33 bytes."""
    ihdr = b"IHDR" + struct.pack(">IIBBBBB", width, height, 8, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + ihdr + struct.pack(">I", zlib.crc32(ihdr))


def png(width: int, height: int, mode: str) -> bytes:
    """A real PNG of `mode` ("RGB", "L") and this size, as Pillow writes it."""
    out = io.BytesIO()
    Image.new(mode, (width, height)).save(out, format="PNG")
    return out.getvalue()


def first_image(data: bytes) -> Callable[[Path], tuple[Path, str]]:
    """The first frame's base camera replaced by `data`."""
    def edit(dataset: Path) -> tuple[Path, str]:
        path = data_file(dataset)
        def change(table: pa.Table) -> pa.Table:
            cells = table.column("image").to_pylist()
            return set_column(table, "image", [{"bytes": data, "path": None}, *cells[1:]])
        edit_table(path, change)
        return path, "'image'"
    return edit


DATASET_ATTACKS = [
    dataset_attack("episode_task_disagrees", "manifest", episode_task, "episode 0"),
    dataset_attack("episode_missing_from_meta", "manifest", episode_dropped, "meta/episodes"),
    dataset_attack("index_duplicated", "manifest", index_column("index", duplicate_first)),
    dataset_attack("frame_index_swapped", "manifest", index_column("frame_index", swap_first), "`frame_index` 1, expected 0"),
    dataset_attack("episode_index_swapped", "capture", index_column("episode_index", lambda v: [v[-1], *v[1:]])),
    dataset_attack("fps_zero", "manifest", info_value("fps", 0), "positive"),
    dataset_attack("fps_negative", "capture", info_value("fps", -10), "positive"),
    dataset_attack("fps_text", "manifest", info_value("fps", "10"), "positive"),
    dataset_attack("total_episodes", "manifest", info_value("total_episodes", 9), "holds 8"),
    dataset_attack("total_frames", "capture", info_value("total_frames", 1), "meta/episodes"),
    dataset_attack("stats_nan", "manifest", stats_nan),
    dataset_attack("episode_stats_inf", "manifest", episode_stats_inf, "NaN or Inf"),
    dataset_attack("task_missing_from_tasks", "capture", task_row_dropped, "`tasks`"),
    dataset_attack("task_index_renumbered", "capture", task_renumbered, "does not list"),
    dataset_attack("actions_shape", "capture", feature_shape("actions", [6]), "'actions'", "holds 7"),
    dataset_attack("state_shape", "manifest", feature_shape("state", [8, 2]), "'state'"),
    dataset_attack("image_shape", "capture", feature_shape("image", [32, 32, 3]), "64x64", "[32, 32, 3]"),
    dataset_attack("png_corrupt", "capture", first_image(b"\x89PNG not an image"), "not a PNG"),
    dataset_attack("png_8x8", "capture", first_image(png(8, 8, "RGB")), "8x8"),
    dataset_attack("png_grayscale", "capture", first_image(png(64, 64, "L")), "colour type 0"),
    dataset_attack("png_12000", "capture", first_image(png_header(12000, 12000, 2)), "12000x12000"),
]


def demo_file(name: str, edit: Callable[[h5py.File], str]) -> Attack:
    """`filter` of a folder holding one of the world's LIBERO demo files after `edit(h5py file)`."""
    def attack(world: World, tmp_path: Path) -> Case:
        source = sorted((world.inputs / "inputs" / "demos").rglob("*_demo.hdf5"))[0]
        folder = tmp_path / "demos"
        folder.mkdir()
        target = folder / source.name
        shutil.copyfile(source, target)
        with h5py.File(target, "a") as handle:
            where = edit(handle)
        return Case(["filter", "--input-dir", folder, "--output-dir", tmp_path / "filtered", "--glob", "*.hdf5"],
                    (str(target), where))
    return named(name, attack)


def demo_renamed(key: str) -> Callable[[h5py.File], str]:
    def edit(handle: h5py.File) -> str:
        handle.move("data/demo_1", f"data/{key}")
        return f"`data` holds [{key}]"
    return edit


def actions_scaled(handle: h5py.File) -> str:
    """The demo's actions times 1e300: finite in float64 (as LIBERO stores them), Inf once cast to float32."""
    values = handle["data/demo_0/actions"][()].astype(np.float64) * 1e300
    del handle["data/demo_0/actions"]
    handle["data/demo_0/actions"] = values
    return f"data/demo_0/actions holds {np.abs(values).max():g}, expected magnitudes up to {MAX_ABS_VALUE:g}"


HDF5_ATTACKS = [
    demo_file("demo_x", demo_renamed("demo_x")),
    demo_file("demo_negative", demo_renamed("demo_-5")),
    demo_file("demo_leading_zero", demo_renamed("demo_01")),
    demo_file("actions_overflow_float32", actions_scaled),
]


def manifest_twice(world: World, tmp_path: Path) -> Case:
    """`concept-map` of a manifest listing every segment twice (it would double every concept's samples)."""
    manifest = json.loads((world.data / "manifests" / "open_vs_close.json").read_text())
    manifest["segments"] = manifest["segments"] * 2
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(manifest))
    argv = good(world, tmp_path)["concept-map"]
    argv[argv.index("--manifest-path") + 1] = path
    return Case(["concept-map", *argv], (str(path), f"segments[{len(manifest['segments']) // 2}]",
                                         "the same segment as segments[0]"))


def concepts_share_rows(world: World, tmp_path: Path) -> Case:
    """`slice` with a concept map whose second concept also holds the first concept's first row."""
    concept_map = json.loads((world.data / "manifests" / "open_vs_close_concept_map.json").read_text())
    first, second = list(concept_map["concepts"])
    concept_map["concepts"][second].append(concept_map["concepts"][first][0])
    concept_map["concept_count"][second] += 1
    path = tmp_path / "concept_map.json"
    path.write_text(json.dumps(concept_map))
    argv = good(world, tmp_path)["slice"]
    argv[argv.index("--concept-map-path") + 1] = path
    return Case(["slice", *argv], (str(path), f"concepts[{second!r}]", f"concepts[{first!r}]", "share dataset index"))


ATTACKS = [*DATASET_ATTACKS, *HDF5_ATTACKS, manifest_twice, concepts_share_rows]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda attack: attack.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)


def test_world_dataset_passes(attack_world):
    from steering_core.data.dataset_checks import check_dataset

    meta = check_dataset(attack_world.dataset)  # written by lerobot: every check holds
    assert meta.info["total_frames"] == sum(e.length for e in meta.episodes)
