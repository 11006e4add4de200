"""The bad-input table, errors of the machine: a disk that fills up mid-write, a path part over the file system's 255
bytes, a config nested past Python's recursion limit, memory exhausted, counts whose product is more work than any
study needs, a demo image too small to resize and a NaN state inside a manifest window. Each is refused in one line
naming the file (or the settings to lower) with no traceback, and nothing half-written is left
(`helpers_attack.assert_refused`)."""

from __future__ import annotations

import errno
import functools
import itertools
import pathlib
import shutil
from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import safetensors.torch
import torch
from helpers_attack import CLOSE, OPEN, Case, World, assert_refused, good
from safetensors.torch import load_file, save_file
from test_attack_inputs import config_case, config_text, named
from test_attack_paths import demo_file
from tqdm.auto import tqdm

from steering_core import tensor_files
from steering_core.sae.formats import WEIGHTS_FILE
from steering_core.workload import MAX_EVALUATION_SAMPLES, MAX_ROLLOUT_STEPS

LONG = "n" * 300  # one path part over the 255 bytes of a file-system name
DISK_FULL = "no space left on the device"

# ----------------------------------------------------------------------------- a disk that fills up mid-write

# the writers the steps go through: Python's file writes, and safetensors' own (Rust) save, imported by name
SAVE_FILE_USERS = ("steering_core.capture.shards", "steering_core.vectors.concept_stats", "steering_core.evaluate.report")


def fill_disk_under(monkeypatch: pytest.MonkeyPatch, root: Path, after: int = 0) -> None:
    """Make every write of a file under `root`, after the first `after` of them, write half its bytes, then fail as a
    full disk does (ENOSPC)."""
    writes = itertools.count()

    def full(path: Path, data: bytes) -> None:
        with open(path, "wb") as handle:
            handle.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    def guarded(original, path_at: int = 0, fill: bytes | None = None):
        def write(*args, **kwargs):
            path = Path(args[path_at])
            if not path.absolute().is_relative_to(root) or next(writes) < after:
                return original(*args, **kwargs)
            data = args[1] if fill is None else fill
            return full(path, data.encode() if isinstance(data, str) else bytes(data))
        return write

    monkeypatch.setattr(pathlib.Path, "write_bytes", guarded(pathlib.Path.write_bytes))
    monkeypatch.setattr(pathlib.Path, "write_text", guarded(pathlib.Path.write_text))
    for module in SAVE_FILE_USERS:
        monkeypatch.setattr(f"{module}.save_file", guarded(safetensors.torch.save_file, 1, b"\0" * 64))
    monkeypatch.setattr(tensor_files, "save_torch_without_crcs",
                        guarded(tensor_files.save_torch_without_crcs, 1, b"\0" * 64))


DISK_FULL_COMMANDS = ["filter", "manifest", "split", "concept-map", "capture", "slice", "steer", "train-sae", "evaluate"]


@pytest.mark.parametrize("command", DISK_FULL_COMMANDS)
def test_disk_full_is_one_line(attack_world, tmp_path, monkeypatch, command):
    assert_disk_full_refused(attack_world, tmp_path, monkeypatch, command)


# the commands that write many files for one output, and how many of them are written before the disk fills up
LATER_FILES = [("train-sae", after) for after in (1, 2, 3)] + [("steer", after) for after in (1, 9, 14, 30)]


@pytest.mark.parametrize(("command", "after"), LATER_FILES, ids=[f"{c}-{a}" for c, a in LATER_FILES])
def test_disk_full_at_a_later_file_keeps_nothing(attack_world, tmp_path, monkeypatch, command, after):
    """A disk that fills up at the Nth file of an output: the one line says nothing was kept, and nothing was."""
    assert_disk_full_refused(attack_world, tmp_path, monkeypatch, command, after)


def assert_disk_full_refused(world: World, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, command: str,
                             after: int = 0) -> None:
    """Run `command` on the world with the disk full after `after` files; check the one line and that nothing is left."""
    monkeypatch.chdir(tmp_path)
    if command == "train-sae":  # SAELens's progress bars go to stderr: not part of the error
        for module in ("sae_lens.training.sae_trainer", "sae_lens.training.activation_scaler"):
            monkeypatch.setattr(f"{module}.tqdm", functools.partial(tqdm, disable=True))
    fill_disk_under(monkeypatch, tmp_path, after)

    def attack(world: World, tmp: Path) -> Case:
        argv = [command, *good(world, tmp)[command]]
        if command == "evaluate":  # the smallest grid: the refusal comes when its outputs are written
            argv += ["--alphas", "0,1", "--random-directions", "8"]
        return Case(argv, (str(tmp), DISK_FULL, "nothing was kept"))

    assert_refused(world, tmp_path, attack)


def test_steer_through_an_sae_that_overflows_keeps_nothing(attack_world, tmp_path):
    """A `b_dec` of 1e38 overflows float32 in the SAE pass: refused naming the file, no concept statistics left."""
    def attack(world: World, tmp: Path) -> Case:
        folder = shutil.copytree(world.sae(1), tmp / "sae")
        tensors = load_file(folder / WEIGHTS_FILE)
        tensors["b_dec"] = torch.full_like(tensors["b_dec"], 1e38)
        save_file(tensors, folder / WEIGHTS_FILE)
        argv = [str(word) for word in good(world, tmp)["steer"]]
        argv[argv.index("--sae") + 1] = str(folder)
        return Case(["steer", *argv], (str(tmp / "steering" / "layer01" / "concepts"), "is NaN or Inf",
                                       "nothing was written"))

    assert_refused(attack_world, tmp_path, attack)


# ----------------------------------------------------------------------------- names over 255 bytes


def long_output(name: str, command: str, flag: str, leaf: str = "") -> Case:
    """`command` of the world with its output option `flag` set to a path holding a 300-byte part."""
    def attack(world: World, tmp_path: Path) -> Case:
        argv = [str(word) for word in good(world, tmp_path)[command]]
        argv[argv.index(flag) + 1] = str(tmp_path / LONG / leaf if leaf else tmp_path / LONG)
        return Case([command, *argv], (str(tmp_path), "is 300 bytes", "at most 255 bytes per name"))
    return named(name, attack)


def long_config_root(world: World, tmp_path: Path) -> Case:
    """A run config whose output_root holds a 300-byte part: preflight names the first folder the run would make."""
    def edit(data: dict) -> None:
        data["output_root"] = str(tmp_path / LONG)
    case = config_case(tmp_path, config_text(world, tmp_path, edit))
    return Case(case.argv, (str(tmp_path / LONG), "is 300 bytes", "at most 255 bytes per name"))


NAME_ATTACKS = [
    long_output("filter_output_dir", "filter", "--output-dir"),
    long_output("convert_output_dir", "convert", "--output-dir"),
    long_output("manifest_output_folder", "manifest", "--output", "m.json"),
    long_output("split_output", "split", "--output"),
    long_output("concept_map_output", "concept-map", "--output-path"),
    long_output("capture_output_dir", "capture", "--output-dir"),
    long_output("slice_output_dir", "slice", "--output-dir"),
    long_output("steer_output_root", "steer", "--output-root"),
    long_output("train_sae_output_dir", "train-sae", "--output-dir"),
    long_config_root,
]


# ----------------------------------------------------------------------------- nesting, memory


def deep_yaml(command: str) -> object:
    def attack(world: World, tmp_path: Path) -> Case:
        text = "name:\n" + "".join("  " * depth + f"k{depth}:\n" for depth in range(1, 3000))
        case = config_case(tmp_path, text, "nested more than 64 levels")
        return Case([command, *case.argv[1:]], case.names)
    return named(f"{command}_config_nested_3000_deep", attack)


def deep_flow_yaml(world: World, tmp_path: Path) -> Case:
    return config_case(tmp_path, "layers: " + "[" * 100_000 + "]" * 100_000, "nested more than 64 levels")


def deep_json(world: World, tmp_path: Path) -> Case:
    path = tmp_path / "pairs.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    argv = [str(word) for word in good(world, tmp_path)["steer"]]
    argv[argv.index("--pairs-config") + 1] = str(path)
    return Case(["steer", *argv], (str(path), "nested too deeply"))


NESTING_ATTACKS = [deep_yaml("capture"), deep_yaml("run"), deep_flow_yaml, deep_json]


def test_memory_exhausted_is_one_line(attack_world, tmp_path, monkeypatch):
    def exhausted(*args, **kwargs):
        raise MemoryError("Unable to allocate 3.2 TiB for an array with shape (10000, 256, 50, 7)")

    monkeypatch.setattr("latent_steering_cli.contrast.build_manifest", exhausted)
    line = assert_refused(attack_world, tmp_path, lambda world, tmp: Case(
        ["manifest", *good(world, tmp)["manifest"]], ("out of memory", "Unable to allocate 3.2 TiB", "lower them")))
    assert "frames, episodes" in line


# ----------------------------------------------------------------------------- estimated work


def evaluate_work(name: str, *flags: str) -> object:
    def attack(world: World, tmp_path: Path) -> Case:
        return Case(["evaluate", *good(world, tmp_path)["evaluate"][:-4], *flags],
                    ("action chunks sampled per (pair, layer)", f"at most {MAX_EVALUATION_SAMPLES:,}", "lower max_frames"))
    return named(name, attack)


def config_work(name: str, section: str, values: dict, expect: str, command: str = "capture",
                extra: tuple[str, ...] = ()) -> object:
    """A run config whose `section` gets `values` (each within its own bound); `command --config` refuses the product."""
    def attack(world: World, tmp_path: Path) -> Case:
        case = config_case(tmp_path, config_text(world, tmp_path, lambda data: data[section].update(values)), expect)
        return Case([command, *case.argv[1:], *extra], case.names)
    return named(name, attack)


ROLLOUT_MAX = {"episodes": 1000, "max_steps": 10_000, "random_directions": 256, "alphas": [float(a) for a in range(64)]}
WORK_ATTACKS = [
    evaluate_work("evaluate_frames_by_seeds", "--max-frames", "10000", "--noise-seeds", "256"),
    evaluate_work("evaluate_directions_by_alphas", "--random-directions", "4096", "--alphas",
                  ",".join(str(a / 2) for a in range(-128, 128)), "--noise-seeds", "32", "--max-frames", "64"),
    config_work("config_evaluate_frames_by_seeds", "evaluate", {"max_frames": 10_000, "noise_seeds": 256},
                f"at most {MAX_EVALUATION_SAMPLES:,}"),
    config_work("config_rollout_episodes_by_steps", "rollout", ROLLOUT_MAX, f"at most {MAX_ROLLOUT_STEPS:,}"),
    config_work("rollout_config_episodes_by_steps", "rollout", ROLLOUT_MAX, "lower rollout.episodes", "rollout"),
    config_work("rollout_episodes_flag", "rollout", {**ROLLOUT_MAX, "episodes": 1}, "episodes 1000", "rollout",
                ("--episodes", "1000")),
]


# ----------------------------------------------------------------------------- demo and dataset content


def tiny_images(world: World, tmp_path: Path) -> Case:
    """`filter` of a demo file whose camera images are 1x1 (a resize the converter cannot do)."""
    def edit(handle: h5py.File) -> str:
        steps = handle["data/demo_0/actions"].shape[0]
        del handle["data/demo_0/obs/agentview_rgb"]
        handle["data/demo_0/obs/agentview_rgb"] = np.zeros((steps, 1, 1, 3), np.uint8)
        return f"data/demo_0/obs/agentview_rgb declares shape ({steps}, 1, 1, 3): height 1 < 8, width 1 < 8"
    return demo_file(world, tmp_path, edit)


def nan_state(frame: int, position: int) -> object:
    """`manifest` of a dataset copy with a NaN at `state[position]` of episode 0's frame `frame`."""
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = tmp_path / "dataset"
        shutil.copytree(world.dataset, dataset)
        data_file = sorted((dataset / "data").rglob("*.parquet"))[0]
        table = pq.read_table(data_file)
        rows = [e == 0 and f == frame for e, f in zip(table.column("episode_index").to_pylist(),
                                                      table.column("frame_index").to_pylist(), strict=True)]
        states = table.column("state").to_pylist()
        states[rows.index(True)][position] = float("nan")
        column = pa.array(states, type=table.schema.field("state").type)
        pq.write_table(table.set_column(table.schema.get_field_index("state"), "state", column), data_file)
        return Case(["manifest", "--lerobot-root", dataset, "--task-a-text", OPEN, "--task-b-text", CLOSE,
                     "--output", tmp_path / "m.json"],
                    (str(data_file), f"episode 0 frame_index {frame}", f"`state`[{position}] is nan"))
    return named(f"manifest_nan_state_frame{frame}_axis{position}", attack)


CONTENT_ATTACKS = [tiny_images, nan_state(10, 2), nan_state(0, 0)]

ATTACKS = [*NAME_ATTACKS, *NESTING_ATTACKS, *WORK_ATTACKS, *CONTENT_ATTACKS]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda attack: attack.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)
