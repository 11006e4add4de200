"""The bad-input table, command-line options: each step's good command line with one option made wrong.

Every case is refused with exit 1 and one `error: ...` line naming the option or file (exit 2 and typer's
usage message for values its own types reject), and no file changes anywhere (`helpers_attack`).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers_attack import OPEN, Case, World, assert_refused, good


def with_option(argv: list, option: str, value, drop: str | None = None) -> list:
    """`argv` with `option`'s value replaced (or the option added), and the option `drop` with its value removed."""
    argv = list(argv)
    if drop is not None:
        del argv[argv.index(drop):argv.index(drop) + 2]
    if option in argv:
        argv[argv.index(option) + 1] = value
    else:
        argv += [option, value]
    return argv


def case(command: str, option: str, value, *names: str, exit_code: int = 1, drop: str | None = None):
    """A case: `command`'s good line with `option` set to `value` (a callable gets the world and tmp)."""
    def attack(world: World, tmp: Path) -> Case:
        bad = value(world, tmp) if callable(value) else value
        argv = with_option(good(world, tmp)[command], option, bad, drop)
        expected = [name(world, tmp) if callable(name) else name for name in names] or [Path(bad).name]
        return Case([command, *argv], tuple(expected), exit_code=exit_code)
    attack.__name__ = f"{command} {option} {value.__name__ if callable(value) else value}"
    return attack


def missing(world: World, tmp: Path) -> Path:
    return tmp / "no_such_input"


def a_folder(world: World, tmp: Path) -> Path:
    (tmp / "a_folder").mkdir(exist_ok=True)
    return tmp / "a_folder"


def empty_folder(world: World, tmp: Path) -> Path:
    return a_folder(world, tmp)


def a_file(world: World, tmp: Path) -> Path:
    (tmp / "a_file.txt").write_text("text\n")
    return tmp / "a_file.txt"


def empty_file(world: World, tmp: Path) -> Path:
    (tmp / "empty.json").write_bytes(b"")
    return tmp / "empty.json"


def not_json(world: World, tmp: Path) -> Path:
    (tmp / "broken.json").write_text("{\"pairs\": [")
    return tmp / "broken.json"


def json_list(world: World, tmp: Path) -> Path:
    (tmp / "list.json").write_text("[1, 2, 3]")
    return tmp / "list.json"


INPUT_FILES = {  # options naming a file the step reads
    "concept-map": ["--manifest-path"],
    "split": ["--manifest"],
    "slice": ["--concept-map-path"],
    "steer": ["--pairs-config"],
    "evaluate": ["--pairs-config", "--tokenizer-path", "--arch-file"],
    "capture": ["--tokenizer-path", "--arch-file"],
    "rollout": ["--config"],
    "run": ["--config"],
    "serve": ["--tokenizer-path", "--arch-file"],
}
JSON_FILES = {
    "concept-map": ["--manifest-path"],
    "split": ["--manifest"],
    "slice": ["--concept-map-path"],
    "steer": ["--pairs-config"],
    "evaluate": ["--pairs-config"],
    "capture": ["--arch-file"],
}
INPUT_FOLDERS = {  # options naming a folder the step reads
    "filter": ["--input-dir"],
    "convert": ["--input-dir"],
    "manifest": ["--lerobot-root"],
    "concept-map": ["--lerobot-root"],
    "capture": ["--checkpoint-path", "--lerobot-root"],
    "slice": ["--run-dir"],
    "steer": ["--sae"],
    "evaluate": ["--lerobot-root", "--checkpoint-path", "--data-root"],
    "serve": ["--checkpoint-path", "--vectors"],
}

CASES = [
    *[case(command, option, value) for command, options in INPUT_FILES.items() for option in options
      for value in (missing, a_folder, empty_file)],
    *[case(command, option, value) for command, options in JSON_FILES.items() for option in options
      for value in (not_json, json_list)],
    *[case(command, option, value) for command, options in INPUT_FOLDERS.items() for option in options
      for value in (missing, empty_folder)],
    # numbers and names out of range
    case("convert", "--image-size", "0", "--image-size"),
    case("convert", "--image-size", "-64", "--image-size"),
    case("convert", "--fps", "0", "--fps", exit_code=2),
    case("convert", "--repo-id", "", "repo"),
    case("filter", "--task", "no such task anywhere", "no such task anywhere"),
    case("filter", "--glob", "*.nothing", "*.nothing"),
    case("manifest", "--task-a-text", "no such task anywhere", "no such task anywhere"),
    case("manifest", "--task-a-index", "99", "99", drop="--task-a-text"),
    case("manifest", "--task-a-index", "-1", "-1", drop="--task-a-text"),
    case("manifest", "--task-a-index", "0", "--task-a-text", exit_code=2),
    case("manifest", "--pad", "-1", "--pad"),
    case("manifest", "--progress-frac", "1.5", "--progress-frac"),
    case("manifest", "--progress-frac", "nan", "--progress-frac", exit_code=2),
    case("manifest", "--min-abs-delta", "-1", "--min-abs-delta"),
    case("manifest", "--min-abs-delta", "inf", "--min-abs-delta", exit_code=2),
    case("manifest", "--max-demos-per-task", "0", "--max-demos-per-task"),
    case("manifest", "--segments-per-class", "0", "--segments-per-class"),
    case("manifest", "--task-a-episodes", "9-3", "9-3", exit_code=2),
    case("manifest", "--task-a-episodes", "x", "x", exit_code=2),
    case("manifest", "--task-a-episodes", "500", "500"),
    case("manifest", "--backend", "parquet", "parquet", exit_code=2),
    case("manifest", "--task-b-text", OPEN, OPEN),
    case("capture", "--layers", "99", "99"),
    case("capture", "--layers", "-1", "-1"),
    case("capture", "--layers", "one", "one", exit_code=2),
    case("capture", "--layers", "", "--layers", exit_code=2),
    case("capture", "--batch-size", "0", "--batch-size", exit_code=2),
    case("capture", "--device", "tpu", "tpu"),
    case("capture", "--device", "cuda:7", "cuda"),
    case("capture", "--dtype", "int8", "int8"),
    case("capture", "--dtype", "float128", "float128"),
    case("capture", "--token-type", "everything", "everything", exit_code=2),
    case("split", "--holdout-fraction", "1.5", "--holdout-fraction", exit_code=2),
    case("split", "--holdout-fraction", "-0.1", "--holdout-fraction", exit_code=2),
    case("slice", "--layers", "7", "7"),
    case("slice", "--token-type", "prompt", "prompt"),
    case("slice", "--device", "tpu", "tpu"),
    case("slice", "--max-samples-per-concept", "0", "--max-samples-per-concept", exit_code=2),
    case("slice", "--split", missing),
    case("steer", "--layer", "7", "7"),
    case("steer", "--batch-size", "0", "--batch-size 0: input should be greater than 0"),  # the model refuses it
    case("steer", "--top-k", "0", "--top-k 0: input should be greater than 0"),
    case("steer", "--top-k", "300", "top_k 300", "256"),  # within the bound, above the SAE's latents
    case("steer", "--device", "tpu", "tpu"),
    case("steer", "--sae", "no-such-release", "no-such-release"),
    case("steer", "--sae", lambda world, tmp: world.sae(2), "sae_layer02"),
    case("steer", "--sae-cfg-from", missing, "cfg.json"),
    case("evaluate", "--layer", "7", "7"),
    case("evaluate", "--alphas", "1,2", "0"),
    case("evaluate", "--alphas", "a,b", "a,b", exit_code=2),
    case("evaluate", "--alphas", "0,nan", "nan"),
    case("evaluate", "--pair", "no_such_pair", "no_such_pair"),
    case("evaluate", "--max-frames", "1", "--max-frames 1: input should be greater than or equal to 2"),  # the model
    case("evaluate", "--random-directions", "2", "--random-directions 2: input should be greater than or equal to 8"),
    case("evaluate", "--device", "tpu", "tpu"),
    case("evaluate", "--expert-layers", "3", "--decision-run", exit_code=2),
    case("evaluate", "--decision-run", missing, "--expert-layers", exit_code=2),
    case("evaluate", "--steering-root", missing),
    case("evaluate", "--norm-stats", missing),
    case("rollout", "--pair", "no_such_pair", "no_such_pair"),
    case("rollout", "--layer", "7", "7"),
    case("rollout", "--episodes", "0", "--episodes", exit_code=2),
    case("rollout", "--api-key-file", missing),
    case("rollout", "--libero-assets", missing),
    case("rollout", "--policy", "http://127.0.0.1:1", "http://127.0.0.1:1"),
    case("serve", "--steer", "open_vs_close", "open_vs_close"),
    case("serve", "--steer", "no_such_pair:1:2", "no_such_pair"),
    case("serve", "--steer", "open_vs_close:7:2", "7"),
    case("serve", "--steer", "open_vs_close:1:nan", "nan"),
    case("serve", "--steer", "open_vs_close:1:2:sideways", "sideways"),
    case("serve", "--port", "70000", "--port", exit_code=2),
    case("serve", "--max-message-mb", "0", "--max-message-mb", exit_code=2),
    case("serve", "--api-key-file", missing),
    case("serve", "--api-key-file", empty_file),
    case("serve", "--norm-stats", missing),
    case("serve", "--action-horizon", "0", "--action-horizon 0: input should be greater than or equal to 1"),
    case("serve", "--device", "tpu", "tpu"),
    case("make-demos", "--image-size", "0", "--image-size"),
    case("make-demos", "--demos-per-task", "0", "--demos-per-task", exit_code=2),
    case("make-demos", "--num-steps", "1", "--num-steps"),
    case("train-sae", "--run-dir", missing, "no_such_input", "metadata.json"),
    case("train-sae", "--run-dir", a_folder, "a_folder", "metadata.json"),
    case("train-sae", "--layer", "3", "layer 3", "metadata.json"),
    case("train-sae", "--k", "100", "k is 100", "d_sae (64)"),
    case("train-sae", "--batch-size", "1000", "batch_size is 1000", "training_rows (640)"),
    case("train-sae", "--d-sae", "0", "--d-sae"),
    # counts and sizes beyond what a step can hold: refused before anything is allocated
    case("train-sae", "--d-sae", "1000000000", "--d-sae 1000000000", "less than or equal to 1048576"),
    case("train-sae", "--training-rows", "1000000000000000", "--training-rows", "less than or equal to 10000000000"),
    case("train-sae", "--buffer-rows", "100000000", "--buffer-rows", "less than or equal to 2097152"),
    case("train-sae", "--batch-size", "10000000", "--batch-size", "less than or equal to 65536"),
    case("train-sae", "--k", "100000", "--k", "less than or equal to 4096"),
    case("steer", "--top-k", "100000000", "--top-k", "less than or equal to 4096"),
    case("steer", "--batch-size", "100000000", "--batch-size", "less than or equal to 1048576"),
    case("train-sae", "--architecture", "gated", "--architecture", exit_code=2),
    case("train-sae", "--device", "tpu", "tpu"),
    case("train-sae", "--output-dir", a_file, "a_file.txt"),
    case("train-sae", "--exclude-episode", "99", "episodes 99", "metadata.json"),
]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("attack", CASES, ids=lambda attack: attack.__name__)
def test_refused(attack_world, tmp_path, attack):
    assert_refused(attack_world, tmp_path, attack)


def test_the_good_lines_run(attack_world, tmp_path):
    """The table's base lines are good: a light step among them runs from them unchanged."""
    from typer.testing import CliRunner

    from latent_steering_cli import app

    lines = good(attack_world, tmp_path)
    result = CliRunner().invoke(app, ["split", *map(str, lines["split"])])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "split.json").is_file()

