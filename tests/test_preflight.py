"""Preflight: every input of a run checked before its first step, one line per problem naming the file."""

from __future__ import annotations

import argparse
import math
import pickle
import shutil

import pytest
import torch
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from steering_core.config import DatasetSection, load_run_config, write_run_config
from steering_core.data.convert import ConvertSettings, convert_libero
from steering_core.demo import build_demo
from steering_core.preflight import PreflightError, check_run, run_problems
from steering_core.synthetic.sae import write_sae_folder


@pytest.fixture(scope="module")
def demo_config(tmp_path_factory):
    return build_demo(tmp_path_factory.mktemp("preflight") / "demo", demos_per_task=2)


@pytest.fixture
def config(demo_config):
    return load_run_config(demo_config)


def with_model(config, **update):
    return config.model_copy(update={"model": config.model.model_copy(update=update)})


def with_sae(config, layer, path):
    sae = dict(config.sae)
    sae[layer] = sae[layer].model_copy(update={"path": path})
    return config.model_copy(update={"sae": sae})


def text_file(path):
    path.write_text("these are not tensors\n")
    return path


def pickle_file(path):
    path.write_bytes(pickle.dumps({"W_enc": [1.0, 2.0]}))
    return path


def pickled_objects(path):
    torch.save({"W_enc": torch.ones(2, 2), "cfg": argparse.Namespace(d_in=2)}, path)
    return path


def poisoned_sae(config, layer, tmp_path, tensor, value):
    """A copy of the layer's SAE folder whose `tensor` starts with `value`."""
    folder = tmp_path / "sae"
    shutil.copytree(config.sae_for(layer).path, folder)
    weights = load_file(folder / "sae_weights.safetensors")
    weights[tensor].view(-1)[0] = value
    save_file(weights, folder / "sae_weights.safetensors")
    return folder


def poisoned_checkpoint(config, tmp_path):
    """A copy of the checkpoint folder whose token embedding starts with NaN."""
    folder = tmp_path / "checkpoint"
    shutil.copytree(config.model.checkpoint, folder)
    tensors = load_file(folder / "model.safetensors")
    tensors["paligemma_with_expert.paligemma.lm_head.weight"][0, 0] = math.nan
    save_file(tensors, folder / "model.safetensors")
    return folder


def truncated_copy(config, tmp_path):
    """A copy of the demo folder whose first file is cut in half (a copy interrupted midway)."""
    folder = tmp_path / "demos"
    shutil.copytree(config.sources.folders[0], folder)
    first = sorted(folder.glob("*.hdf5"))[0]
    first.write_bytes(first.read_bytes()[: first.stat().st_size // 2])
    return config.model_copy(update={"sources": config.sources.model_copy(update={"folders": (folder,)})}), first


def test_a_good_run_has_no_problems(config):
    assert run_problems(config) == []
    check_run(config)


# each case: (make the bad config, text the single problem line must hold)
CASES = {
    "sources folder missing": (
        lambda c, t: c.model_copy(update={"sources": c.sources.model_copy(update={"folders": (t / "nowhere",)})}),
        "nowhere: input folder not found"),
    "checkpoint is text": (lambda c, t: with_model(c, checkpoint=text_file(t / "model.safetensors")),
                           "model.safetensors: not a safetensors file"),
    "checkpoint is a renamed pickle": (lambda c, t: with_model(c, checkpoint=pickle_file(t / "model.safetensors")),
                                       "it looks like a pickle"),
    "checkpoint folder empty": (lambda c, t: with_model(c, checkpoint=t), "pi0.5 checkpoint not found"),
    "checkpoint of another arch": (
        lambda c, t: with_model(c, arch=c.model.arch.model_copy(update={"width": c.model.arch.width * 2})),
        "prefix tensors (up to decoder layer"),
    "tokenizer is text": (lambda c, t: with_model(c, tokenizer=text_file(t / "tok.model")),
                          "tok.model: not a SentencePiece model"),
    "SAE pickled with objects": (lambda c, t: with_sae(c, 1, pickled_objects(t / "sae.pt")),
                                 "sae.pt: holds pickled objects other than tensors"),
    "SAE folder without cfg": (lambda c, t: with_sae(c, 2, t), "not a SAELens SAE folder"),
    "output root is a file": (lambda c, t: c.model_copy(update={"output_root": text_file(t / "out")}),
                              "out: is a file; expected a folder"),
    "action-expert rows for the SAE phase": (
        lambda c, t: c.model_copy(update={"capture": c.capture.model_copy(update={"token_type": "decision"})}),
        "capture.token_type: 'decision' captures action-expert rows, but the run's SAE and steering phase reads "
        "language-model rows (instructions, prompt or last); keep a prompt token type and set evaluate.expert_layers"),
    "SAE of another width": (
        lambda c, t: with_sae(c, 1, write_sae_folder(t / "narrow", d_in=c.model.arch.width // 2, d_sae=32, hook_layer=1)),
        "SAE of layer 1 has d_in 32, but the model's residual width (model.arch.width) is 64"),
    "SAE with an Inf b_enc": (lambda c, t: with_sae(c, 2, poisoned_sae(c, 2, t, "b_enc", math.inf)),
                              "sae_weights.safetensors: tensor `b_enc` holds NaN or Inf (inf at 0)"),
    "checkpoint with a NaN tensor": (lambda c, t: with_model(c, checkpoint=poisoned_checkpoint(c, t)),
                                     "model.safetensors: tensor `paligemma_with_expert.paligemma.lm_head.weight` "
                                     "holds NaN or Inf (nan at (0, 0))"),
    "a run folder's parent is a file": (
        lambda c, t: c.model_copy(update={"output_root": text_file(t / "residuals").parent}),
        "residuals: is a file (a parent of"),
}


@pytest.mark.parametrize("case", CASES)
def test_each_bad_input_is_one_line_naming_it(config, tmp_path, case):
    make, expected = CASES[case]
    problems = run_problems(make(config, tmp_path))
    assert len(problems) == 1, problems
    assert expected in problems[0]
    assert "weights_only=False" not in problems[0]  # torch's advice would run the file's code


def test_truncated_demo_is_named(config, tmp_path):
    config, first = truncated_copy(config, tmp_path)
    problems = run_problems(config)
    assert problems and all(first.name in line for line in problems), problems
    assert any("not a readable HDF5 file" in line for line in problems)


def test_every_problem_at_once(config, tmp_path):
    config = with_model(config, checkpoint=text_file(tmp_path / "model.safetensors"),
                        tokenizer=text_file(tmp_path / "tok.model"))
    config = with_sae(config, 1, pickled_objects(tmp_path / "sae.pt"))
    with pytest.raises(PreflightError) as caught:
        check_run(config)
    assert len(caught.value.problems) == 3
    assert "3 problem(s) found before the run started" in str(caught.value)


def test_cuda_device_without_a_gpu(config):
    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    config = config.model_copy(update={"capture": config.capture.model_copy(update={"device": "cuda"})})
    assert len(problems := run_problems(config)) == 1 and "CUDA is not available" in problems[0]
    assert run_problems(config, capture_device=False) == []  # capture runs on gpu workers


def test_cli_run_stops_before_prefect_starts(config, tmp_path, monkeypatch):
    import flows.pipeline
    from latent_steering_cli import app

    monkeypatch.setattr(flows.pipeline, "latent_steering", lambda *a: pytest.fail("the flow started"))
    bad = with_model(config, checkpoint=pickle_file(tmp_path / "model.safetensors"))
    path = write_run_config(bad, tmp_path / "run.yaml")
    result = CliRunner().invoke(app, ["run", "--config", str(path)])
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    assert "model.safetensors: not a safetensors file" in result.output


@pytest.fixture(scope="module")
def existing_dataset(demo_config, tmp_path_factory):
    """The demo's hdf5 files converted once to v2.1 (by `convert`), to be named by `dataset.existing`."""
    config = load_run_config(demo_config)
    root = tmp_path_factory.mktemp("existing") / "libero"
    convert_libero(config.sources.folders, root, ConvertSettings(repo_id="libero", image_size=16,
                                                                 codebase_version="v2.1"))
    return root


def reading(config, dataset):
    """`config` reading `dataset` in place instead of converting its sources."""
    return config.model_copy(update={"sources": None, "dataset": DatasetSection(existing=dataset)})


def test_an_existing_dataset_is_checked_instead_of_sources(config, existing_dataset, tmp_path):
    assert run_problems(reading(config, existing_dataset)) == []
    typo = config.pairs[0].model_copy(update={"positive": "open the top drawer of the cabinett"})
    problems = run_problems(reading(config, existing_dataset).model_copy(update={"pairs": (typo, *config.pairs[1:])}))
    assert len(problems) == 1 and "task 'open the top drawer of the cabinett' is not in the dataset" in problems[0]
    assert "closest task texts: ['open the top drawer of the cabinet'" in problems[0]
    broken = tmp_path / "broken"
    shutil.copytree(existing_dataset, broken)
    (broken / "data/chunk-000/episode_000001.parquet").unlink()
    problems = run_problems(reading(config, broken))
    assert problems == [f"{broken}: data file(s) ['data/chunk-000/episode_000001.parquet'] listed in "
                        "meta/episodes.jsonl are missing"]
    assert "LeRobot dataset folder not found" in run_problems(reading(config, tmp_path / "nowhere"))[0]
