"""The bad-input table, area "bounds": sizes and counts bounded before they are spent, and settings refused where
they are first seen, not after the model is loaded (issue 48, classes 3 and 6).

Bounds: an arch whose depths disagree with the checkpoint's header, a YAML alias bomb, more frame workers than
cores, synthetic demos of terabytes, episode ranges of a trillion. Cases that allocate in proportion to the request
when the bound is missing run the CLI in a child process under a memory limit (`RLIMIT_AS`) and a timeout, so a
missing bound fails the case instead of the machine.

Settings: devices this machine lacks, α beyond `MAX_ALPHA`, NaN and ±inf in float options and settings, a rename
merging two tasks into one concept, one pair of tasks twice. Each is refused in one line naming the file, setting
or option (`helpers_attack.assert_refused`), or by typer's usage error (exit 2) for an option's own type.
"""

from __future__ import annotations

import json
import logging
import resource
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from helpers_attack import (
    CLOSE,
    OPEN,
    Attack,
    Case,
    World,
    assert_refused,
    config_case,
    config_text,
    good,
    registrar,
    snapshot,
)
from test_attack_finite import no_pipeline  # noqa: F401 (a fixture)

import steering_core.capture.frames as frames_module
from latent_steering_cli.lazy import COMMANDS, load_command
from latent_steering_cli.numbers import FiniteNumber
from steering_core.config.yaml_files import MAX_VALUES
from steering_core.data.contrast import MAX_EPISODES
from steering_core.pi05.steering import MAX_ALPHA
from steering_core.synthetic.libero import MAX_FILE_BYTES

CASES: list[Attack] = []  # refused in-process
GUARDED: list[Attack] = []  # refused in a child process under a memory limit
case, guarded = registrar(CASES), registrar(GUARDED)

CHILD_MEMORY = 5 << 30   # address space of a guarded case's process: torch's libraries map ~4.5 GiB of it
CHILD_SECONDS = 240      # far beyond a refusal's few seconds; a case that runs on is stopped here, and fails


def arch_file(world: World, tmp_path: Path, **change: int) -> Path:
    """Return a copy of the world's arch file with `change` applied."""
    arch = json.loads((world.data / "arch.json").read_text()) | change
    path = tmp_path / "arch.json"
    path.write_text(json.dumps(arch))
    return path


def model_flags(world: World, arch: Path) -> list:
    return ["--checkpoint-path", world.checkpoint, "--tokenizer-path", world.tokenizer, "--arch-file", arch,
            "--device", "cpu"]


def capture_argv(world: World, tmp_path: Path, arch: Path, *extra: str) -> list:
    return ["capture", *model_flags(world, arch), "--lerobot-root", world.dataset, "--output-dir", tmp_path / "run",
            "--layers", "1", "--num-workers", "0", *extra]


# ----------------------------------------------------------------------------- class 3: depths against the header


@guarded("capture_arch_file_vision_depth_1e8")
def vision_depth(world: World, tmp_path: Path) -> Case:
    model = world.checkpoint / "model.safetensors"
    return Case(capture_argv(world, tmp_path, arch_file(world, tmp_path, vision_depth=10**8)),
                (str(model), "vision_depth 100000000", "holds 2 SigLIP encoder layers"))


@guarded("capture_arch_file_depth_1e9_decision_rows")
def depth_decision(world: World, tmp_path: Path) -> Case:
    model = world.checkpoint / "model.safetensors"
    return Case(capture_argv(world, tmp_path, arch_file(world, tmp_path, depth=10**9), "--token-type", "decision"),
                (str(model), "depth 1000000000", "holds 4 action expert layers"))


@guarded("run_config_model_arch_depth_1e9")
def config_depth(world: World, tmp_path: Path) -> Case:
    def edit(data: dict) -> None:
        data["model"]["arch"]["depth"] = 10**9
    path = tmp_path / "run.yaml"
    path.write_text(config_text(world, tmp_path, edit))
    return Case(["run", "--config", path], ("before the run started", str(world.checkpoint / "model.safetensors"),
                                            "depth 1000000000"))


@case("capture_arch_file_depth_disagrees")
def depth_disagrees(world: World, tmp_path: Path) -> Case:
    """A depth one more than the checkpoint's: refused from the header, not after the first layers loaded."""
    return Case(capture_argv(world, tmp_path, arch_file(world, tmp_path, depth=5)),
                (str(world.checkpoint / "model.safetensors"), "depth 5", "holds 4 action expert layers"))


# ----------------------------------------------------------------------------- class 3: YAML aliases


def alias_bomb(levels: int) -> str:
    """A run config whose `layers:` holds a list alias nested `levels` deep: 9**levels values in ~70 bytes a level."""
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for level in range(1, levels - 1):
        lines.append(f"a{level}: &a{level} [" + ", ".join([f"*a{level - 1}"] * 9) + "]")
    lines.append("layers: [" + ", ".join([f"*a{levels - 2}"] * 9) + "]")
    return "\n".join(lines) + "\n"


@case("config_yaml_alias_bomb_9e6")
def bomb_small(world: World, tmp_path: Path) -> Case:
    return config_case(tmp_path, alias_bomb(6), f"more than {MAX_VALUES:,} values")


@case("config_yaml_alias_inside_itself")
def alias_loop(world: World, tmp_path: Path) -> Case:
    return config_case(tmp_path, "layers: &loop [1, *loop]\n", f"more than {MAX_VALUES:,} values")


@guarded("config_yaml_alias_bomb_9e9")
def bomb_large(world: World, tmp_path: Path) -> Case:
    assert len(alias_bomb(9)) < 700
    return config_case(tmp_path, alias_bomb(9), f"more than {MAX_VALUES:,} values")


@case("config_error_value_truncated")
def long_value(world: World, tmp_path: Path) -> Case:
    """A setting of the wrong type holding a 1 MB string: the line shows its start, not the megabyte."""
    case = config_case(tmp_path, config_text(world, tmp_path, lambda data: data.update(name=["x" * 1_000_000])),
                       "name: input should be a valid string")
    return Case(case.argv, (*case.names, "x...x"))


# ----------------------------------------------------------------------------- class 3: counts by arithmetic


@guarded("make_demos_a_million_per_task")
def make_demos(world: World, tmp_path: Path) -> Case:
    return Case(["make-demos", "--output-dir", tmp_path / "demos", "--demos-per-task", "1000000"],
                ("demos_per_task 1,000,000", f"at most {MAX_FILE_BYTES >> 30} GiB", "lower --demos-per-task"))


@guarded("demo_a_million_per_task")
def demo_demos(world: World, tmp_path: Path) -> Case:
    return Case(["demo", "--output-dir", tmp_path / "demo", "--demos-per-task", "1000000"],
                ("demo --demos-per-task 1,000,000", "frames", "lower --demos-per-task"))


@case("manifest_episode_range_of_a_trillion")
def episode_range(world: World, tmp_path: Path) -> Case:
    return Case(["manifest", *good(world, tmp_path)["manifest"], "--task-a-episodes", "0-999999999999"],
                ("--task-a-episodes", "1,000,000,000,000", f"{MAX_EPISODES:,}"), exit_code=2)


@case("manifest_unknown_episodes_listed_short")
def unknown_episodes(world: World, tmp_path: Path) -> Case:
    """100,000 episodes the dataset lacks: the line names a few and their count."""
    return Case(["manifest", *good(world, tmp_path)["manifest"], "--task-a-episodes", "1000-100999"],
                ("--task-a-episodes", "(100,000 of them)", "not episodes of"))


# ----------------------------------------------------------------------------- class 6: devices


def device_case(command: str, device: str) -> None:
    @case(f"{command}_device_{device}")
    def attack(world: World, tmp_path: Path) -> Case:
        argv = [str(word) for word in good(world, tmp_path)[command]]
        argv[argv.index("--device") + 1] = device
        return Case([command, *argv], (f"device {device!r}", "not available here"))


for _command in ("capture", "evaluate", "steer", "train-sae"):
    for _device in ("mps", "xpu"):
        device_case(_command, _device)


@case("evaluate_device_meta")
def meta_device(world: World, tmp_path: Path) -> Case:
    argv = [str(word) for word in good(world, tmp_path)["evaluate"]]
    argv[argv.index("--device") + 1] = "meta"
    return Case(["evaluate", *argv], ("device 'meta'", "expected cpu, auto or one of cuda, mps, xpu"))


def run_config_case(name: str, edit, *names: str) -> None:
    """`run --config` of the world's config after `edit`: preflight (or the config's validation) refuses it."""
    @case(f"run_{name}")
    def attack(world: World, tmp_path: Path) -> Case:
        path = tmp_path / "run.yaml"
        path.write_text(config_text(world, tmp_path, edit))
        return Case(["run", "--config", path], names)


for _section in ("steering", "capture", "evaluate", "rollout"):
    run_config_case(f"{_section}_device_mps", lambda data, section=_section: data[section].update(device="mps"),
                    "before the run started", f"{_section}.device: device 'mps'", "not available here")


@case("rollout_config_device_xpu")
def rollout_device(world: World, tmp_path: Path) -> Case:
    case = config_case(tmp_path, config_text(world, tmp_path, lambda data: data["rollout"].update(device="xpu")))
    return Case(["rollout", *case.argv[1:]], ("rollout.device: device 'xpu'", "not available here"))


# ----------------------------------------------------------------------------- class 6: α within MAX_ALPHA


@case("evaluate_alphas_1e300")
def evaluate_alphas(world: World, tmp_path: Path) -> Case:
    return Case(["evaluate", *good(world, tmp_path)["evaluate"], "--alphas", "0,1e300"],
                ("alphas hold |α| = 1e+300", f"above {MAX_ALPHA:g}"))


@case("config_rollout_alphas_1e18")
def rollout_alphas(world: World, tmp_path: Path) -> Case:
    return config_case(tmp_path, config_text(world, tmp_path, lambda data: data["rollout"].update(alphas=[0, 1e18])),
                       "rollout.alphas: alphas hold |α| = 1e+18", f"above {MAX_ALPHA:g}")


@case("config_evaluate_alphas_minus_1000")
def config_evaluate_alphas(world: World, tmp_path: Path) -> Case:
    return config_case(tmp_path, config_text(world, tmp_path,
                                             lambda data: data["evaluate"].update(alphas=[-1000.0, 0.0, 1.0])),
                       "evaluate.alphas: alphas hold |α| = 1000", f"above {MAX_ALPHA:g}")


# ----------------------------------------------------------------------------- class 6: NaN and ±inf


@case("deploy_heartbeat_timeout_nan")
def heartbeat_nan(world: World, tmp_path: Path) -> Case:
    return Case(["deploy", "--config", world.config, "--heartbeat-timeout", "nan"],
                ("--heartbeat-timeout", "'nan': expected", "finite"), exit_code=2)


@case("manifest_min_abs_delta_inf")
def min_delta_inf(world: World, tmp_path: Path) -> Case:
    return Case(["manifest", *good(world, tmp_path)["manifest"], "--min-abs-delta", "inf"],
                ("--min-abs-delta", "'inf': expected", "finite"), exit_code=2)


@case("train_sae_lr_nan")
def lr_nan(world: World, tmp_path: Path) -> Case:
    argv = [str(word) for word in good(world, tmp_path)["train-sae"]]
    return Case(["train-sae", *argv, "--lr", "nan"], ("--lr", "'nan': expected", "finite"), exit_code=2)


@case("config_orchestration_wait_inf")
def config_inf(world: World, tmp_path: Path) -> Case:
    text = config_text(world, tmp_path, lambda data: data.setdefault("orchestration", {}).update(
        worker_wait_seconds=float("inf")))
    return config_case(tmp_path, text, "orchestration.worker_wait_seconds: input should be a finite number")


def test_every_float_option_refuses_nan_and_inf():
    """The class, not its examples: every float option of every command parses through `FiniteNumber`."""
    unguarded = []
    for name in COMMANDS:
        for param in load_command(name).params:
            described = getattr(param, "type_descriptor", None)
            annotation = getattr(described, "annotation", None)
            if (annotation is float or float in getattr(annotation, "__args__", ())) and \
                    not isinstance(described.parameter_info.parser, FiniteNumber):
                unguarded.append(f"{name} {param.opts[0]}")
    assert not unguarded
    for value in ("nan", "inf", "-inf", "1e400"):
        with pytest.raises(ValueError, match="expected a finite number"):
            FiniteNumber()(value)


# ----------------------------------------------------------------------------- class 6: one concept per task, one pair of tasks once


@case("concept_map_rename_merges_two_tasks")
def rename_merge(world: World, tmp_path: Path) -> Case:
    rename = tmp_path / "rename.json"
    rename.write_text(json.dumps({OPEN: CLOSE}))
    manifest = world.data / "manifests" / "open_vs_close.json"
    return Case(["concept-map", *good(world, tmp_path)["concept-map"], "--concept-map", rename],
                (str(manifest), "one concept", repr(OPEN), repr(CLOSE)))


@case("config_same_two_tasks_twice")
def same_pair_twice(world: World, tmp_path: Path) -> Case:
    def edit(data: dict) -> None:
        first = data["pairs"][0]
        data["pairs"] += [{**first, "name": f"copy{i}", "positive": first["negative"], "negative": first["positive"]}
                          for i in range(5000)]
    return config_case(tmp_path, config_text(world, tmp_path, edit), "pairs[0] and pairs[2]",
                       "contrast the same two tasks")


# ----------------------------------------------------------------------------- the tables


@pytest.mark.parametrize("attack", CASES, ids=lambda attack: attack.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack, no_pipeline):  # noqa: F811
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (CHILD_MEMORY, CHILD_MEMORY))


@pytest.mark.parametrize("attack", GUARDED, ids=lambda attack: attack.__name__)
def test_refused_within_memory(attack_world, tmp_path, attack):
    """The case's command in a child process limited to `CHILD_MEMORY` of address space: refused in one line before
    it allocates in proportion to the request (a missing bound ends in a MemoryError or the timeout, and fails)."""
    case = attack(attack_world, tmp_path)
    roots = (attack_world.inputs, attack_world.data, tmp_path)
    before = snapshot(*roots)
    code = "import sys; from latent_steering_cli import app; sys.argv[0] = 'latent-steering'; app()"
    home = tmp_path.parent / f"{tmp_path.name}-home"  # outside the folders that must stay unchanged
    env = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "HOME": str(home)}
    try:
        result = subprocess.run([sys.executable, "-c", code, *map(str, case.argv)], capture_output=True, text=True,
                                timeout=CHILD_SECONDS, cwd=tmp_path, env=env, preexec_fn=_limit_memory)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{case.argv[0]} ran past {CHILD_SECONDS} s under a {CHILD_MEMORY >> 30} GiB limit")
    logged = ("INFO ", "WARNING ")  # the library's log lines on stderr (`configure_logging`): not the error
    lines = [line for line in (result.stdout + result.stderr).splitlines()
             if line.strip() and not any(f" {level}" in line[:20] for level in logged)]
    assert result.returncode == 1, (result.returncode, lines[-5:])
    assert len(lines) == 1 and lines[0].startswith("error: "), lines[-5:]
    for name in case.names:
        assert name in lines[0], (name, lines[0])
    assert snapshot(*roots) == before


def test_frame_workers_are_capped_by_the_cores(monkeypatch, caplog):
    """`capture --num-workers 64` on 2 cores starts 2 frame workers (each a process with torch), and says so."""
    monkeypatch.setattr(frames_module, "usable_cores", lambda: 2)
    with caplog.at_level(logging.WARNING, logger=frames_module.__name__):
        assert frames_module.frame_workers(64) == 2
        assert frames_module.frame_workers(2) == 2 and frames_module.frame_workers(0) == 0
    assert "capture.num_workers 64 is more than the 2 usable cores" in caplog.text
    assert "starting 2 frame workers" in caplog.text
    assert len(caplog.records) == 1


def test_capture_runs_with_more_workers_than_cores(attack_world, tmp_path, monkeypatch, caplog):
    """The capped count is what runs: a capture asking for 64 workers on one core completes, on one worker."""
    from typer.testing import CliRunner

    from latent_steering_cli import app

    monkeypatch.setattr(frames_module, "usable_cores", lambda: 1)
    started = []
    original = frames_module.frame_loader
    monkeypatch.setattr(frames_module, "frame_loader", lambda frames, plan, keys, workers, *rest:
                        started.append(workers) or original(frames, plan, keys, workers, *rest))
    argv = [str(word) for word in good(attack_world, tmp_path)["capture"]]
    argv[argv.index("--num-workers") + 1] = "64"
    with caplog.at_level(logging.WARNING, logger=frames_module.__name__):
        result = CliRunner().invoke(app, ["capture", *argv])
    assert result.exit_code == 0, result.output
    assert started == [1]
    assert "capture.num_workers 64 is more than the 1 usable cores" in caplog.text


def test_a_small_config_with_aliases_still_loads(attack_world, tmp_path):
    """Aliases themselves stay allowed: a config repeating a list by alias loads when its expansion is small."""
    from steering_core.config import load_run_config

    data = yaml.safe_load(attack_world.config.read_text())
    data["output_root"] = str(tmp_path / "out")
    data["rollout"]["layers"] = "ALIAS"
    text = yaml.safe_dump(data, sort_keys=False).replace("layers: ALIAS", "layers: *layers")
    path = tmp_path / "run.yaml"
    path.write_text(text.replace("layers:\n- 1\n- 2\n", "layers: &layers [1, 2]\n", 1))
    assert load_run_config(path).rollout.layers == (1, 2)
