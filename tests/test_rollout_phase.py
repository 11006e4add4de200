"""Phase 5 end to end on the tiny π0.5 in the real LIBERO simulator: the `rollout` command's path in-process, then
the same cells through `latent-steering serve`'s server (same model, same noise seed) and on two simulation workers
sharing one policy: the same episodes; Ctrl-C and a killed worker in a `rollout` command's process."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_serve import FIXED_THREADS_ENV, fixed_threads, write_vectors

from bench.common import session_processes
from steering_core.config import RolloutSection, load_run_config, write_run_config
from steering_core.config.run import RunConfig
from steering_core.config.sections import DatasetSection, ModelSection, PairSection, SourcesSection
from steering_core.pi05.policy import Pi05Policy
from steering_core.rollout.client import LocalPolicy
from steering_core.rollout.local_run import rollout_config
from steering_core.rollout.plan import config_jobs
from steering_core.rollout.records import read_cell
from steering_core.rollout.run import run_chunk
from steering_core.rollout.settings import LiberoTask, RolloutPair
from steering_core.serve import PolicyServer, SteeredPi05Policy, VectorCatalog
from steering_core.serve.server import serving_in_thread
from steering_core.synthetic.pi05 import tiny_arch, write_pi05_checkpoint
from steering_core.synthetic.tokenizer import write_tokenizer

pytestmark = pytest.mark.slow  # a closed-loop run of the demo's grid in the simulator

ARCH = tiny_arch()
PAIR = "open_vs_close"
# libero_goal: both tasks in one scene, so the module builds one env; 2 episodes in chunks of 1 (merged per cell)
TASKS = RolloutPair(positive=LiberoTask(suite="libero_goal", task="open the middle drawer of the cabinet"),
                    negative=LiberoTask(suite="libero_goal", task=7))
CELLS = ("negative_unsteered_a+0", "negative_instruction_swap_a+0", "negative_sae_a+2", "negative_random_0_a+2")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rollout")
    checkpoint = write_pi05_checkpoint(folder / "ckpt", ARCH, seed=3)
    tokenizer = write_tokenizer(folder / "tokenizer.model")
    write_vectors(folder / "data" / "latent_steering", ARCH.width)
    config = RunConfig(
        output_root=folder / "data", sources=SourcesSection(folders=(folder / "demos",)),
        dataset=DatasetSection(repo_id="unused"),
        pairs=(PairSection(name=PAIR, positive="open the top drawer of the cabinet",
                           negative="close the top drawer of the cabinet"),),
        layers=(1,), model=ModelSection(checkpoint=checkpoint, tokenizer=tokenizer, arch=ARCH), evaluate=None,
        rollout=RolloutSection(pairs={PAIR: TASKS}, alphas=(0, 2), episodes=2, chunk_episodes=1, max_steps=12,
                               sides=("negative",), random_directions=1, device="cpu", note="tiny random policy"),
    )
    path = write_run_config(config, folder / "run.yaml")
    with fixed_threads():
        summaries = rollout_config(load_run_config(path))
    return load_run_config(path), summaries


def cell(config, name):
    return read_cell(config.rollout_layer_path(1) / PAIR / name)


def test_every_cell_is_written_with_paired_episodes_videos_and_a_summary(run):
    config, summaries = run
    layer_path = config.rollout_layer_path(1)
    assert summaries == {1: layer_path / "summary.md"}
    summary = json.loads((layer_path / "summary.json").read_text())
    assert summary["note"] == "tiny random policy"
    table = json.loads((layer_path / PAIR / "cells.json").read_text())
    assert sorted(row["cell"] for row in table["cells"]) == sorted(CELLS)
    assert (layer_path / PAIR / "success_vs_alpha.png").stat().st_size > 0
    for name in CELLS:
        record, arrays = cell(config, name)
        assert [e["init_index"] for e in record["episodes"]] == [0, 1]  # two chunks merged in order
        assert [e["seed"] for e in record["episodes"]] == [7, 7]
        assert record["success"]["toward"]["n"] == 2
        video = record["episodes"][0]["video"]
        assert video and (layer_path / PAIR / name / video).stat().st_size > 0
        assert record["episodes"][1]["video"] is None
        assert arrays["actions"].shape[0] == 2 and np.isfinite(arrays["actions"][0, : arrays["lengths"][0]]).all()
    thresholds = cell(config, "negative_sae_a+2")[0]["run"]["thresholds"]  # libero's own predicates, swept
    assert {joint: [label for label, _ in entries] for joint, entries in thresholds.items()} == {
        "flat_stove_1_button": ["turnon"], "wooden_cabinet_1_middle_level": ["open"]}
    assert thresholds["flat_stove_1_button"][0][1] == pytest.approx(0.5, abs=0.006)
    assert (layer_path / PAIR / "joint_trajectories.png").stat().st_size > 0
    assert cell(config, "negative_instruction_swap_a+0")[0]["prompt"] == "open the middle drawer of the cabinet"
    assert cell(config, "negative_sae_a+2")[0]["prompt"] == "turn on the stove"


def test_steering_reaches_the_policy_and_controls_differ(run):
    config, _ = run
    first = {name: cell(config, name)[1]["actions"][0, 0] for name in CELLS}
    # the first action of episode 0 comes from the same observation in every cell: only prompt/steering differ
    assert not np.array_equal(first["negative_sae_a+2"], first["negative_unsteered_a+0"])
    assert not np.array_equal(first["negative_random_0_a+2"], first["negative_sae_a+2"])
    assert not np.array_equal(first["negative_instruction_swap_a+0"], first["negative_unsteered_a+0"])


def test_the_served_policy_gives_the_same_episodes(run):
    config, _ = run
    policy = Pi05Policy.from_checkpoint(config.model.checkpoint, ARCH, device="cpu",
                                        tokenizer_path=config.model.tokenizer)
    served = PolicyServer(SteeredPi05Policy(policy, noise_seed=0), VectorCatalog.scan(config.steering_root),
                          host="127.0.0.1", port=0)
    local = {name: cell(config, name)[1] for name in CELLS[2:]}
    with fixed_threads(), serving_in_thread(served) as server:
        section = config.rollout.model_copy(update={"policy": f"ws://127.0.0.1:{server.port}"})
        rollout_config(config.model_copy(update={"rollout": section}), [(PAIR, 1)])
        episodes = list(server.episodes)
    for name, arrays in local.items():
        _, remote = cell(config, name)
        assert torch.equal(torch.from_numpy(remote["actions"]), torch.from_numpy(arrays["actions"])), name
    assert len(episodes) == 2 * len(CELLS)
    assert {e["task"] for e in episodes} == {"turn on the stove", "open the middle drawer of the cabinet"}
    assert all(e["success"] is False and e["inferences"] > 0 for e in episodes)


def test_a_chunk_on_two_envs_in_lockstep_gives_the_episodes_of_chunks_on_one(run, tmp_path, monkeypatch):
    """Both initial states in one task run, two envs sharing batched calls: each episode as its chunk of one ran it.
    The batched rows equal the lone calls' to float32 rounding: exactly that on the first chunk (the same
    observation), a little more later on as the simulator carries it; a row given to the wrong episode is ~1 off."""
    config, _ = run
    settings = config.rollout.settings().model_copy(update={"chunk_episodes": 2, "envs_per_worker": 2})
    job = next(job for job in config_jobs(config, PAIR, 1) if job.cell.name == "negative_sae_a+2")
    job = job.model_copy(update={"init_states": (0, 1), "output_dir": tmp_path})
    rows, progress, infer_batch = [], [], LocalPolicy.infer_batch
    monkeypatch.setattr(LocalPolicy, "infer_batch", lambda self, batch: rows.append(len(batch)) or infer_batch(self, batch))
    with fixed_threads():
        folder = run_chunk(job, config.capture_settings(), settings, progress=lambda *done: progress.append(done))
    assert progress == [(1, 2), (2, 2)] and rows == [2, 2, 2]  # both replan at steps 0, 5 and 10 of 12
    together, together_arrays = read_cell(folder)
    alone, alone_arrays = cell(config, "negative_sae_a+2")
    assert [e["init_index"] for e in together["episodes"]] == [0, 1]
    for mine, theirs in zip(together["episodes"], alone["episodes"], strict=True):
        assert (mine["outcome"], mine["steps"]) == (theirs["outcome"], theirs["steps"])
    np.testing.assert_allclose(together_arrays["actions"][:, :5], alone_arrays["actions"][:, :5], atol=1e-5)
    np.testing.assert_allclose(together_arrays["actions"], alone_arrays["actions"], atol=1e-2)
    assert together["episodes"][0]["video"] and together["episodes"][1]["video"] is None


def worker_root(config, folder):
    """Return `config` writing its rollouts under `folder` (its steering vectors copied there)."""
    shutil.copytree(config.steering_root, folder / "data" / "latent_steering")
    return config.model_copy(update={"output_root": folder / "data"})


def test_two_workers_give_the_episodes_of_one(run, tmp_path):
    """The same cells on two simulation workers sharing one served policy: per episode the same outcome in the same
    steps, and the same actions (the served rows equal the in-process ones; test above)."""
    config, _ = worker_root(run[0], tmp_path), None
    config = config.model_copy(update={"rollout": config.rollout.model_copy(update={"workers": 2})})
    with fixed_threads():
        rollout_config(config)
    for name in CELLS:
        (mine, mine_arrays), (theirs, theirs_arrays) = cell(config, name), cell(run[0], name)
        assert [(e["init_index"], e["outcome"], e["steps"]) for e in mine["episodes"]] == \
            [(e["init_index"], e["outcome"], e["steps"]) for e in theirs["episodes"]], name
        np.testing.assert_allclose(mine_arrays["actions"], theirs_arrays["actions"], atol=1e-5)


def rollout_process(config, folder):
    """Start `latent-steering rollout` on `config` with 2 workers in a session of its own; return it (its stderr
    collected in `.log`) once both simulation workers run."""
    config = config.model_copy(update={"rollout": config.rollout.model_copy(update={"workers": 2})})
    path = write_run_config(config, folder / "run.yaml")
    process = subprocess.Popen([sys.executable, "-c", "from latent_steering_cli import app; app()", "rollout",
                                "--config", str(path)], start_new_session=True, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True, env={**os.environ, **FIXED_THREADS_ENV})
    process.log = []  # its stderr's lines, all read once `process.reader` ends
    process.reader = threading.Thread(target=lambda: process.log.extend(process.stderr), daemon=True)
    process.reader.start()
    deadline = time.monotonic() + 600  # imports and the policy's load on a loaded machine; prompt when it works
    while len(workers_of(process)) < 2 and time.monotonic() < deadline:
        assert process.poll() is None, "the rollout ended before its workers started"
        time.sleep(0.2)
    return process


def workers_of(process):
    """Return the spawned worker processes of a rollout process."""
    found = []
    for pid in session_processes(process.pid):
        with contextlib.suppress(OSError):
            if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text():
                found.append(pid)
    return found


def busy_worker(process):
    """Return the process id of a worker that has started a chunk (its log line says so)."""
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        assert process.poll() is None, "the rollout ended before a worker started a chunk"
        found = re.search(r"\| worker (\d+) \| steering_core\.rollout\.run - chunk ", "".join(process.log))
        if found:
            return int(found.group(1))
        time.sleep(0.2)
    raise AssertionError("no worker started a chunk in 10 minutes")


def test_ctrl_c_leaves_no_process_behind(run, tmp_path):
    """A terminal's Ctrl-C (SIGINT to the whole process group: the workers get it too) as the workers run: exit 130
    with one line, no traceback (EGL's included), no process left."""
    process = rollout_process(worker_root(run[0], tmp_path), tmp_path)
    assert workers_of(process)
    os.killpg(process.pid, signal.SIGINT)
    assert process.wait(timeout=120) == 130
    deadline = time.monotonic() + 60
    while session_processes(process.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert session_processes(process.pid) == []
    process.reader.join(timeout=60)
    log = "".join(process.log)
    assert "Traceback" not in log and "Exception ignored" not in log, log[-3000:]
    assert log.strip().splitlines()[-1] == ("interrupted: latent-steering rollout stopped by SIGINT; nothing "
                                            "half-written was kept; rerun the same command to resume"), log[-3000:]


def test_a_killed_worker_costs_only_its_chunk(run, tmp_path):
    config = worker_root(run[0], tmp_path)
    process = rollout_process(config, tmp_path)
    os.kill(busy_worker(process), signal.SIGKILL)
    assert process.wait(timeout=1800) == 0
    log = "".join(process.log)
    assert re.search(r"simulation worker \(process \d+\) died while running chunk \d+ of \w+ layer \d+ \S+; its job "
                     r"is lost", log), log[-3000:]
    assert "rendering with EGL on llvmpipe" in log
    for name in CELLS:
        record, _ = cell(config, name)
        assert [e["init_index"] for e in record["episodes"]] == [0, 1], name  # every episode once
    assert session_processes(process.pid) == []
