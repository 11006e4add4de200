"""The command line itself: commands load lazily, help and light commands start without the heavy libraries,
option errors read as one sentence, and log lines name the Prefect run they come from."""

from __future__ import annotations

import importlib
import inspect
import logging
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

import latent_steering_cli
from latent_steering_cli import app
from latent_steering_cli.lazy import COMMANDS, load_command

HEAVY = ("torch", "lerobot", "transformers", "prefect")


def modules_loaded_by(*argv: str) -> tuple[list[str], str]:
    """Run `latent-steering *argv` in a fresh interpreter; return the heavy top-level modules it imported, and its output."""
    code = (
        "import sys\n"
        "from latent_steering_cli import app\n"
        f"sys.argv = ['latent-steering', *{list(argv)!r}]\n"
        "try:\n    app()\nexcept SystemExit:\n    pass\n"
        f"print('LOADED', sorted({{m.split('.')[0] for m in sys.modules}} & {set(HEAVY)!r}))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    last = done.stdout.strip().splitlines()[-1]
    assert last.startswith("LOADED"), done.stdout[-2000:] + done.stderr[-2000:]
    return eval(last.removeprefix("LOADED "), {}), done.stdout  # noqa: S307  (our own printed list)


@pytest.mark.parametrize("argv", [("--help",), ("filter", "--help"), ("manifest", "--help"), ("concept-map", "--help")])
def test_help_and_light_commands_load_no_heavy_library(argv):
    loaded, output = modules_loaded_by(*argv)
    assert loaded == [], f"{' '.join(argv)} imported {loaded}"
    assert "Usage" in output


def test_help_lists_every_command_with_its_docstring():
    loaded, output = modules_loaded_by("--help")
    for name in ("filter", "convert", "manifest", "concept-map", "capture", "slice", "steer", "run", "demo", "deploy"):
        assert name in COMMANDS and f" {name} " in output, name


def test_the_command_list_matches_the_registered_commands():
    """Every command a module registers is listed with its module and its docstring's first line, and no other."""
    for module in sorted({source.module for source in COMMANDS.values()}):
        importlib.import_module(module)
    for path in sorted(Path(latent_steering_cli.__file__).parent.glob("*.py")):
        importlib.import_module(f"latent_steering_cli.{path.stem}")  # a command in a module not listed is found too
    from latent_steering_cli.app import app as shared

    registered = {info.name: (info.callback.__module__, inspect.getdoc(info.callback).splitlines()[0])
                  for info in shared.registered_commands}
    assert registered == {name: (source.module, source.help) for name, source in COMMANDS.items()}
    assert load_command("slice").name == "slice"


def test_a_heavy_command_loads_its_libraries_when_run():
    loaded, _ = modules_loaded_by("steer", "--help")
    assert "torch" in loaded and "prefect" not in loaded


def test_option_validation_error_is_one_sentence(tmp_path):
    result = CliRunner().invoke(app, ["convert", "--input-dir", str(tmp_path / "demos"), "--repo-id", "x",
                                      "--output-dir", str(tmp_path / "out"), "--image-size", "3"])
    assert result.exit_code == 1
    assert result.output == "error: --image-size 3: input should be greater than or equal to 8\n"


def test_unknown_command_is_a_usage_error():
    result = CliRunner().invoke(app, ["no-such-step"])
    assert result.exit_code == 2 and "No such command" in result.output


def test_log_lines_name_the_prefect_run_and_libraries_stay_quiet():
    configure_logging = sys.modules["latent_steering_cli.app"].configure_logging
    formatter_of = sys.modules["latent_steering_cli.app"].RunNameFormatter
    record = logging.LogRecord("prefect.task_runs", logging.INFO, __file__, 1, "Finished in state %s", ("Cached()",), None)
    record.task_run_name = "slice on_vs_off layer 2"
    text = formatter_of("%(name)s%(run)s: %(message)s").format(record)
    assert text == "prefect.task_runs [slice on_vs_off layer 2]: Finished in state Cached()"
    plain = logging.LogRecord("steering_core.x", logging.INFO, __file__, 1, "hello", (), None)
    assert formatter_of("%(name)s%(run)s: %(message)s").format(plain) == "steering_core.x: hello"
    saved = {name: logging.getLogger(name).level for name in ("httpx", "")}
    try:
        configure_logging(verbose=False)
        assert not logging.getLogger("httpx").isEnabledFor(logging.INFO)
        configure_logging(verbose=True)
        assert logging.getLogger("httpx").isEnabledFor(logging.INFO)
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def test_train_sae_takes_every_training_setting_as_an_option_of_the_models_default_and_help(tmp_path):
    from steering_core.sae.training.settings import TrainSettings

    options = {param.name: param for param in load_command("train-sae").params}
    for name, field in TrainSettings.model_fields.items():
        assert options[name].opts == ["--" + name.replace("_", "-")], name
        assert options[name].default == field.default and options[name].help == field.description, name
    result = CliRunner().invoke(app, ["train-sae", "--run-dir", str(tmp_path), "--layer", "1", "--output-dir",
                                      str(tmp_path / "sae"), "--d-sae", "8", "--k", "9"])
    assert result.exit_code == 1 and "k is 9, expected at most d_sae (8)" in result.output, result.output
    result = CliRunner().invoke(app, ["train-sae", "--run-dir", str(tmp_path), "--layer", "1", "--output-dir",
                                      str(tmp_path / "sae"), "--lr", "2"])
    assert result.exit_code == 1 and "--lr" in result.output, result.output


# the settings model each command builds from its options (where one option sets one field of the same name)
COMMAND_SETTINGS = {
    "filter": "steering_core.data.filtering:FilterSettings", "convert": "steering_core.data.convert:ConvertSettings",
    "make-demos": "steering_core.synthetic.libero:SyntheticSettings",
    "manifest": "steering_core.data.contrast:ContrastSettings", "split": "steering_core.evaluate.settings:EvaluateSettings",
    "capture": "steering_core.capture.settings:CaptureSettings", "slice": "steering_core.capture.slicing:SliceSettings",
    "train-sae": "steering_core.sae.training.settings:TrainSettings",
    "steer": "steering_core.vectors.directions:SteeringSettings",
    "evaluate": "steering_core.evaluate.settings:EvaluateSettings", "rollout": "steering_core.rollout.settings:RolloutSettings",
}
# options whose default differs from the model's on purpose
OWN_DEFAULTS = {("make-demos", "num_steps"): "short demos for a quick look; the library's default is nearer real ones"}


def _comparable(value):
    if isinstance(value, str) and value.replace(",", " ").replace(" ", "").isdigit():
        return tuple(int(part) for part in value.replace(",", " ").split())  # a list option given as text: "12 14"
    if isinstance(value, list | tuple):
        return tuple(_comparable(item) for item in value)
    return str(value) if isinstance(value, Path) else getattr(value, "value", value)


def test_an_option_that_sets_a_setting_defaults_to_the_models_default():
    """Hand-written options are checked against the settings model they fill: same name, same default (None: the
    run config's or the model's applies)."""
    wrong = []
    for command, where in COMMAND_SETTINGS.items():
        module, name = where.split(":")
        model = getattr(importlib.import_module(module), name)
        for param in load_command(command).params:
            field = model.model_fields.get(param.name)
            if field is None or param.default is None or field.is_required() or (command, param.name) in OWN_DEFAULTS:
                continue
            if _comparable(param.default) != _comparable(field.default):
                wrong.append(f"{command} {param.opts[0]}: {param.default!r}, {name}.{param.name}: {field.default!r}")
    assert not wrong, "\n".join(wrong)
