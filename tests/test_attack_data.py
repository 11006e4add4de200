"""The bad-input table, round four, area "data": the data a step reads comes from the files the user named, and a
bad frame anywhere in a dataset is one line.

- An HDF5 demo dataset whose values lie in another file (external raw storage, a virtual dataset) is refused like
  an external link, before a byte of it is read.
- A LeRobot dataset whose frame at some later row is empty, declares another size in its PNG header (refused
  from the header, before decoding), or whose video feature has no files; an `info.json` field of the wrong type.

Each refused in one line naming the file and the dataset, episode and frame, or key (`helpers_attack`).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers_attack import Attack, Case, World, assert_refused, registrar

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


@pytest.mark.parametrize("attack", CASES, ids=lambda f: f.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)
