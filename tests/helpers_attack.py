"""The bad-input table's harness: one finished tiny run to attack, and the checks every refusal must pass.

A case builds its bad input (files under its own `tmp_path`, or options pointing into the finished run)
and returns the command line with the names its error must hold. `assert_refused` runs it in-process and
checks the exit status, that the output is one `error: ...` line holding every name, that no traceback or
torch's `weights_only=False` advice shows, and that no file changed anywhere: not in the finished run and
not beside the bad input (nothing half-written, no existing output touched).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import yaml
from typer.testing import CliRunner

from latent_steering_cli import app


@dataclass(frozen=True)
class World:
    """A finished tiny run: the demo's inputs, its run config, and the seed layout the CLI steps wrote."""

    inputs: Path  # build_demo's folder: run.yaml, inputs/ (demos, checkpoint, tokenizer, SAEs)
    config: Path  # run.yaml
    data: Path  # filtered/, libero_lerobot/<repo>/, manifests/, residuals/, latent_steering/, arch.json

    @property
    def dataset(self) -> Path:
        return self.data / "libero_lerobot" / "libero_demo_lerobot"

    @property
    def checkpoint(self) -> Path:
        return self.inputs / "inputs" / "pi05_tiny"

    @property
    def tokenizer(self) -> Path:
        return self.inputs / "inputs" / "tokenizer.model"

    def sae(self, layer: int) -> Path:
        return self.inputs / "inputs" / f"sae_layer{layer:02d}"


@dataclass(frozen=True)
class Case:
    """A command line, the strings its one error line must hold, and its expected exit status."""

    argv: list[str]
    names: tuple[str, ...]
    exit_code: int = 1
    watch: tuple[Path, ...] = field(default=())  # further folders that must stay unchanged


Attack = Callable[[World, Path], Case]


def registrar(table: list[Attack]) -> Callable[[str], Callable[[Attack], Attack]]:
    """Return `case(name)`: a decorator adding the attack it decorates to `table` under `name` (its test id)."""
    def case(name: str) -> Callable[[Attack], Attack]:
        def register(attack: Attack) -> Attack:
            attack.__name__ = name
            table.append(attack)
            return attack
        return register
    return case


def named(name: str, attack: Attack) -> Attack:
    """`attack` under `name`, the id its table row shows."""
    attack.__name__ = name
    return attack


def dataset_copy(world: World, tmp_path: Path) -> Path:
    """A copy of the world's dataset under `tmp_path`, for a case to change."""
    dataset = tmp_path / "dataset"
    shutil.copytree(world.dataset, dataset)
    return dataset


def snapshot(*roots: Path) -> dict[str, tuple[int, int]]:
    """Every file (with its size and modification time) and folder under `roots`.

    A folder counts by its existence only: a lock file made and removed again beside an output is no change.
    """
    seen = {}
    for root in roots:
        if root.exists():
            for path in (root, *root.rglob("*")):
                stat = path.lstat()
                seen[str(path)] = (-1, 0) if path.is_dir() else (stat.st_size, stat.st_mtime_ns)
    return seen


def assert_refused(world: World, tmp_path: Path, attack: Attack) -> str:
    """Build the case, run it, check it was refused in one line naming its input and changed nothing; return the line."""
    case = attack(world, tmp_path)
    roots = (world.inputs, world.data, tmp_path, *case.watch)
    before = snapshot(*roots)
    result = CliRunner().invoke(app, [str(arg) for arg in case.argv])
    output = result.output
    assert result.exit_code == case.exit_code, (case.argv, output, result.exception)
    assert "Traceback" not in output and "weights_only" not in output, output
    lines = output.strip().splitlines()
    if case.exit_code == 1:
        assert len(lines) == 1 and lines[0].startswith("error: "), output
    for name in case.names:
        assert str(name) in output, (name, output)
    after = snapshot(*roots)
    assert after == before, sorted(set(after.items()) ^ set(before.items()))
    return lines[0] if lines else ""


def config_text(world: World, tmp_path: Path, edit: Callable[[dict], None] | None = None) -> str:
    """Return the world's run config as YAML, writing under `tmp_path/out`, after `edit` of its mapping."""
    data = yaml.safe_load(world.config.read_text(encoding="utf-8"))
    data["output_root"] = str(tmp_path / "out")
    if edit is not None:
        edit(data)
    return yaml.safe_dump(data, sort_keys=False, allow_unicode=True)


def config_case(tmp_path: Path, text: str | bytes, *names: str) -> Case:
    """Return `capture --config` of a run config holding `text`; its error names the file and `names`."""
    path = tmp_path / "run.yaml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return Case(["capture", "--config", path], (str(path), *names))


def make_world(base: Path) -> World:
    """Build the demo's inputs (2 demos per task) and run every CLI step but the evaluation into `base/data`."""
    from helpers_pipeline import run_cli_steps

    from steering_core.config import load_run_config
    from steering_core.demo import build_demo

    config_path = build_demo(base / "demo", demos_per_task=2)
    config = load_run_config(config_path)
    run_cli_steps(config.model_copy(update={"evaluate": None}), base / "data")
    return World(inputs=base / "demo", config=config_path, data=base / "data")


OPEN, CLOSE = "open the top drawer of the cabinet", "close the top drawer of the cabinet"
REPO = "libero_demo_lerobot"


def good(world: World, tmp: Path) -> dict[str, list[str]]:
    """Each command's working command line on the finished run, writing (if it ran) under `tmp`."""
    data = world.data
    model = ["--checkpoint-path", world.checkpoint, "--tokenizer-path", world.tokenizer,
             "--arch-file", data / "arch.json", "--device", "cpu"]
    return {
        "filter": ["--input-dir", world.inputs / "inputs" / "demos", "--output-dir", tmp / "filtered", "--task", OPEN],
        "convert": ["--input-dir", data / "filtered", "--repo-id", REPO, "--output-dir", tmp / "dataset",
                    "--image-size", "16"],
        "manifest": ["--lerobot-root", world.dataset, "--task-a-text", OPEN, "--task-b-text", CLOSE,
                     "--output", tmp / "manifest.json"],
        "concept-map": ["--manifest-path", data / "manifests" / "open_vs_close.json", "--output-path",
                        tmp / "concept_map.json", "--lerobot-root", world.dataset],
        "capture": [*model, "--lerobot-root", world.dataset, "--output-dir", tmp / "run", "--layers", "1",
                    "--num-workers", "0"],
        "split": ["--manifest", data / "manifests" / "open_vs_close.json", "--output", tmp / "split.json"],
        "slice": ["--run-dir", data / "residuals" / "demo", "--concept-map-path",
                  data / "manifests" / "open_vs_close_concept_map.json", "--output-dir", tmp / "slices",
                  "--layers", "1"],
        "steer": ["--pairs-config", data / "layer1_pairs.json", "--output-root", tmp / "steering", "--layer", "1",
                  "--device", "cpu", "--sae", world.sae(1)],
        "evaluate": ["--pairs-config", data / "layer1_pairs.json", "--layer", "1", "--data-root", data,
                     "--output-root", tmp / "eval", "--lerobot-root", world.dataset, *model,
                     "--max-frames", "2", "--noise-seeds", "1"],
        "rollout": ["--config", world.config],
        "run": ["--config", world.config],
        "serve": ["--checkpoint-path", world.checkpoint, "--tokenizer-path", world.tokenizer, "--arch-file",
                  data / "arch.json", "--vectors", data / "latent_steering", "--device", "cpu", "--port", "0"],
        "make-demos": ["--output-dir", tmp / "demos", "--image-size", "16", "--demos-per-task", "1"],
        "train-sae": ["--run-dir", data / "residuals" / "demo", "--layer", "1", "--output-dir", tmp / "sae",
                      "--d-sae", "64", "--k", "4", "--batch-size", "32", "--training-rows", "640",
                      "--buffer-rows", "512", "--checkpoints", "0", "--norm-estimate-batches", "2", "--device", "cpu"],
    }
