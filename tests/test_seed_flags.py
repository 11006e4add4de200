"""The seed's commands under `latent-steering`: its flag spellings, its missing flags, its reproduction switches."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers_libero import tiny_task
from PIL import Image
from typer.testing import CliRunner

from latent_steering_cli import app
from latent_steering_cli.app import seed_spellings
from latent_steering_cli.lazy import load_command
from steering_core.data.convert import read_sources
from steering_core.data.dataset import read_meta
from steering_core.data.libero import read_demo
from steering_core.data.v2_frames import V2Frames
from steering_core.synthetic.libero import SyntheticSettings, write_libero_file

OPEN = "open the top drawer of the cabinet"
CLOSE = "close the top drawer of the cabinet"
DEMOS = SyntheticSettings(image_size=16, num_steps=10, length_jitter=4, state_dim=12)


def command(name: str):
    return load_command(name)  # commands are imported lazily: in a fresh process none is loaded yet


def invoke(*args) -> str:
    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


def test_seed_spellings_are_rewritten():
    assert seed_spellings(command("capture"), ["--layers", "12", "14", "--repo_id", "x", "--capture-instructions"]) == [
        "--layers", "12 14", "--repo-id", "x", "--capture-instructions"]
    assert seed_spellings(command("manifest"), ["--task-a-episodes", "3", "4", "--task_b_episodes=5", "--pad", "2"]) == [
        "--task-a-episodes", "3", "--task-a-episodes", "4", "--task-b-episodes=5", "--pad", "2"]
    assert seed_spellings(command("convert"), ["--input_dir", "a", "b", "--image_size", "256", "--unknown_flag"]) == [
        "--input-dir", "a", "--input-dir", "b", "--image-size", "256", "--unknown_flag"]  # unknown names untouched
    assert seed_spellings(command("filter"), ["--task", "a b", "--copy", "--", "--x_y"]) == [
        "--task", "a b", "--copy", "--", "--x_y"]


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    """Two task files of 11 demos each: enough for demo_10 to sort before demo_2."""
    folder = tmp_path_factory.mktemp("lab") / "libero_90"  # the lab folder is the --search-root
    folder.mkdir()
    write_libero_file(folder, tiny_task(OPEN, axis=2, direction=1), num_demos=11, settings=DEMOS)
    write_libero_file(folder, tiny_task(CLOSE, axis=2, direction=-1), num_demos=11, settings=DEMOS)
    return folder


@pytest.fixture(scope="module")
def seed_dataset(demos, tmp_path_factory):
    """The seed's conversion: no flip, bicubic 16 -> 32, demos in sorted(keys) order, written with seed spellings."""
    root = tmp_path_factory.mktemp("seed") / "libero_open_close_lerobot"
    invoke("convert", "--input_dir", demos, "--repo_id", "libero_open_close_lerobot", "--output_dir", root,
           "--image_size", 32, "--orientation", "as_stored", "--resize-filter", "bicubic",
           "--demo-order", "lexicographic", "--fps", 20, "--codebase-version", "v2.1")
    return root


def test_seed_conversion(demos, seed_dataset):
    info = json.loads((seed_dataset / "meta/info.json").read_text())
    assert (info["fps"], info["codebase_version"], info["total_episodes"]) == (20, "v2.1", 22)
    sources = read_sources(seed_dataset).episodes
    assert [s.demo for s in sources[:4]] == ["demo_0", "demo_1", "demo_10", "demo_2"]
    close_file = sources[0].file  # files by name: "KITCHEN_SCENE1_close..." before "..._open..."
    assert close_file.startswith("KITCHEN_SCENE1_close")
    raw = read_demo(demos / close_file, "demo_10").agentview_rgb[3]
    expected = np.asarray(Image.fromarray(raw).resize((32, 32), Image.BICUBIC))  # no flip, PIL bicubic
    item = V2Frames(read_meta(seed_dataset), [2])[3]
    assert item["frame_index"] == 3
    np.testing.assert_array_equal((item["image"].permute(1, 2, 0) * 255).round().byte().numpy(), expected)


def test_hdf5_manifest_maps_like_the_dataset_manifest(demos, seed_dataset, tmp_path):
    names = {s.task: s.file for s in read_sources(seed_dataset).episodes}
    invoke("manifest", "--backend", "hdf5", "--task-a-file", names[OPEN], "--task-b-file", names[CLOSE],
           "--search-root", demos.parent, "--demo-order", "lexicographic", "--max-demos-per-task", 4,
           "--output", tmp_path / "hdf5.json")
    invoke("manifest", "--lerobot-root", seed_dataset, "--task-a-text", OPEN, "--task-b-index", 0,
           "--max-demos-per-task", 4, "--output", tmp_path / "lerobot.json")
    from_hdf5, from_dataset = (json.loads((tmp_path / n).read_text()) for n in ("hdf5.json", "lerobot.json"))
    assert from_hdf5["axis"] == from_dataset["axis"]
    assert [s["file"] for s in from_hdf5["segments"]][:1] == [f"{demos.name}/{names[OPEN]}"]
    assert [s["demo"] for s in from_hdf5["segments"]][:4] == ["demo_0", "demo_1", "demo_10", "demo_2"]
    window = ("task", "start_step", "end_step", "axis_delta", "axis_values")
    assert [[s[k] for k in window] for s in from_hdf5["segments"]] == [
        [s[k] for k in window] for s in from_dataset["segments"]]
    for name in ("hdf5", "lerobot"):
        invoke("concept-map", "--manifest_path", tmp_path / f"{name}.json", "--output_path", tmp_path / f"{name}_map.json",
               "--lerobot_root", seed_dataset, "--repo_id", "libero_open_close_lerobot")
    map_hdf5, map_dataset = (json.loads((tmp_path / f"{n}_map.json").read_text()) for n in ("hdf5", "lerobot"))
    assert map_hdf5["concepts"] == map_dataset["concepts"] and map_hdf5["concept_count"] == {OPEN: 4, CLOSE: 4}


def test_labels_name_the_concepts(seed_dataset, tmp_path):
    invoke("manifest", "--lerobot-root", seed_dataset, "--task-a-index", 1, "--task-b-index", 0,
           "--task-a-label", "open", "--task-b-label", "close", "--task-a-episodes", "11", "12",
           "--task-b-episodes", 0, 1, "--output", tmp_path / "labelled.json")
    manifest = json.loads((tmp_path / "labelled.json").read_text())
    assert [s["task"] for s in manifest["segments"]] == ["open", "open", "close", "close"]
    assert manifest["dataset"]["task_texts"] == {"open": OPEN, "close": CLOSE}
    invoke("concept-map", "--manifest-path", tmp_path / "labelled.json", "--output-path", tmp_path / "map.json",
           "--lerobot-root", seed_dataset)
    assert json.loads((tmp_path / "map.json").read_text())["concept_count"] == {"close": 2, "open": 2}


def failure(*args) -> tuple[int, str]:
    """Return the exit code and the output with rich's box drawing and line wrapping removed."""
    result = CliRunner().invoke(app, [str(a) for a in args])
    return result.exit_code, " ".join(result.output.replace("│", " ").split())


def test_manifest_flag_errors(seed_dataset, tmp_path):
    code, text = failure("manifest", "--lerobot-root", seed_dataset, "--task-a-text", OPEN, "--task-a-index", 1,
                         "--task-b-index", 0, "--output", tmp_path / "x.json")
    assert code == 2 and "give exactly one of --task-a-text and --task-a-index" in text
    code, text = failure("manifest", "--backend", "hdf5", "--task-a-file", "a.hdf5", "--output", tmp_path / "x.json")
    assert code == 2 and "the hdf5 backend needs --task-a-file and --task-b-file" in text
    code, text = failure("manifest", "--lerobot-root", seed_dataset, "--task-a-index", 7, "--task-b-index", 0,
                         "--output", tmp_path / "x.json")
    assert code == 1 and "task A index 7 is not in the dataset; task indices are [0, 1]" in text
