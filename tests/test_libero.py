"""LIBERO hdf5 reader: schema validation on open, one error per file, instruction lookup, demo order."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from helpers_libero import edit_file, write_tiny

from steering_core.data import libero

OPEN = "open the top drawer of the cabinet"


@pytest.fixture
def tiny_file(tmp_path):
    """A valid two-demo file (16 px, 8 steps)."""
    return write_tiny(tmp_path, OPEN, num_demos=2).path


def test_generated_file_validates_and_reads_back(tiny_file):
    info = libero.validate_file(tiny_file)
    assert info.instruction == OPEN
    assert info.instruction_source == "problem_info"
    assert info.demo_lengths == {"demo_0": 8, "demo_1": 8}

    demo = libero.read_demo(tiny_file, "demo_1")
    assert demo.key == "demo_1" and demo.num_steps == 8
    assert demo.agentview_rgb.shape == (8, 16, 16, 3) and demo.agentview_rgb.dtype == np.uint8
    assert demo.eye_in_hand_rgb.shape == (8, 16, 16, 3) and demo.eye_in_hand_rgb.dtype == np.uint8
    for name, width in [("ee_pos", 3), ("ee_ori", 3), ("ee_states", 6), ("gripper_states", 2),
                        ("joint_states", 7), ("actions", 7), ("robot_states", 9)]:
        array = getattr(demo, name)
        assert array.shape == (8, width) and array.dtype == np.float64, name
    assert demo.rewards.dtype == np.uint8 and demo.rewards.tolist() == [0] * 7 + [1]
    # the openpi state is ee_pos, ee_ori, gripper in that order, as float32
    expected_state = np.hstack([demo.ee_pos, demo.ee_ori, demo.gripper_states]).astype(np.float32)
    np.testing.assert_array_equal(demo.state8(), expected_state)
    assert demo.state8().dtype == np.float32


def test_demo_keys_are_numeric_order_with_gaps(tmp_path):
    path = write_tiny(tmp_path, OPEN, demo_indices=[10, 2, 9, 0]).path
    assert libero.list_demos(path) == ["demo_0", "demo_2", "demo_9", "demo_10"]
    assert [d.key for d in libero.iter_demos(path)] == ["demo_0", "demo_2", "demo_9", "demo_10"]
    assert [d.key for d in libero.iter_demos(path, ["demo_9", "demo_0"])] == ["demo_9", "demo_0"]


def test_unknown_demo_key_names_available(tiny_file):
    with pytest.raises(ValueError, match=r"no demo\(s\) \['demo_7'\]; available: \[demo_0, demo_1\]"):
        libero.read_demo(tiny_file, "demo_7")


def _replace(handle, name, data):
    del handle[name]
    handle.create_dataset(name, data=data)


CORRUPTIONS = [
    (
        "missing dataset",
        lambda h: h["data/demo_0/obs"].__delitem__("ee_pos"),
        "data/demo_0/obs/ee_pos is missing",
    ),
    (
        "float images",
        lambda h: _replace(h, "data/demo_1/obs/agentview_rgb", np.zeros((8, 16, 16, 3), np.float32)),
        "data/demo_1/obs/agentview_rgb is (8, 16, 16, 3) float32, expected (T, *, *, 3) uint8",
    ),
    (
        "wrong width",
        lambda h: _replace(h, "data/demo_0/obs/ee_pos", np.zeros((8, 2))),
        "data/demo_0/obs/ee_pos is (8, 2) float64, expected (T, 3) float",
    ),
    (
        "integer actions",
        lambda h: _replace(h, "data/demo_0/actions", np.zeros((8, 7), np.int64)),
        "data/demo_0/actions is (8, 7) int64, expected (T, 7) float",
    ),
    (
        "2-D rewards",
        lambda h: _replace(h, "data/demo_0/rewards", np.zeros((8, 1), np.uint8)),
        "data/demo_0/rewards is (8, 1) uint8, expected (T,) uint8",
    ),
    (
        "short dataset",
        lambda h: _replace(h, "data/demo_1/actions", np.zeros((7, 7))),
        "data/demo_1/actions has 7 steps, expected 8 like the demo's other datasets",
    ),
    (
        "NaN state",
        lambda h: h["data/demo_1/states"].__setitem__((3, 0), np.nan),
        "tensor `data/demo_1/states` holds NaN or Inf (nan at (3, 0)); expected finite values",
    ),
    (
        "all-NaN actions",
        lambda h: h["data/demo_0/actions"].__setitem__(Ellipsis, np.nan),
        "tensor `data/demo_0/actions` holds NaN or Inf (nan at (0, 0))",
    ),
    (
        "num_samples disagrees",
        lambda h: h["data/demo_0"].attrs.__setitem__("num_samples", 9),
        "data/demo_0 attribute num_samples is 9, expected 8",
    ),
    (
        "group instead of dataset",
        lambda h: (h["data/demo_0"].__delitem__("states"), h["data/demo_0"].create_group("states")),
        "data/demo_0/states is a group, expected a dataset",
    ),
    (
        "no demos",
        lambda h: (h["data"].__delitem__("demo_0"), h["data"].__delitem__("demo_1")),
        "`data` has no demo_<k> groups",
    ),
    (
        "bad problem_info",
        lambda h: h["data"].attrs.__setitem__("problem_info", "{not json"),
        "data attribute problem_info is not valid JSON",
    ),
]


@pytest.mark.parametrize(("change", "message"), [c[1:] for c in CORRUPTIONS], ids=[c[0] for c in CORRUPTIONS])
def test_each_corruption_has_its_message(tiny_file, change, message):
    edit_file(tiny_file, change)
    with pytest.raises(ValueError) as err:
        libero.validate_file(tiny_file)
    text = str(err.value)
    assert text.startswith(f"{tiny_file}: 1 problem(s) with the LIBERO demo schema:")  # the whole path
    assert message in text
    assert "fix: re-export the file with LIBERO's scripts/create_dataset.py" in text


def test_every_problem_is_reported_at_once(tiny_file):
    def break_three(handle):
        handle["data/demo_0/obs"].__delitem__("joint_states")
        _replace(handle, "data/demo_1/dones", np.zeros(8, np.float32))
        _replace(handle, "data/demo_1/obs/gripper_states", np.zeros((5, 2)))

    edit_file(tiny_file, break_three)
    with pytest.raises(ValueError) as err:
        libero.read_demo(tiny_file, "demo_0")  # readers validate the whole file on open
    text = str(err.value)
    assert "3 problem(s)" in text
    assert "data/demo_0/obs/joint_states is missing" in text
    assert "data/demo_1/dones is (8,) float32, expected (T,) uint8" in text
    assert "data/demo_1/obs/gripper_states has 5 steps, expected 8" in text


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere_demo.hdf5: LIBERO demo file not found"):
        libero.validate_file(tmp_path / "nowhere_demo.hdf5")
    junk = tmp_path / "junk_demo.hdf5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(ValueError, match="junk_demo.hdf5: not a readable HDF5 file"):
        libero.read_instruction(junk)
    empty = tmp_path / "empty_demo.hdf5"
    with h5py.File(empty, "w") as handle:
        handle.create_group("other")
    with pytest.raises(ValueError, match=r"no `data` group \(found top-level keys \['other'\]\)"):
        libero.validate_file(empty)


# ----------------------------------------------------------------------------- instructions


def _set_problem_info(value):
    def change(handle):
        handle["data"].attrs["problem_info"] = json.dumps({"problem_name": "x", "language_instruction": value})

    return change


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("turn on the stove", "turn on the stove"),
        ('"turn on the stove"', "turn on the stove"),              # LIBERO's reader strips quotes
        (["turn", "on", "the", "stove"], "turn on the stove"),      # list-valued instructions are joined
        ("  turn on\nthe  stove ", "turn on the stove"),
    ],
)
def test_instruction_from_problem_info(tiny_file, value, expected):
    edit_file(tiny_file, _set_problem_info(value))
    assert libero.read_instruction_with_source(tiny_file) == (expected, "problem_info")


def test_instruction_falls_back_to_bddl_then_file_name(tmp_path):
    path = write_tiny(tmp_path, "put the bowl on the plate", scene="LIVING_ROOM_SCENE2").path
    edit_file(path, lambda h: h["data"].attrs.__delitem__("problem_info"))
    bddl = "(define (problem P)\n (:language  stack the bowls )\n)"
    edit_file(path, lambda h: h["data"].attrs.__setitem__("bddl_file_content", bddl))
    assert libero.read_instruction_with_source(path) == ("stack the bowls", "bddl")

    edit_file(path, lambda h: h["data"].attrs.__delitem__("bddl_file_content"))
    assert libero.read_instruction_with_source(path) == ("put the bowl on the plate", "filename")
    assert libero.validate_file(path).instruction_source == "filename"


def test_empty_problem_info_instruction_uses_bddl(tiny_file):
    edit_file(tiny_file, _set_problem_info(""))
    assert libero.read_instruction_with_source(tiny_file) == (OPEN, "bddl")


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet_demo.hdf5", "close the top drawer of the cabinet"),
        ("KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet_demo.hdf5", "open the top drawer of the cabinet"),
        ("LIVING_ROOM_SCENE2_pick_up_the_butter_and_put_it_in_the_basket_demo.hdf5",
         "pick up the butter and put it in the basket"),
        ("STUDY_SCENE4_pick_up_the_book_on_the_right_and_place_it_under_the_cabinet_shelf_demo.hdf5",
         "pick up the book on the right and place it under the cabinet shelf"),
        ("pick_up_the_black_bowl_on_the_cookie_box_and_place_it_on_the_plate_demo.hdf5",
         "pick up the black bowl on the cookie box and place it on the plate"),
        ("/some/dir/KITCHEN_SCENE3_turn_on_the_stove.hdf5", "turn on the stove"),
    ],
)
def test_instruction_from_filename(name, expected):
    assert libero.instruction_from_filename(name) == expected


def test_task_file_name_round_trips():
    name = libero.task_file_name("turn  off the stove", "KITCHEN_SCENE8")
    assert name == "KITCHEN_SCENE8_turn_off_the_stove_demo.hdf5"
    assert libero.instruction_from_filename(name) == "turn off the stove"


def test_demo_sort_key():
    assert sorted(["demo_10", "demo_9", "demo_1"], key=libero.demo_sort_key) == ["demo_1", "demo_9", "demo_10"]
    with pytest.raises(ValueError, match="'mask' does not look like demo_<k>"):
        libero.demo_sort_key("mask")
