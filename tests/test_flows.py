"""The parent flow end to end in Prefect's test harness, on the generated demo inputs.

One module-wide sequence, each step a fixture building on the previous one:
1. `latent-steering demo` with a fault injected into one task (retried: its state history shows
   it); its outputs equal the CLI steps run one by one on the same inputs;
2. `latent-steering run --config` on unchanged inputs: every task run is `Cached` (read through
   Prefect's API);
3. a refresh with nothing changed ends at once without running the pipeline;
4. one demo file added, then a refresh: only its episodes are captured, only the pair it
   belongs to is recomputed (and re-evaluated), existing shards are untouched.
"""

from __future__ import annotations

import errno
import json
import os
import re
import sys
import threading
import time
from pathlib import Path
from uuid import UUID

import pytest
import torch
import yaml
from prefect import flow, task
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import (
    ArtifactFilter,
    ArtifactFilterFlowRunId,
    ArtifactFilterKey,
    FlowFilter,
    FlowFilterName,
    FlowRunFilter,
    FlowRunFilterId,
    FlowRunFilterParentFlowRunId,
)
from prefect.client.schemas.sorting import FlowRunSort
from prefect.states import Failed
from safetensors import SafetensorError
from safetensors.torch import load_file
from typer.testing import CliRunner

from flows.pipeline import PIPELINE_FLOW, latent_steering
from flows.refresh import refresh
from latent_steering_cli import app
from steering_core.capture import slicing
from steering_core.capture.shards import read_run_metadata
from steering_core.config import load_run_config
from steering_core.data.contrast import read_manifest
from steering_core.data.convert import read_sources
from steering_core.demo import DEMO_ROLLOUT_METHODS, DEMO_STEPS, PLANTED_DIR, build_demo, format_summary, summarise
from steering_core.identity import code_modules, code_version
from steering_core.layout import layer_dir
from steering_core.remote import filesystems, publish
from steering_core.storage import fileio, mirrors
from steering_core.storage.digests import file_digest
from steering_core.storage.fileio import read_json, sha256_file
from steering_core.synthetic.libero import DRAWER_OPEN, MotionSpec, SyntheticSettings, SyntheticTask, write_libero_file
from tasks.cache_keys import content_key
from tasks.cache_records import CACHE_DIR, OUTPUTS
from tasks.results import RESULTS, TaskSet, is_cached, rooted
from tasks.retries import retry_if, transient_gpu, transient_io

PREFLIGHT = "check the run's inputs"  # the parent flow's first task, never cached


@pytest.fixture(scope="module", autouse=True)
def prefect_backend(prefect_server):
    """Every test here talks to the session's Prefect test server (tests/conftest.py)."""
    return prefect_server


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("flows") / "demo_output"


@pytest.fixture(scope="module")
def demo_config(first_run, demo_dir) -> Path:
    return demo_dir / "run.yaml"


def invoke(*args: str):
    """Run a CLI command in this process; environment variables it sets are undone afterwards."""
    saved = dict(os.environ)
    try:
        result = CliRunner().invoke(app, list(args))
    finally:
        os.environ.clear()
        os.environ.update(saved)
    assert result.exit_code == 0, (args[0], result.output, result.exception)
    return result


def latest_pipeline_run() -> UUID:
    """Return the id of the most recent `latent-steering` flow run."""
    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=[PIPELINE_FLOW])),
                                     sort=FlowRunSort.START_TIME_DESC, limit=1)
    return runs[0].id


# ----------------------------------------------------------------------------- cache keys and retries

@task(cache_policy=content_key("steering_core.layout", source=file_digest, ignore=("label",)), **RESULTS)
def double(label: str, source: str, output: str, times: int = 2) -> dict:
    """Write `times` copies of a file's text into `output`."""
    Path(output).write_text(Path(source).read_text() * times)
    return {OUTPUTS: [output]}


@flow
def double_twice(root: str, source: str, label: str = "a", times: int = 2) -> list[str]:
    states = [rooted(double, root)(label, source, f"{root}/out-{i}.txt", times, return_state=True) for i in range(2)]
    return [state.name for state in states]


def test_content_key_caches_on_content_and_reruns_for_missing_outputs(tmp_path):
    source = tmp_path / "in.txt"
    source.write_text("x")
    assert double_twice(str(tmp_path), str(source)) == ["Completed", "Completed"]
    assert double_twice(str(tmp_path), str(source), label="b") == ["Cached", "Cached"]  # ignored parameter
    (tmp_path / "out-1.txt").unlink()
    assert double_twice(str(tmp_path), str(source)) == ["Cached", "Completed"]  # its output was gone
    assert (tmp_path / "out-1.txt").read_text() == "xx"
    source.write_text("y")  # same path, new content
    assert double_twice(str(tmp_path), str(source)) == ["Completed", "Completed"]
    assert double_twice(str(tmp_path), str(source), times=3) == ["Completed", "Completed"]  # a plain parameter
    records = list((tmp_path / CACHE_DIR).iterdir())
    assert len(records) == 2 * 3  # one record per distinct key, beside the outputs


def test_is_cached_predicts_a_cached_run_without_starting_one(tmp_path):
    source = tmp_path / "in.txt"
    source.write_text("x")
    args = ("a", str(source), f"{tmp_path}/out-0.txt")
    assert not is_cached(double, tmp_path, *args)
    assert double_twice(str(tmp_path), str(source)) == ["Completed", "Completed"]
    assert is_cached(double, tmp_path, *args) and is_cached(double, tmp_path, "another label", *args[1:])
    assert not is_cached(double, tmp_path, *args, times=3)
    Path(args[2]).unlink()
    assert not is_cached(double, tmp_path, *args)  # its output is gone: it would run again


@flow
def double_in_a_task_set(root: str, source: str) -> str:
    return TaskSet(root, sys.modules[__name__]).double("a", source, f"{root}/out.txt", return_state=True).name


def test_a_task_set_roots_each_task_of_its_modules_once(tmp_path):
    module = sys.modules[__name__]
    tasks = TaskSet(tmp_path, module)
    source = tmp_path / "in.txt"
    source.write_text("x")
    assert double_in_a_task_set(str(tmp_path), str(source)) == "Completed"
    assert len(list((tmp_path / CACHE_DIR).iterdir())) == 1  # its record under the set's root, as `rooted` puts it
    assert tasks.double is tasks.double and tasks.is_cached("double", "b", str(source), f"{tmp_path}/out.txt")
    assert not TaskSet(tmp_path / "elsewhere", module).is_cached("double", "b", str(source), f"{tmp_path}/out.txt")
    with pytest.raises(AttributeError, match=r"no task 'halve' in this TaskSet \(it has \['double'\]\)"):
        tasks.halve  # noqa: B018
    with pytest.raises(ValueError, match="task 'double' is defined in two of"):
        TaskSet(tmp_path, module, module)


def test_code_version_follows_project_imports_only():
    modules = code_modules("steering_core.capture.slicing")
    assert {"steering_core.capture.slicing", "steering_core.capture.shards", "steering_core.data.concept_map", "steering_core.storage.fileio",
            "steering_core.layout", "steering_core.storage.schema"} <= set(modules)
    assert "steering_core.capture.loop" not in modules and not any(m.startswith("torch") for m in modules)
    assert modules["steering_core.storage.fileio"] == sha256_file(Path(fileio.__file__))
    # capture imports the prefix model lazily inside a function: still part of its code version
    assert "steering_core.pi05.model" in code_modules("steering_core.capture.loop")
    assert code_version("steering_core.capture.slicing") != code_version("steering_core.capture.shards")


def test_code_modules_parse_each_source_once_and_again_when_it_changes(tmp_path, monkeypatch):
    """A tree of its own (steering_core/a.py imports b): the second walk parses nothing; an edited a.py that imports c
    instead is parsed again, and its version follows c, not the b it remembered."""
    from steering_core import identity

    package = tmp_path / "steering_core"
    package.mkdir()
    (package / "b.py").write_text("X = 1\n")
    (package / "c.py").write_text("Y = 2\n")
    (package / "a.py").write_text("from steering_core import b\n")
    monkeypatch.setattr(identity, "_PROJECT_ROOT", tmp_path)
    monkeypatch.setattr(identity, "_module_file", identity._module_file.__wrapped__)  # no paths remembered
    monkeypatch.setattr(identity, "_IMPORTS", {})
    parsed = []
    real_parse = identity.ast.parse
    monkeypatch.setattr(identity.ast, "parse", lambda source: parsed.append(source) or real_parse(source))

    assert list(identity.code_modules("steering_core.a")) == ["steering_core.a", "steering_core.b"]
    assert len(parsed) == 2
    identity.code_modules("steering_core.a")
    assert len(parsed) == 2  # nothing parsed again
    (package / "a.py").write_text("from steering_core import c\n")
    assert list(identity.code_modules("steering_core.a")) == ["steering_core.a", "steering_core.c"]
    assert parsed[2:] == [b"from steering_core import c\n", b"Y = 2\n"]


def test_retry_only_on_transient_errors():
    io, gpu = retry_if(transient_io), retry_if(transient_gpu)
    assert io(double, None, Failed(data=OSError(errno.EIO, "disk")))
    assert io(double, None, Failed(data=TimeoutError("network mount")))
    assert not io(double, None, Failed(data=FileNotFoundError(errno.ENOENT, "gone")))  # a bad path stays bad
    assert not io(double, None, Failed(data=ValueError("bad content")))
    assert gpu(double, None, Failed(data=torch.cuda.OutOfMemoryError("held by a neighbour")))
    assert not gpu(double, None, Failed(data=RuntimeError("shape mismatch")))  # a bug: never retried
    assert not io(double, None, Failed(data=torch.cuda.OutOfMemoryError("x")))
    # safetensors' I/O errors are no OSError: the errno in Rust's message decides (28: disk full)
    full = 'Error while serializing: I/O error: No space left on device (os error 28) at path "/out/.tmpX"'
    assert io(double, None, Failed(data=SafetensorError(full)))
    assert gpu(double, None, Failed(data=SafetensorError(full)))
    assert not io(double, None, Failed(data=SafetensorError(full.replace("os error 28", "os error 2"))))
    assert not io(double, None, Failed(data=SafetensorError("invalid header: shapes disagree with offsets")))


# ----------------------------------------------------------------------------- reading runs back

def flow_runs_under(client, root: UUID) -> list:
    """Return the flow run `root` and every subflow run below it."""
    found, frontier = [], [root]
    while frontier:
        runs = client.read_flow_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=frontier)))
        found += runs
        frontier = [r.id for r in client.read_flow_runs(
            flow_run_filter=FlowRunFilter(parent_flow_run_id=FlowRunFilterParentFlowRunId(any_=frontier)))]
    return found


def task_runs_under(root: UUID, settle_seconds: float = 30.0) -> dict[str, object]:
    """Return task run name -> task run for every task of `root` and its subflows (subflow stand-ins excluded).

    Prefect 3 records task run states from events, asynchronously: right after a flow returns, a task
    may still read as Running. Poll until every state is final (or `settle_seconds` pass).
    """
    deadline = time.monotonic() + settle_seconds
    while True:
        with get_client(sync_client=True) as client:
            runs = flow_runs_under(client, root)
            subflow_stand_ins = {r.parent_task_run_id for r in runs}
            tasks = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[r.id for r in runs])))
        named = {t.name: t for t in tasks if t.id not in subflow_stand_ins}
        if all(t.state is not None and t.state.is_final() for t in named.values()) or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert len(named) == len(tasks) - len(subflow_stand_ins & {t.id for t in tasks}), "task run names must be unique"
    return named


def shard_files(config) -> dict[str, tuple[int, str]]:
    """Return shard file -> (mtime_ns, sha256) of the pipeline's residual run."""
    return {str(p): (p.stat().st_mtime_ns, sha256_file(p)) for p in sorted(config.run_dir.glob("**/shard-*.safetensors"))}


# ----------------------------------------------------------------------------- the run sequence

@pytest.fixture(scope="module")
def first_run(demo_dir):
    """`latent-steering demo`, with the first slicing call of its main run failing on an I/O error (retried);
    the planted-concept check runs before it."""
    real = slicing.slice_concepts
    lock, calls = threading.Lock(), []

    def flaky(*args, **kwargs):
        main_run = PLANTED_DIR not in Path(args[2]).parts
        with lock:
            calls.extend([args[2]] if main_run else [])
            first = main_run and len(calls) == 1
        if first:
            raise OSError(errno.EIO, "injected: shared file system hiccup")
        return real(*args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(slicing, "slice_concepts", flaky)
        result = invoke("demo", "--output-dir", str(demo_dir), "--demos-per-task", "2")
    return latest_pipeline_run(), result.output


@pytest.fixture(scope="module")
def second_run(first_run, demo_config):
    """`latent-steering run --config` on the same inputs."""
    config = load_run_config(demo_config)
    shards_before = shard_files(config)
    result = invoke("run", "--config", str(demo_config))
    return latest_pipeline_run(), shards_before, result.output


@pytest.mark.slow
def test_first_run_writes_the_seed_layout(first_run, demo_config):
    config = load_run_config(demo_config)
    tasks = task_runs_under(first_run[0])
    assert all(t.state.name == "Completed" for t in tasks.values()), {n: t.state.name for n, t in tasks.items()}
    # one task per step, fanned out over pairs and layers
    for pair in ("open_vs_close", "on_vs_off"):
        assert {f"manifest {pair}", f"concept map {pair}"} <= set(tasks)
        for layer in config.layers:
            assert {f"slice {pair} layer {layer}", f"directions {pair} layer {layer}",
                    f"encode {pair} positive layer {layer}", f"encode {pair} negative layer {layer}"} <= set(tasks)
            assert (config.layer_path(layer) / pair / "latent_direction.pt").is_file()
            assert (config.slices_dir(config.pair(pair)) / layer_dir(layer) / "index.json").is_file()
    assert {"capture episodes 0-7", "pairwise stats layer 1", "report layer 2"} <= set(tasks)
    assert tasks["capture episodes 0-7"].tags == ["gpu"]
    # phase 4: a held-out split per pair, one evaluation per (pair, layer) on the gpu tag, a summary per layer
    for pair in ("open_vs_close", "on_vs_off"):
        split = read_json(config.split_path(config.pair(pair)))
        held_out = {e for side in split["tasks"].values() for e in side["holdout"]}
        assert len(held_out) == 2 and f"held-out split {pair}" in tasks
        for layer in config.layers:
            assert tasks[f"evaluate {pair} layer {layer}"].tags == ["gpu"]
            record = read_json(config.eval_layer_path(layer) / pair / "dose_response.json")
            assert record["in_sample"] is False and {f["episode_index"] for f in record["frames"]} == held_out
            index = read_json(config.slices_dir(config.pair(pair)) / layer_dir(layer) / "index.json")
            sliced = {s["episode_index"] for c in index["concepts"].values() for s in c["segments"]}
            assert not sliced & held_out and index["settings"]["holdout_episodes"] == sorted(held_out)
    for layer in config.layers:
        assert f"evaluation summary layer {layer}" in tasks
        assert "these numbers mean nothing" in (config.eval_layer_path(layer) / "summary.md").read_text()
    # the action expert: a decision capture beside the main one, sliced without the held-out episodes, evaluated
    assert config.expert_layers == (2,)
    assert tasks["capture decision episodes 0-7"].tags == ["gpu"]
    decision = read_run_metadata(config.decision_run_dir)
    assert decision.run.token_type == "decision" and decision.run.layers == config.expert_layers
    assert decision.episodes == tuple(range(8)) and decision.run.inputs["num_steps"] == config.evaluate.num_steps
    for pair in ("open_vs_close", "on_vs_off"):
        split = read_json(config.split_path(config.pair(pair)))
        held_out = {e for side in split["tasks"].values() for e in side["holdout"]}
        index = read_json(config.decision_slices_dir(config.pair(pair)) / "layer02" / "index.json")
        assert index["width"] == decision.run.width and index["settings"]["token_type"] == "decision"
        sliced = {s["episode_index"] for c in index["concepts"].values() for s in c["segments"]}
        assert sliced and not sliced & held_out and index["settings"]["holdout_episodes"] == sorted(held_out)
        assert tasks[f"slice {pair} expert layer 2"].state.name == "Completed"
        assert tasks[f"evaluate {pair} expert layer 2"].tags == ["gpu"]
        record = read_json(config.eval_layer_path(2, "expert") / pair / "dose_response.json")
        assert record["stream"] == "expert" and list(record["directions"])[:2] == ["mean_difference",
                                                                                  "mean_difference:clamp"]
        assert len(record["random"]["names"]) == 32 and {f["episode_index"] for f in record["frames"]} == held_out
        lm = read_json(config.eval_layer_path(2) / pair / "dose_response.json")
        assert record["frames"] == lm["frames"]  # the same held-out frames (and noise) as the language model's
        vectors = load_file(config.eval_layer_path(2, "expert") / pair / "dose_response.safetensors")["directions"]
        assert vectors.shape == (2 + 32 + len(record["random"]["permuted"]), decision.run.width)  # both modes
    assert {"evaluation summary expert layer 2", "evaluation pathways"} <= set(tasks)
    pathways = read_json(config.eval_root / "pathways.json")
    assert [(r["pair"], r["lm"]["chosen"][0]["layer"] in config.layers, r["expert"]["chosen"][0]["layer"])
            for r in pathways["rows"]] == [
        ("open_vs_close", True, 2), ("on_vs_off", True, 2)]
    assert "these numbers mean nothing" in (config.eval_root / "pathways.md").read_text()
    assert read_run_metadata(config.run_dir).episodes == tuple(range(8))
    for layer in config.layers:
        assert (config.layer_path(layer) / "summary.md").is_file()
        assert read_json(config.pairs_config_path(layer))["pairs"][0]["name"] == "open_vs_close"


@pytest.mark.slow
def test_the_demo_trains_layer_1s_sae_judges_it_on_held_out_episodes_and_steers_through_it(first_run, demo_config):
    from steering_core.sae.model import load_sae

    config = load_run_config(demo_config)
    tasks = task_runs_under(first_run[0])
    assert tasks["train SAE layer 1"].tags == ["gpu"] and tasks["judge SAE layer01"].tags == ["gpu"]
    assert "features layer01" in tasks and config.trained_layers == (1,)
    sae = load_sae(config.trained_sae_dir(1))
    assert (sae.cfg.hook_name, sae.cfg.model_name, sae.cfg.d_in) == ("blocks.1.hook_resid_post", "pi05", 64)
    # trained without the evaluation's held-out episodes, judged on exactly their rows
    held = {e for pair in config.pairs for side in read_json(config.split_path(pair))["tasks"].values()
            for e in side["holdout"]}
    trained_on = set(read_json(config.trained_sae_dir(1) / "training.json")["source"]["episodes"])
    metadata = read_run_metadata(config.run_dir)
    assert held and not trained_on & held and trained_on | held == set(metadata.episodes)
    held_rows = sum(r.rows for r in metadata.layer_shards(1) if set(r.episodes) <= held)
    judged = read_json(config.sae_layer_path(1) / "fidelity.json")
    assert judged["saes"]["trained"]["rows"]["rows"] == held_rows == judged["saes"]["borrowed"]["rows"]["rows"]
    # the borrowed SAE is random: the trained one must reconstruct far better, rows and actions alike
    trained, borrowed = judged["saes"]["trained"], judged["saes"]["borrowed"]
    assert trained["rows"]["fvu"] < 0.2 < 1 < borrowed["rows"]["fvu"]
    assert trained["actions"]["recovered"] > borrowed["actions"]["recovered"]
    assert judged["verdict"].startswith("trained reconstructs better")
    # layer 1 steers through it; layer 2 through the borrowed SAE of its config
    steered = read_json(config.layer_path(1) / "open_vs_close" / "directions.json")["sae"]
    assert steered["weights_path"] == str(config.trained_sae_dir(1) / "sae_weights.safetensors")
    report = (config.layer_path(1) / "summary.md").read_text()
    assert judged["verdict"] in report and "../../saes/demo/layer01/features.html" in report
    assert "trained on this run's own" not in (config.layer_path(2) / "summary.md").read_text()
    assert (config.sae_layer_path(1) / "features.html").stat().st_size > 10_000
    assert f"layer 1, against the borrowed one (held-out episodes): {judged['verdict']}" in first_run[1]


@pytest.mark.slow
def test_demo_prints_summary_and_locations(first_run, demo_config):
    config = load_run_config(demo_config)
    output = first_run[1]
    summary = summarise(config)
    assert format_summary(summary, random_sae=True) in output
    rows = summary["pairs"]
    assert [(r["layer"], r["pair"]) for r in rows] == [(1, "open_vs_close"), (1, "on_vs_off"),
                                                       (2, "open_vs_close"), (2, "on_vs_off")]
    for row in rows:  # counts are the slice rows; the cosine and FVU are the pair's own
        index = read_json(config.slices_dir(config.pair(row["pair"])) / layer_dir(row["layer"]) / "index.json")
        pair = config.pair(row["pair"])
        assert (row["positive_rows"], row["negative_rows"]) == (
            index["concepts"][pair.positive]["rows"], index["concepts"][pair.negative]["rows"])
        directions = read_json(config.layer_path(row["layer"]) / row["pair"] / "directions.json")
        assert row["decoded_cosine"] == directions["decoded_vs_mean_difference_cosine"]
        assert row["fvu"] == (directions["concepts"]["positive"]["fvu"], directions["concepts"]["negative"]["fvu"])
    for row in summary["between"]:  # the one pairwise entry of each layer, in its own table
        entry = read_json(config.layer_path(row["layer"]) / "pairwise_stats.json")["entries"]["open_vs_close__on_vs_off"]
        assert row["pairs"] == ("open_vs_close", "on_vs_off") and row["residual_cosine"] == entry["residual_cosine"]
    assert [r["layer"] for r in summary["between"]] == [1, 2]
    assert "The demo's borrowed SAEs are random" in output
    assert f"outputs: {config.output_root}" in output
    assert f"report: {config.layer_path(2) / 'summary.md'}" in output
    assert f"report: {config.eval_layer_path(2) / 'summary.md'}" in output
    assert f"report: {config.eval_layer_path(2, 'expert') / 'summary.md'}" in output
    assert f"report: {config.eval_root / 'pathways.md'}" in output


@pytest.mark.slow
def test_closing_table_names_every_task_run_with_its_state(first_run, demo_config):
    output, root = first_run[1], load_run_config(demo_config).output_root
    tasks = task_runs_under(first_run[0])
    assert f"{len(tasks)} task runs: {len(tasks)} ran" in output
    lines = output.splitlines()
    header = max(i for i, line in enumerate(lines) if line.split()[:2] == ["step", "pair"])
    assert lines[header].endswith(f"output (under {root})")  # the main run's table, after the planted check's
    lines = lines[header:]
    slices = [line.split() for line in lines if line.startswith("slice-concepts ")]
    # 2 pairs x (2 layers + 1 expert layer, whose rows read `expert 2`); one retried (the fault)
    assert len(slices) == 6 and sum(" ran (2 attempts) " in " ".join(line) for line in slices) == 1
    encode = next(words for words in map(str.split, lines) if words[:4] == ["encode-concept", "on_vs_off", "negative", "2"])
    assert encode[-1] == "latent_steering/layer02/concepts/"
    assert any(line.split()[:3] == ["capture-residuals", "episodes", "0-7"] for line in lines)
    assert any(line.split()[:4] == ["capture-residuals", "decision", "episodes", "0-7"] for line in lines)
    assert any(line.split()[1:4] == ["on_vs_off", "expert", "2"] and line.endswith("steering_eval/expert_layer02/on_vs_off/")
               for line in lines)


def steered_cells() -> list[str]:
    """Return the demo's steered rollout cells: every method of the demo in both modes, on the negative side at
    push 1."""
    return [f"negative_{method}{mode}_a+1" for method in DEMO_ROLLOUT_METHODS for mode in ("", "+clamp")]


@pytest.mark.slow
def test_demo_rolls_the_steered_policy_out_in_the_simulator(first_run, demo_config):
    config = load_run_config(demo_config)
    tasks = task_runs_under(first_run[0])
    chunks = {name: run for name, run in tasks.items() if name.startswith("rollout open_vs_close layer 1 ")}
    assert sorted(name.split()[4] for name in chunks) == sorted(  # at α toward the other task 0 and 1
        ["negative_unsteered_a+0"] + steered_cells())
    assert {run.state.name for run in chunks.values()} == {"Completed"}
    layer_path = config.rollout_layer_path(1)
    summary = read_json(layer_path / "summary.json")
    answered = sorted((row["side"], row["condition"]) for row in summary["pairs"][0]["answers"])
    assert answered == sorted(("negative", f"{method}{mode}") for method in DEMO_ROLLOUT_METHODS
                              for mode in ("", "+clamp"))
    assert {(row["method"], row["mode"]) for row in summary["methods"]} == {
        (method, mode) for method in DEMO_ROLLOUT_METHODS for mode in ("add", "clamp")}
    for cell in chunks:
        record = read_json(layer_path / "open_vs_close" / cell.split()[4] / "rollouts.json")
        assert len(record["episodes"]) == 2 and all(e["steps"] <= 30 for e in record["episodes"])
    output = first_run[1]
    assert "Closed-loop rollouts in LIBERO, layer01" in output and "says nothing about a real policy" in output
    assert f"report: {layer_path / 'summary.md'}" in output


@pytest.mark.slow
def test_demo_finds_the_planted_concept(first_run):
    check = first_run[1].split("The planted-concept check", 1)[1]
    row = next(line for line in check.splitlines() if line.startswith("planted "))
    assert "mean_difference" in row and ", layer 0 " in row and " 1 / " in row  # either mode, at α = 1
    assert row.count("1.000 [1.000, 1.000]") == 2 and row.split()[-1] == "0.030"  # both sides; p = 1/33
    assert "better than random directions" in check


@pytest.mark.slow
def test_injected_fault_is_retried_and_recorded(first_run):
    tasks = task_runs_under(first_run[0])
    retried = [t for t in tasks.values() if t.run_count > 1]
    assert [t.name.split(" layer")[0].split(" ")[0] for t in retried] == ["slice"]
    with get_client(sync_client=True) as client:
        history = [s.name for s in client.read_task_run_states(retried[0].id)]
    # the failed attempt waits out its retry delay, then the second attempt completes
    assert history[history.index("Running"):] == ["Running", "AwaitingRetry", "Retrying", "Completed"], history
    assert retried[0].state.name == "Completed"


@pytest.mark.slow
def test_artifacts_are_published(first_run):
    progress = ["capture-demo-episodes-0-7", "convert-libero-demo-lerobot", "slice-on-vs-off-layer02",
                "encode-open-vs-close-negative-layer01",
                "evaluate-on-vs-off-layer01"]
    keys = ["demo-report-layer01", "demo-pairwise-cosines-layer02", *progress, "demo-evaluation-layer02",
            "demo-evaluation-pathways"]
    with get_client(sync_client=True) as client:  # this run's versions: other runs of the session share the keys
        runs = [run.id for run in flow_runs_under(client, first_run[0])]
        artifacts = client.read_artifacts(artifact_filter=ArtifactFilter(
            key=ArtifactFilterKey(any_=keys), flow_run_id=ArtifactFilterFlowRunId(any_=runs)))
    by_key = {a.key: a for a in artifacts}
    assert set(by_key) == set(keys)
    assert {key: by_key[key].data for key in progress} == dict.fromkeys(progress, 100.0)
    report = by_key["demo-report-layer01"].data
    assert report.startswith("# Steering vectors, layer01")
    # readable in the UI on its own: plots inline (the trained SAE's judgement too), no relative images or file:// links
    assert report.count("](data:image/png;base64,") == 4 and "](pairwise_cosine.png)" not in report
    assert "fidelity.png)" not in report
    assert "file://" not in report and "## Files" in report
    assert by_key["demo-pairwise-cosines-layer02"].type == "table"
    assert by_key["demo-evaluation-layer02"].data.startswith("# Steering evaluation, layer02")
    assert by_key["demo-evaluation-pathways"].data.startswith("# Steering pathways: language model vs action expert")
    assert "open_vs_close vs on_vs_off" in by_key["demo-pairwise-cosines-layer02"].data


@pytest.mark.slow
def test_outputs_equal_the_cli_steps(first_run, demo_config, cli_steps_run):
    """The seed's steps run one by one through the CLI on the same demo inputs (built in another folder, shared
    with test_reproducible): every output must be equal."""
    config = load_run_config(demo_config)
    out = cli_steps_run[1]
    run_dir = out / "residuals" / "demo"

    for pair in config.pairs:
        ours, theirs = read_manifest(config.manifest_path(pair)), read_manifest(out / "manifests" / f"{pair.name}.json")
        assert (ours.axis, ours.segments) == (theirs.axis, theirs.segments)
        assert (read_json(config.concept_map_path(pair))["concepts"]
                == read_json(out / "manifests" / f"{pair.name}_concept_map.json")["concepts"])
    # shards are byte-identical: same rows, same dtype, same header
    assert ([(r.file, r.sha256) for r in read_run_metadata(config.run_dir).shards]
            == [(r.file, r.sha256) for r in read_run_metadata(run_dir).shards])
    for layer in config.layers:
        for pair in config.pairs:
            for concept in (pair.positive, pair.negative):
                name = f"{concept}.pt"
                assert torch.equal(
                    torch.load(config.slices_dir(pair) / layer_dir(layer) / name, weights_only=True),
                    torch.load(out / "residuals" / f"{pair.name}_slices" / layer_dir(layer) / name, weights_only=True))
            for stem in ("latent_direction", "residual_direction", "positive_latent_mean"):
                ours = load_file(config.layer_path(layer) / pair.name / f"{stem}.safetensors")
                theirs = load_file(out / "latent_steering" / layer_dir(layer) / pair.name / f"{stem}.safetensors")
                assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
        assert (read_json(config.layer_path(layer) / "pairwise_stats.json")["entries"]
                == read_json(out / "latent_steering" / layer_dir(layer) / "pairwise_stats.json")["entries"])

    # phase 4 at the last layer (the CLI's `evaluate`): the same frames, noise, directions and actions
    layer = config.layers[-1]
    for pair in config.pairs:
        ours = load_file(config.eval_layer_path(layer) / pair.name / "dose_response.safetensors")
        theirs = load_file(out / "steering_eval" / layer_dir(layer) / pair.name / "dose_response.safetensors")
        for key in ("actions", "swap_actions", "efficacy", "alphas_vector_units", "z"):
            assert torch.equal(ours[key], theirs[key]), (pair.name, key)
    # the action expert (`capture --token-type decision`, `evaluate --decision-run`): the same rows, slices, outputs
    assert ([(r.file, r.sha256) for r in read_run_metadata(config.decision_run_dir).shards]
            == [(r.file, r.sha256) for r in read_run_metadata(out / "residuals" / "demo_decision").shards])
    for pair in config.pairs:
        for concept in (pair.positive, pair.negative):
            ours = config.decision_slices_dir(pair) / "layer02" / f"{concept}.pt"
            theirs = out / "residuals" / f"{pair.name}_decision_slices" / "layer02" / f"{concept}.pt"
            assert torch.equal(torch.load(ours, weights_only=True), torch.load(theirs, weights_only=True))
        ours = load_file(config.eval_layer_path(2, "expert") / pair.name / "dose_response.safetensors")
        theirs = load_file(out / "steering_eval" / "expert_layer02" / pair.name / "dose_response.safetensors")
        for key in ("actions", "swap_actions", "efficacy", "directions", "z"):
            assert torch.equal(ours[key], theirs[key]), (pair.name, key)


@pytest.fixture(scope="module")
def bucket_run(first_run, demo_dir, s3_endpoint, tmp_path_factory):
    """The demo's run config again with every root in a bucket: its inputs uploaded there, outputs under
    `<bucket>/data`, this process's mirror in a folder of its own (rollouts left out: they are closed-loop
    episodes, not under test here). Return the bucket's URL."""
    bucket = f"s3://flows-{os.getpid()}-{time.monotonic_ns()}"
    fs = filesystems.filesystem("s3")
    fs.mkdir(bucket[5:])
    inputs, data = (demo_dir / "inputs").resolve(), (demo_dir / "data").resolve()
    fs.put(str(inputs), f"{bucket[5:]}/inputs", recursive=True)
    raw = yaml.safe_load((demo_dir / "run.yaml").read_text().replace(str(inputs), f"{bucket}/inputs")
                         .replace(str(data), f"{bucket}/data"))
    raw.pop("rollout")
    fs.pipe_file(f"{bucket[5:]}/run.yaml", yaml.safe_dump(raw).encode())
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(mirrors.MIRROR_ENV, str(tmp_path_factory.mktemp("mirror")))
        try:
            result = latent_steering(f"{bucket}/run.yaml")
        finally:
            mirrors.unmount_all()
    assert result["reports"]["1"] == f"{bucket}/data/latent_steering/layer01"  # the outputs named by URL
    return bucket


@pytest.mark.slow
def test_outputs_on_a_bucket_equal_the_local_run(bucket_run, demo_dir):
    """Every output the local demo run wrote (but the rollouts) is in the bucket, published, with equal bytes:
    tensors exactly, text files apart from where they name the roots (a path here, a URL there) and the digests
    computed over those names. Nothing is left in staging."""
    fs, local = filesystems.filesystem("s3"), demo_dir / "data"
    roots = {str(local.resolve()): "<data>", str((demo_dir / "inputs").resolve()): "<inputs>",
             f"{bucket_run}/data": "<data>", f"{bucket_run}/inputs": "<inputs>"}

    def text(data: bytes) -> str:
        found = data.decode("utf-8")
        for root, name in roots.items():
            found = found.replace(root, name)
        return found

    compared = []
    for path in sorted(p for p in local.rglob("*") if p.is_file()):
        relative = path.relative_to(local).as_posix()
        if relative.split("/")[0] in (CACHE_DIR, "refresh", "rollouts") or path.name.endswith(".lock"):
            continue
        url = f"{bucket_run}/data/{relative}"
        assert publish.is_published(url), url
        ours, theirs = path.read_bytes(), fs.cat_file(url[5:])
        if path.suffix in (".json", ".md", ".html", ".jsonl"):
            ours, theirs = without_root_digests(text(ours)), without_root_digests(text(theirs))
        assert ours == theirs, relative
        compared.append(relative)
    assert sum(name.endswith(".safetensors") for name in compared) > 40  # shards, slices, statistics, directions
    assert publish.staging_files(bucket_run) == []


def without_root_digests(text: str) -> str:
    """Return `text` with its sha256 digests masked: identities of files and settings that name the roots (a
    concept map names its dataset's folder, an SAE its weights file) differ between a local and a bucket root.
    The files they stand for are compared themselves."""
    return re.sub(r'"[0-9a-f]{64}"', '"<digest>"', text)


@pytest.mark.slow
def test_expert_evaluation_key_follows_its_own_pair_only(first_run, demo_config):
    """Changing one pair's decision residuals changes that pair's evaluation key, and no other's."""
    from safetensors.torch import save_file

    from steering_core.evaluate.run import run_config_job
    from steering_core.storage.fileio import sha256_json
    from tasks.evaluate import job_inputs

    config = load_run_config(demo_config)
    jobs = {p.name: run_config_job(config, p.name, 2, "expert") for p in config.pairs}

    def keys() -> dict[str, str]:
        return {name: sha256_json(job_inputs(job)) for name, job in jobs.items()}

    before = keys()
    target = jobs["open_vs_close"].negative_slice.with_suffix(".safetensors")  # what the evaluation reads
    saved = target.read_bytes()
    try:
        tensors = load_file(target)
        tensors["residuals"][0, 0] += 1.0
        save_file(tensors, str(target))
        changed = keys()
    finally:
        target.write_bytes(saved)
    assert changed["open_vs_close"] != before["open_vs_close"] and changed["on_vs_off"] == before["on_vs_off"]
    assert keys() == before


@pytest.mark.slow
def test_cli_refuses_a_decision_run_it_cannot_steer_with(first_run, demo_config, tmp_path):
    """One error line naming --decision-run (or the flag), before anything is sliced or evaluated."""
    import shutil

    config = load_run_config(demo_config)
    wide = tmp_path / "wide"
    shutil.copytree(config.decision_run_dir, wide)
    metadata = read_json(wide / "metadata.json")
    width = metadata["run"]["width"]
    metadata["run"]["width"] = width + 1
    (wide / "metadata.json").write_text(json.dumps(metadata))
    slices = config.decision_slices_dir(config.pair("open_vs_close"))
    stamp = {p: p.stat().st_mtime_ns for p in slices.rglob("*")}
    out = tmp_path / "eval"
    base = ["evaluate", "--pair", "open_vs_close", "--data-root", str(config.output_root), "--output-root", str(out),
            "--lerobot-root", str(config.dataset_root), "--checkpoint-path", str(config.model.checkpoint),
            "--tokenizer-path", str(config.model.tokenizer), "--arch-file",
            str(config.model.checkpoint.parent / "pi05_tiny_arch.json"), "--device", "cpu"]
    cases = {
        (str(wide), "2"): f"error: --decision-run {wide}: its rows are {width + 1} wide, the checkpoint's action "
                          f"expert is {width} wide (an expert direction of the wrong width)",
        (str(config.run_dir), "2"): f"error: --decision-run {config.run_dir}: it holds `instructions` rows, expected "
                                    "`decision` rows",
        (str(config.decision_run_dir), "9"): "error: action-expert layer 9 is not a layer of the policy: it has 4",
    }
    for (run_dir, layers), message in cases.items():
        result = CliRunner().invoke(app, [*base, "--decision-run", run_dir, "--expert-layers", layers])
        assert result.exit_code == 1 and message in " ".join(result.output.split()), result.output
    missing = CliRunner().invoke(app, [*base, "--decision-run", str(wide)])
    assert missing.exit_code == 2 and "--expert-layers required" in " ".join(missing.output.split())
    for extra, message in ((["--expert-layers", "1"], "[1]: the run config's evaluate.expert_layers are [2]"),
                           (["--decision-run", str(wide)], "--decision-run cannot be combined with --config")):
        refused = CliRunner().invoke(app, ["evaluate", "--config", str(demo_config), *extra])
        assert refused.exit_code == 2 and message in " ".join(refused.output.replace("│", " ").split()), refused.output
    assert not out.exists() and {p: p.stat().st_mtime_ns for p in slices.rglob("*")} == stamp


@pytest.mark.slow
def test_capture_cli_with_run_config_agrees_with_the_pipeline(first_run, demo_config):
    """`capture --config` resolves the same settings as the flow: every shard the flow wrote counts as complete."""
    result = invoke("capture", "--config", str(demo_config))
    assert "0 shard group(s) written" in result.output and ", 0 frame(s) captured" in result.output
    refused = CliRunner().invoke(app, ["capture", "--config", str(demo_config), "--layers", "3"])
    assert refused.exit_code == 2 and "--layers cannot be combined with --config" in refused.output


@pytest.mark.slow
def test_second_run_on_unchanged_inputs_is_all_cached(second_run, demo_config):
    run_id, _, output = second_run
    tasks = task_runs_under(run_id)
    assert f"report: {load_run_config(demo_config).layer_path(1) / 'summary.md'}" in output
    assert len(tasks) >= 25
    # every step cached; only the preflight checks run again (files, folders and devices can change)
    assert {name: t.state.name for name, t in tasks.items() if t.state.name != "Cached"} == {PREFLIGHT: "Completed"}
    assert f"{len(tasks)} task runs: 1 ran, {len(tasks) - 1} cached" in output
    assert any(line.split()[:2] == ["preflight", "-"] and line.split()[3] == "ran" for line in output.splitlines())


@pytest.fixture(scope="module")
def unchanged_refresh(second_run, demo_config):
    state = refresh(str(demo_config), return_state=True)
    return state


@pytest.mark.slow
def test_refresh_without_changes_ends_at_once(unchanged_refresh):
    assert unchanged_refresh.result() == {"ran": False, "changes": "0 added, 0 changed, 0 removed"}
    with get_client(sync_client=True) as client:
        runs = flow_runs_under(client, unchanged_refresh.state_details.flow_run_id)
    assert len(runs) == 1  # the refresh alone: no pipeline subflow


@pytest.fixture(scope="module")
def added_demo_refresh(unchanged_refresh, second_run, demo_config):
    """Add one 'open the drawer' demo file (named to sort last), then let the refresh flow react."""
    config = load_run_config(demo_config)
    _, shards_before, _ = second_run
    episodes_before = read_sources(config.dataset_root).episodes
    task = SyntheticTask(instruction=DRAWER_OPEN, scene="LIVING_ROOM_SCENE1", motion=MotionSpec(axis=2, direction=1))
    write_libero_file(config.sources.folders[0], task, num_demos=1,
                      settings=SyntheticSettings(image_size=32, num_steps=DEMO_STEPS, seed=7))
    state = refresh(str(demo_config), return_state=True)
    assert state.is_completed(), state
    return state, shards_before, episodes_before


@pytest.mark.slow
def test_added_demo_recomputes_only_what_depends_on_it(added_demo_refresh, demo_config):
    state, shards_before, episodes_before = added_demo_refresh
    config = load_run_config(demo_config)
    assert state.result()["ran"] is True
    assert state.result()["changes"].startswith("1 added (LIVING_ROOM_SCENE1_open_the_top_drawer_of_the_cabinet_demo")

    # the dataset grew by one episode appended after the old ones
    episodes = read_sources(config.dataset_root).episodes
    assert episodes[:8] == episodes_before and len(episodes) == 9 and episodes[8].file.startswith("LIVING_ROOM")

    tasks = task_runs_under(state.state_details.flow_run_id)
    recomputed = {name for name, t in tasks.items() if t.state.name != "Cached"}
    steps = {f"{step} layer {layer}" for layer in config.layers for step in (
        "slice open_vs_close", "encode open_vs_close positive", "directions open_vs_close", "pairwise stats", "report",
        "evaluate open_vs_close", "evaluation summary")}
    # layer 1's SAE is trained on the run's rows: the new episode's rows retrain it, so every pair of layer 1 is
    # encoded, directed and evaluated again through the new SAE (layer 2's borrowed SAE keeps the stove pair cached)
    steps |= {"train SAE layer 1", "judge SAE layer01", "features layer01", "encode open_vs_close negative layer 1",
              "encode on_vs_off positive layer 1", "encode on_vs_off negative layer 1", "directions on_vs_off layer 1",
              "evaluate on_vs_off layer 1"}
    # the held-out split of both pairs runs again (their manifests record the dataset's new fingerprint)
    assert recomputed == {
        f"filter demos into {config.filtered_dir}", f"convert to LeRobot {config.dataset.repo_id}",
        "manifest open_vs_close", "manifest on_vs_off", "concept map open_vs_close", "concept map on_vs_off",
        "held-out split open_vs_close", "held-out split on_vs_off",
        "capture episodes 8-8", f"run metadata {config.run_dir}", PREFLIGHT, *steps,
        # the action expert: the new episode's decision rows change the drawer pair's decision slices only
        "capture decision episodes 8-8", f"run metadata {config.decision_run_dir}",
        "slice open_vs_close expert layer 2", "evaluate open_vs_close expert layer 2",
        "evaluation summary expert layer 2", "evaluation pathways",
        # closed loop: the drawer pair's steered cells (its vector changed), not its α = 0 cells
        *(name.format(cell) for cell in steered_cells()
          for name in ("rollout open_vs_close layer 1 {} chunk 0", "merge rollout open_vs_close layer 1 {}")),
        "rollout summary layer 1",
    }
    assert all(tasks[name].state.name == "Completed" for name in recomputed)
    assert tasks["capture episodes 0-7"].state.name == "Cached"
    assert tasks["capture decision episodes 0-7"].state.name == "Cached"
    # the refreshed vector (and decision slices) re-evaluate only their own pair
    assert tasks["evaluate on_vs_off layer 2"].state.name == "Cached"
    assert tasks["slice on_vs_off expert layer 2"].state.name == "Cached"
    assert tasks["evaluate on_vs_off expert layer 2"].state.name == "Cached"

    # only the new episode's shards were written; every old shard is the same file as before
    shards_after = shard_files(config)
    assert {path: shards_after[path] for path in shards_before} == shards_before
    assert sorted(set(shards_after) - set(shards_before)) == [
        str(config.run_dir / "instructions" / layer_dir(layer) / "shard-00008.safetensors") for layer in config.layers]
    assert read_run_metadata(config.run_dir).episodes == tuple(range(9))
    # the stove pair kept its outputs; the drawer pair's positive concept grew
    counts = read_json(config.layer_path(1) / "open_vs_close" / "directions.json")["counts"]
    index = read_json(config.slices_dir(config.pair("open_vs_close")) / "layer01" / "index.json")
    assert counts["positive"] == index["concepts"][DRAWER_OPEN]["rows"]
    # three drawer-opening episodes now: the split holds one out, the slices hold the other two
    split = read_json(config.split_path(config.pair("open_vs_close")))["tasks"][DRAWER_OPEN]
    assert len(split["train"]) + len(split["holdout"]) == 3 and len(split["holdout"]) == 1
    assert [s["episode_index"] for s in index["concepts"][DRAWER_OPEN]["segments"]] == split["train"]


def test_bad_input_fails_the_flow_in_its_preflight_task(tmp_path):
    """Before any step: the flow fails with the preflight task's one-line problems, and nothing is written."""
    from flows.pipeline import latent_steering
    from steering_core.config import write_run_config

    config = load_run_config(build_demo(tmp_path / "demo", demos_per_task=2))
    text = tmp_path / "model.safetensors"
    text.write_text("not tensors\n")
    bad = config.model_copy(update={"model": config.model.model_copy(update={"checkpoint": text})})
    state = latent_steering(str(write_run_config(bad, tmp_path / "bad.yaml")), return_state=True)
    assert state.is_failed()
    tasks = task_runs_under(state.state_details.flow_run_id)
    assert list(tasks) == [PREFLIGHT] and tasks[PREFLIGHT].state.is_failed()
    assert f"{text}: not a safetensors file" in tasks[PREFLIGHT].state.message
    assert not config.output_root.exists()
