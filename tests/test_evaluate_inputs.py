"""What `evaluate` refuses before it runs the policy: slices that leak held-out episodes (library and CLI) and a
pairs config whose positive concept is not the manifest's first task (the research group's real files)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from reference_formats import FORMATS
from test_slicing import build_run, segment, write_concept_map
from typer.testing import CliRunner

from latent_steering_cli import app
from steering_core.capture import CaptureSettings
from steering_core.capture.slicing import SliceSettings, slice_concepts
from steering_core.data.contrast import AxisSummary, ContrastManifest, Segment
from steering_core.data.split import HoldoutSplit, TaskSplit, write_split
from steering_core.evaluate import EvaluateSettings
from steering_core.evaluate.run import evaluate_job, pair_job
from steering_core.pi05.spec import ModelSpec
from steering_core.storage.fileio import write_json

OPEN, CLOSE = "open the drawer", "close the drawer"
TASK_OF = {0: OPEN, 1: CLOSE, 2: OPEN, 3: CLOSE}  # test_slicing's run: episodes 0..3, at least 4 frames each
HOLDOUT = (2, 3)
LAYER = 2


def inputs(tmp_path: Path) -> tuple[Path, Path]:
    """Write a run, and the pair `p`'s manifest, concept map and split (episodes 2 and 3 held out) under data/;
    return (run folder, data root)."""
    build_run(tmp_path / "run")
    data = tmp_path / "data"
    (data / "manifests").mkdir(parents=True)
    segments = [Segment(task=task, file="data.parquet", demo=f"episode_{e:06d}", start_step=0, end_step=3,
                        axis_delta=0.1, axis_values=(0.0,) * 4, episode_index=e) for e, task in TASK_OF.items()]
    manifest = ContrastManifest(axis=AxisSummary(index=2, effect_size=3.0, mean_delta_per_task={OPEN: 0.2, CLOSE: -0.2}),
                                segments=tuple(segments))
    write_json(data / "manifests" / "p.json", manifest.model_dump(mode="json"))
    write_concept_map(data / "manifests" / "p_concept_map.json",
                      {task: [segment(e, 0, 3) for e, t in TASK_OF.items() if t == task] for task in (OPEN, CLOSE)})
    split = HoldoutSplit(holdout_fraction=0.5, tasks={OPEN: TaskSplit(train=(0,), holdout=(2,)),
                                                      CLOSE: TaskSplit(train=(1,), holdout=(3,))})
    write_split(split, data / "manifests" / "p_split.json")
    return tmp_path / "run", data


def pairs_config(data: Path, slices: Path) -> Path:
    folder = slices / f"layer{LAYER:02d}"
    return write_json(data / "pairs.json", {"pairs": [{
        "name": "p", "positive_label": OPEN, "positive_path": str(folder / f"{OPEN}.pt"),
        "negative_label": CLOSE, "negative_path": str(folder / f"{CLOSE}.pt")}]})


def job(data: Path, config: Path):
    return pair_job(config, "p", LAYER, relative_to="config", data_root=data, steering_root=data / "latent_steering",
                    dataset_root=data / "lerobot", repo_id="r", output_root=data / "steering_eval")


def test_evaluate_job_refuses_slices_whose_held_out_episodes_differ_from_the_split(tmp_path):
    run, data = inputs(tmp_path)
    (tmp_path / "ckpt").mkdir()
    model = CaptureSettings(model=ModelSpec(checkpoint=tmp_path / "ckpt", tokenizer=tmp_path / "tok"), layers=(LAYER,))
    split = data / "manifests" / "p_split.json"
    for holdout, recorded in (((), r"\[\]"), ((3,), r"\[3\]")):
        slices = tmp_path / f"slices{len(holdout)}"
        slice_concepts(run, data / "manifests" / "p_concept_map.json", slices,
                       SliceSettings(layers=(LAYER,), holdout_episodes=holdout))
        with pytest.raises(ValueError, match=rf"index.json: slices cut holding out episodes {recorded}, but the split "
                                             rf"{split} holds out episodes \[2, 3\]; re-slice with `slice --split"):
            evaluate_job(job(data, pairs_config(data, slices)), model, EvaluateSettings(device="cpu"))
    # slices without an index.json (the seed's) record nothing: refused while the split holds episodes out
    slices = tmp_path / "slices0"
    (slices / f"layer{LAYER:02d}" / "index.json").unlink()
    with pytest.raises(ValueError, match=r"record no held-out episodes .* holds out episodes \[2, 3\]"):
        evaluate_job(job(data, pairs_config(data, slices)), model, EvaluateSettings(device="cpu"))


def test_evaluate_cli_refuses_slices_cut_without_the_split(tmp_path):
    run, data = inputs(tmp_path)
    runner = CliRunner()
    slices = data / "residuals" / "p_slices"
    sliced = runner.invoke(app, ["slice", "--run-dir", str(run), "--concept-map-path",
                                 str(data / "manifests" / "p_concept_map.json"), "--output-dir", str(slices),
                                 "--layers", str(LAYER), "--device", "cpu"])  # no --split: held-out frames sliced
    assert sliced.exit_code == 0, sliced.output
    (tmp_path / "ckpt").mkdir()
    result = runner.invoke(app, [
        "evaluate", "--pairs-config", str(pairs_config(data, slices)), "--layer", str(LAYER), "--data-root", str(data),
        "--lerobot-root", str(tmp_path / "lerobot"), "--checkpoint-path", str(tmp_path / "ckpt"),
        "--tokenizer-path", str(tmp_path / "tok"), "--device", "cpu"])
    assert result.exit_code != 0
    lines = [line for line in result.output.splitlines() if "held" in line or "holding" in line]
    assert len(lines) == 1 and "slices cut holding out episodes []" in lines[0] \
        and "holds out episodes [2, 3]" in lines[0], result.output


def test_evaluation_refuses_a_pairs_config_reversed_against_its_manifest(tmp_path):
    """The research group's files: open_drawer_main's positive is the manifest's first task; swapped, it is refused."""
    data = tmp_path / "data"
    (data / "manifests").mkdir(parents=True)
    shutil.copy(FORMATS / "open_vs_close.json", data / "manifests" / "open_drawer_main.json")
    shutil.copy(FORMATS / "open_vs_close_concept_map.json", data / "manifests" / "open_drawer_main_concept_map.json")
    places = dict(relative_to="config", data_root=data, steering_root=data / "latent_steering", dataset_root=tmp_path,
                  repo_id="r", output_root=data / "steering_eval")
    config = json.loads((FORMATS / "layer12_pairs.json").read_text())
    assert pair_job(FORMATS / "layer12_pairs.json", "open_drawer_main", 12, **places).positive == \
        "open the top drawer of the cabinet"
    spec = config["pairs"][0]
    for side, other in (("label", "label"), ("path", "path")):
        spec[f"positive_{side}"], spec[f"negative_{other}"] = spec[f"negative_{other}"], spec[f"positive_{side}"]
    reversed_config = write_json(tmp_path / "layer12_pairs.json", config)
    with pytest.raises(ValueError, match=r"layer12_pairs.json: pair 'open_drawer_main' has positive 'close the top "
                                         r"drawer of the cabinet' and negative 'open the top drawer of the cabinet', "
                                         r"but its manifest .*open_drawer_main.json lists positive 'open the top "
                                         r"drawer of the cabinet' then negative 'close the top drawer of the cabinet'"):
        pair_job(reversed_config, "open_drawer_main", 12, **places)
