"""Filtering demo files: by task text (exact or ignoring case), by glob, symlink vs copy, selection.json."""

from __future__ import annotations

import os

import pytest
from helpers_libero import edit_file, sha256_bytes, write_tiny
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.data.filtering import FilterSettings, filter_demos, read_selection

OPEN = "open the top drawer of the cabinet"
CLOSE = "close the top drawer of the cabinet"
STOVE_ON = "turn on the stove"
STOVE_OFF = "turn off the stove"


@pytest.fixture
def sources(tmp_path):
    """Two source folders: libero_90-like (drawer files in two scenes, stove) and a second suite."""
    first, second = tmp_path / "libero_90", tmp_path / "libero_10"
    write_tiny(first, OPEN, "KITCHEN_SCENE1", num_demos=2)
    write_tiny(first, OPEN, "KITCHEN_SCENE2")
    write_tiny(first, CLOSE, "KITCHEN_SCENE10", num_demos=3)
    write_tiny(first, STOVE_ON, "KITCHEN_SCENE3")
    write_tiny(second, STOVE_OFF, "KITCHEN_SCENE8")
    write_tiny(second, "pick up the milk and put it in the basket", "LIVING_ROOM_SCENE2")
    return first, second


def _names(selection):
    return [f.name for f in selection.files]


def test_select_by_task_text_writes_symlinks_and_record(sources, tmp_path):
    out = tmp_path / "filtered" / "open_close"
    selection = filter_demos(list(sources), out, FilterSettings(tasks=(OPEN, CLOSE)))
    expected = [
        "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet_demo.hdf5",
        "KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet_demo.hdf5",
        "KITCHEN_SCENE2_open_the_top_drawer_of_the_cabinet_demo.hdf5",
    ]
    assert _names(selection) == expected
    assert sorted(p.name for p in out.iterdir()) == sorted([*expected, "selection.json"])
    for entry in selection.files:
        link = out / entry.name
        source = sources[0] / entry.name
        assert link.is_symlink() and os.readlink(link) == str(source.resolve())
        assert entry.source == str(source.resolve())
        assert entry.sha256 == sha256_bytes(source)
        assert entry.instruction_source == "problem_info"
    assert {e.name: e.num_demos for e in selection.files}[expected[0]] == 3
    assert {e.name: e.instruction for e in selection.files}[expected[1]] == OPEN
    # selection.json on disk is the returned record
    assert read_selection(out) == selection
    assert read_selection(out).format_version == 1


def test_task_text_ignores_case_unless_exact(sources, tmp_path):
    shouty = "  OPEN the Top  drawer of the cabinet "
    selection = filter_demos(list(sources), tmp_path / "a", FilterSettings(tasks=(shouty,)))
    assert [f.instruction for f in selection.files] == [OPEN, OPEN]
    with pytest.raises(ValueError, match="task '  OPEN the Top  drawer of the cabinet ' matches no file's instruction"):
        filter_demos(list(sources), tmp_path / "b", FilterSettings(tasks=(shouty,), match="exact"))
    exact = filter_demos(list(sources), tmp_path / "c", FilterSettings(tasks=(f" {OPEN} ",), match="exact"))
    assert len(exact.files) == 2


def test_select_by_glob_and_union_with_tasks(sources, tmp_path):
    selection = filter_demos(list(sources), tmp_path / "stove", FilterSettings(globs=("*stove*",)))
    assert _names(selection) == [
        "KITCHEN_SCENE3_turn_on_the_stove_demo.hdf5",
        "KITCHEN_SCENE8_turn_off_the_stove_demo.hdf5",
    ]
    union = filter_demos(list(sources), tmp_path / "union", FilterSettings(tasks=(CLOSE,), globs=("LIVING_ROOM_*",)))
    assert _names(union) == [
        "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet_demo.hdf5",
        "LIVING_ROOM_SCENE2_pick_up_the_milk_and_put_it_in_the_basket_demo.hdf5",
    ]


def test_copy_mode_copies_bytes(sources, tmp_path):
    out = tmp_path / "copied"
    selection = filter_demos(list(sources), out, FilterSettings(tasks=(STOVE_OFF,), mode="copy"))
    (entry,) = selection.files
    copied = out / entry.name
    assert not copied.is_symlink() and copied.is_file()
    assert copied.read_bytes() == (sources[1] / entry.name).read_bytes()
    assert entry.sha256 == sha256_bytes(copied)


def test_unknown_task_lists_closest_instructions(sources, tmp_path):
    with pytest.raises(ValueError) as err:
        tasks = ("open the drawer", STOVE_ON, "turn the stove on")
        filter_demos(list(sources), tmp_path / "x", FilterSettings(tasks=tasks, globs=("*.h5",)))
    text = str(err.value)
    assert text.startswith("cannot select demo files:")
    assert (
        "task 'open the drawer' matches no file's instruction; closest available: 'open the top drawer of the cabinet'"
        in text
    )
    assert "task 'turn the stove on' matches no file's instruction; closest available: 'turn on the stove'" in text
    assert "glob '*.h5' matches no file name among 6 candidate(s)" in text
    assert "task 'turn on the stove'" not in text
    assert not (tmp_path / "x").exists()


def test_filename_fallback_selects_files_without_instruction_attributes(sources, tmp_path):
    path = sources[1] / "LIVING_ROOM_SCENE2_pick_up_the_milk_and_put_it_in_the_basket_demo.hdf5"
    def strip_instruction(handle):
        del handle["data"].attrs["problem_info"]
        del handle["data"].attrs["bddl_file_content"]

    edit_file(path, strip_instruction)
    settings = FilterSettings(tasks=("pick up the milk and put it in the basket",))
    selection = filter_demos(list(sources), tmp_path / "milk", settings)
    assert [(f.name, f.instruction_source) for f in selection.files] == [(path.name, "filename")]


def test_rerun_is_idempotent_and_changes_replace_the_folder(sources, tmp_path):
    out = tmp_path / "filtered"
    settings = FilterSettings(tasks=(OPEN,))
    first = filter_demos(list(sources), out, settings)
    before = (out / "selection.json").stat()
    again = filter_demos(list(sources), out, settings)
    after = (out / "selection.json").stat()
    assert again == first
    assert (before.st_ino, before.st_mtime_ns) == (after.st_ino, after.st_mtime_ns)  # untouched

    changed = filter_demos(list(sources), out, FilterSettings(tasks=(CLOSE,)))
    assert sorted(p.name for p in out.iterdir()) == sorted([*_names(changed), "selection.json"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["filtered", "libero_10", "libero_90"]  # no temp leftovers

    # a source whose bytes changed is re-recorded with its new hash
    edit_file(sources[0] / _names(changed)[0], lambda h: h["data"].attrs.__setitem__("total", 99))
    rerecorded = filter_demos(list(sources), out, FilterSettings(tasks=(CLOSE,)))
    assert rerecorded.files[0].sha256 == sha256_bytes(sources[0] / _names(changed)[0]) != changed.files[0].sha256


def test_bad_inputs(sources, tmp_path):
    with pytest.raises(ValueError, match="nothing to select"):
        filter_demos(list(sources), tmp_path / "o", FilterSettings())
    with pytest.raises(FileNotFoundError, match="missing: input folder not found"):
        filter_demos([tmp_path / "missing"], tmp_path / "o", FilterSettings(tasks=(OPEN,)))
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="has no selection.json, so it is not a filter output"):
        filter_demos(list(sources), foreign, FilterSettings(tasks=(OPEN,)))
    assert (foreign / "notes.txt").read_text() == "keep me"
    clash = tmp_path / "clash"
    write_tiny(clash, STOVE_ON, "KITCHEN_SCENE3")
    with pytest.raises(ValueError, match="KITCHEN_SCENE3_turn_on_the_stove_demo.hdf5 in both"):
        filter_demos([sources[0], clash], tmp_path / "o", FilterSettings(tasks=(STOVE_ON,)))
    with pytest.raises(ValueError, match="the input folder is also the output folder"):
        filter_demos([sources[0]], sources[0], FilterSettings(tasks=(OPEN,)))


def test_selected_corrupt_file_is_rejected(sources, tmp_path):
    path = sources[0] / "KITCHEN_SCENE3_turn_on_the_stove_demo.hdf5"
    edit_file(path, lambda h: h["data/demo_0"].__delitem__("actions"))
    with pytest.raises(ValueError, match="data/demo_0/actions is missing"):
        filter_demos(list(sources), tmp_path / "o", FilterSettings(tasks=(STOVE_ON,)))
    # unselected, the same file does not get in the way
    assert len(filter_demos(list(sources), tmp_path / "o", FilterSettings(tasks=(OPEN,))).files) == 2


def test_cli_filter(sources, tmp_path):
    out = tmp_path / "cli"
    runner = CliRunner()
    args = ["filter", "--input-dir", str(sources[0]), "--input-dir", str(sources[1]), "--output-dir", str(out)]
    result = runner.invoke(app, [*args, "--task", OPEN.upper(), "--glob", "*stove*", "--copy"])
    assert result.exit_code == 0, result.output
    selection = read_selection(out)
    assert len(selection.files) == 4 and selection.settings.mode == "copy"
    assert not any(p.is_symlink() for p in out.iterdir())

    result = runner.invoke(app, [*args, "--task", OPEN.upper(), "--exact"])
    assert result.exit_code == 1
    assert "closest available: 'open the top drawer of the cabinet'" in result.output


def test_byte_identical_copy_is_selected_with_a_warning_naming_both_files(sources, tmp_path, caplog):
    original = sources[0] / "KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet_demo.hdf5"
    copy = sources[1] / "copy_of_scene1_open.hdf5"
    copy.write_bytes(original.read_bytes())
    with caplog.at_level("WARNING", logger="steering_core.data.filtering"):
        selection = filter_demos(list(sources), tmp_path / "out", FilterSettings(tasks=(OPEN,)))
    assert copy.name in _names(selection)  # still selected: the user may mean it
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and str(copy.resolve()) in warnings[0] and str(original.resolve()) in warnings[0]
    caplog.clear()
    with caplog.at_level("WARNING", logger="steering_core.data.filtering"):
        filter_demos([sources[0]], tmp_path / "out2", FilterSettings(tasks=(OPEN,)))  # two different files
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
