"""The bad-input table, round three: every path a dataset names stays inside it, and declared sizes are bounded
before anything is read. A LeRobot info.json whose path templates leave the dataset, an image cell naming a file
instead of holding its PNG, an HDF5 demo whose groups are soft links (a loop) or external links, or one declaring
a dataset far beyond a LIBERO demo: each refused in one line naming the file and key (`helpers_attack`)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from helpers_attack import Attack, Case, World, assert_refused, dataset_copy, named

from steering_core.data.libero import MAX_STATE_WIDTH


def info_template(name: str, key: str, template: str, expect: str) -> Attack:
    """`manifest` on a copy of the world's dataset whose info.json `key` is `template`."""
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = dataset_copy(world, tmp_path)
        info_path = dataset / "meta" / "info.json"
        info = json.loads(info_path.read_text())
        info[key] = template
        info_path.write_text(json.dumps(info))
        return Case(["manifest", "--lerobot-root", dataset, "--task-a-index", "0", "--task-b-index", "1",
                     "--output", tmp_path / "m.json"], (str(info_path), f"`{key}`", expect))
    return named(name, attack)


TEMPLATES = [
    info_template("data_path_parent", "data_path", "../../../elsewhere/file-{file_index:03d}.parquet",
                  "a path outside the dataset"),
    info_template("data_path_absolute", "data_path", "/etc/chunk-{chunk_index}/file-{file_index}.parquet",
                  "a path outside the dataset"),
    info_template("data_path_inner_parent", "data_path", "data/../../x/file-{file_index}.parquet",
                  "a path outside the dataset"),
    info_template("data_path_attribute", "data_path", "data/{chunk_index.__class__}/{file_index}.parquet",
                  "formats fields"),
    info_template("data_path_unknown_field", "data_path", "data/{home}/{file_index}.parquet", "formats fields"),
    info_template("data_path_not_a_format", "data_path", "data/{chunk_index/file.parquet", "not a format string"),
    info_template("video_path_parent", "video_path", "../videos/{video_key}/file-{file_index}.mp4",
                  "a path outside the dataset"),
]


def image_cell_path(world: World, tmp_path: Path) -> Case:
    """`capture` of a dataset one of whose image cells holds a path (to a file outside it) instead of its PNG."""
    dataset = dataset_copy(world, tmp_path)
    data_file = sorted((dataset / "data").rglob("*.parquet"))[0]
    table = pq.read_table(data_file)
    cells = table.column("image").to_pylist()
    cells[1] = {"bytes": None, "path": "/etc/passwd"}
    table = table.set_column(table.schema.get_field_index("image"), "image",
                             pa.array(cells, type=table.schema.field("image").type))
    pq.write_table(table, data_file)
    return Case(["capture", "--checkpoint-path", world.checkpoint, "--tokenizer-path", world.tokenizer,
                 "--lerobot-root", dataset, "--layers", "1", "--device", "cpu", "--output-dir", tmp_path / "out",
                 "--arch-file", world.data / "arch.json"],
                (str(data_file), "'image'", "'/etc/passwd'", "hold no PNG bytes"))


def demo_file(world: World, tmp_path: Path, edit) -> Case:
    """`filter` of a folder holding one of the world's LIBERO demo files after `edit(h5py file)`."""
    source = sorted((world.inputs / "inputs" / "demos").rglob("*_demo.hdf5"))[0]
    folder = tmp_path / "demos"
    folder.mkdir()
    target = folder / source.name
    shutil.copyfile(source, target)
    with h5py.File(target, "a") as handle:
        where = edit(handle)
    return Case(["filter", "--input-dir", folder, "--output-dir", tmp_path / "filtered", "--glob", "*.hdf5"],
                (str(target), where))


def soft_link_loop(world: World, tmp_path: Path) -> Case:
    def edit(handle):
        del handle["data/demo_0/obs"]
        handle["data/demo_0/obs"] = h5py.SoftLink("/data/demo_0/obs")  # a loop
        return "data/demo_0/obs/agentview_rgb goes through a soft link to '/data/demo_0/obs'"
    return demo_file(world, tmp_path, edit)


def external_link(world: World, tmp_path: Path) -> Case:
    def edit(handle):
        del handle["data/demo_0/actions"]
        handle["data/demo_0/actions"] = h5py.ExternalLink("/etc/other.hdf5", "/actions")
        return "data/demo_0/actions goes through an external link to /etc/other.hdf5:/actions"
    return demo_file(world, tmp_path, edit)


def declared_huge_states(world: World, tmp_path: Path) -> Case:
    """A few hundred KB declaring `states` of (T, 4e6) float64: refused from its shape, nothing read."""
    def edit(handle):
        steps = handle["data/demo_0/actions"].shape[0]
        del handle["data/demo_0/states"]
        handle.create_dataset("data/demo_0/states", shape=(steps, 4_000_000), dtype="f8")  # unwritten: no bytes
        return f"width 4000000 > {MAX_STATE_WIDTH}"
    return demo_file(world, tmp_path, edit)


ATTACKS = [*TEMPLATES, image_cell_path, soft_link_loop, external_link, declared_huge_states]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda attack: attack.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)


def test_lerobots_own_templates_pass(attack_world):
    from steering_core.data.dataset import read_info

    info = read_info(attack_world.dataset)  # the world's dataset, written by lerobot
    assert "{chunk_index" in info["data_path"] and "{file_index" in info["data_path"]
