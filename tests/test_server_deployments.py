"""A real Prefect server, work pools, deployments and workers: the pipeline as users run it.

Starts `prefect server start` on 127.0.0.1 (free port, a PostgreSQL database of its own when
LATENT_STEERING_TEST_POSTGRES names a server, as `.ci/run` does, else SQLite in a temporary PREFECT_HOME; the
report header says which: tests/helpers_prefect_db.py), runs
`latent-steering deploy`, starts one worker per pool, triggers `prefect deployment run`, and checks
through the API that capture ran on `gpu` (two runs sharing the `gpu` concurrency limit of one) and
the slicing and SAE tasks on `cpu`, with outputs written. Every process it started, and their
children, is killed at the end. Each test has its own server; the two scenarios that mostly wait (no gpu
worker, a dying machine) run in threads from the module's start, beside the busy first test.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import pytest
import yaml
from helpers_prefect_db import server_database
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import (
    FlowFilter,
    FlowFilterName,
    FlowRunFilter,
    FlowRunFilterId,
    LogFilter,
    LogFilterFlowRunId,
)
from prefect.settings import PREFECT_API_URL, temporary_settings

from steering_core.capture.shards import read_run_metadata
from steering_core.config import load_run_config
from steering_core.demo import DEMO_ROLLOUT_METHODS, build_demo
from steering_core.layout import layer_dir
from steering_core.remote import filesystems, publish
from steering_core.storage import mirrors
from steering_core.storage.fileio import read_json

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
PREFECT = [sys.executable, "-m", "prefect"]
LATENT_STEERING = str(Path(sys.executable).parent / "latent-steering")  # the console script of this venv
# Deadlines are generous, so that only a hang fails them: a run that took 900 s beside other jobs (load 5-10, two
# cores) once failed here with its evaluation runs still Running. A scenario's waits are each at most RUN_TIMEOUT.
RUN_TIMEOUT = 3600  # seconds for one deployment run (4 evaluation runs included), or one wait of a scenario
CLI_TIMEOUT = 600   # seconds for one CLI call (`latent-steering deploy`, `prefect deployment run`)
LOG_TIMEOUT = 300   # seconds until a finished run's last log lines are recorded (they are sent after its final state)
WORKER_GRACE = 5   # seconds a worker gets after SIGTERM before SIGKILL (they rarely stop by themselves)
SCENARIO_TIMEOUT = 3 * RUN_TIMEOUT  # seconds a test or background scenario may take (its three waits at most)
# the deploy automation's window in the dying-machines scenario, which waits for it once (the dead parent): five times
# the longest server stall measured under load (60 s, SQLite), not the 600 s default, to keep the scenario short
AUTOMATION_WINDOW = 300
SERVER_START_TIMEOUT = 300  # seconds until /api/health answers: 9-16 s measured idle (migrations on a new database)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def descendants(pid: int) -> list[int]:
    """Return the pids of every live descendant of `pid` (read from /proc; flow runs start their own sessions)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, frontier = [], [pid]
    while frontier:
        frontier = [child for parent in frontier for child in children.get(parent, [])]
        found += frontier
    return found


class Processes:
    """Processes this test started, each in its own process group, stopped together."""

    def __init__(self, env: dict[str, str], logs: Path):
        self.env, self.logs, self.started = env, logs, []

    def start(self, name: str, *args: str, cwd: Path = REPO, env: dict[str, str] | None = None) -> subprocess.Popen:
        log = open(self.logs / f"{name}.log", "w")  # noqa: SIM115  closed in stop()
        process = subprocess.Popen(args, cwd=cwd, env=env or self.env, stdout=log, stderr=subprocess.STDOUT,
                                   start_new_session=True)
        self.started.append((process, log))
        return process

    def stop(self) -> None:
        for process, log in reversed(self.started):
            family = [process.pid, *descendants(process.pid)]
            self._signal(process.pid, family, signal.SIGTERM)
            try:
                process.wait(timeout=WORKER_GRACE)
            except subprocess.TimeoutExpired:
                pass
            self._signal(process.pid, family, signal.SIGKILL)
            process.wait(timeout=30)
            log.close()
        assert not [pid for process, _ in self.started for pid in descendants(process.pid)]

    @staticmethod
    def _signal(leader: int, family: list[int], sig: int) -> None:
        for target in (lambda: os.killpg(leader, sig), *[(lambda p=p: os.kill(p, sig)) for p in family]):
            try:
                target()
            except (ProcessLookupError, PermissionError):
                pass


def start_machine(processes: Processes, name: str, pool: str, folder: Path) -> subprocess.Popen:
    """Start a worker of `pool` as if on its own machine: its own working directory, mirror of the bucket, caches
    and Prefect home. It shares only the Prefect server and the bucket with the others."""
    folder.mkdir(parents=True)
    env = {**processes.env, "LATENT_STEERING_MIRROR": str(folder / "mirror"), "XDG_CACHE_HOME": str(folder / "cache"),
           "LATENT_STEERING_DIGEST_CACHE": str(folder / "digests"), "PREFECT_HOME": str(folder / "prefect_home"),
           "LATENT_STEERING_LOCK_LEASE_S": "15"}  # a killed machine's bucket locks are taken over within 15 s
    return processes.start(name, *PREFECT, "worker", "start", "--pool", pool, cwd=folder, env=env)


def bucket_demo(folder: Path, bucket: str, edit: Callable[[dict], None]) -> str:
    """Put the demo inputs and its run config (edited by `edit`) in the bucket, with every root a URL there (outputs
    under `<bucket>/data`), and delete them here; return the config's URL."""
    config_path = build_demo(folder / "demo", demos_per_task=2)
    raw = yaml.safe_load(config_path.read_text())
    edit(raw)
    inputs, data = (folder / "demo" / "inputs").resolve(), (folder / "demo" / "data").resolve()
    fs = filesystems.filesystem("s3")
    fs.put(str(inputs), f"{bucket[5:]}/inputs", recursive=True)
    text = yaml.safe_dump(raw).replace(str(inputs), f"{bucket}/inputs").replace(str(data), f"{bucket}/data")
    assert str(folder) not in text, text  # nothing on this machine's disk is named
    fs.pipe_file(f"{bucket[5:]}/run.yaml", text.encode())
    shutil.rmtree(folder / "demo")
    return f"{bucket}/run.yaml"


def published(path: Path) -> bool:
    """Return True when the mirror path `path` is a published output in the bucket (or lies in one)."""
    return publish.is_published(mirrors.url_of(path))


def bucket_files(url: str, pattern: str) -> list[str]:
    """Return the objects under `url` whose path matches the glob `pattern` (relative to `url`)."""
    fs, path = filesystems.object_path(url)
    return sorted(fs.glob(f"{path}/{pattern}"))


def run_deployment_and_wait(env: dict[str, str], deployment: str, worker_log: Path):
    """Start a deployment run with the CLI and return the flow run once it completed."""
    run = run_deployment_until_final(env, deployment, worker_log)
    assert run.state.is_completed(), worker_log.read_text()[-5000:]
    return run


def run_deployment_until_final(env: dict[str, str], deployment: str, worker_log: Path):
    """Start a deployment run with the CLI and return the flow run once it reached a final state."""
    output = run_cli(env, *PREFECT, "deployment", "run", deployment)
    run_id = re.search(r"UUID: ([0-9a-f-]{36})", output).group(1)
    deadline = time.monotonic() + RUN_TIMEOUT
    with get_client(sync_client=True) as client:
        while not (run := client.read_flow_run(run_id)).state.is_final():
            assert time.monotonic() < deadline, worker_log.read_text()[-3000:]
            time.sleep(2)
    return run


def run_cli(env: dict[str, str], *args: str, timeout: int = CLI_TIMEOUT) -> str:
    done = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    assert done.returncode == 0, f"{' '.join(args[:4])} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done.stdout + done.stderr


@contextlib.contextmanager
def prefect_server(folder: Path) -> Iterator[tuple[dict[str, str], Processes]]:
    """A Prefect server on a free port with its own database (`server_database`) and home under `folder`; yields
    (env, processes). Only the server gets the database URL: workers and flow runs reach it through the API."""
    port = free_port()
    url = f"http://127.0.0.1:{port}/api"
    env = {**os.environ, "PREFECT_HOME": str(folder / "prefect_home"), "PREFECT_API_URL": url,
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PREFECT_WORKER_QUERY_SECONDS": "2",
           "PREFECT_UI_ENABLED": "false", "HF_HUB_OFFLINE": "1"}
    logs = folder / "logs"
    logs.mkdir()
    processes = Processes(env, logs)
    with server_database() as database:
        try:
            processes.start("server", *PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port),
                            "--no-ui", env={**env, **database})
            deadline = time.monotonic() + SERVER_START_TIMEOUT
            while True:  # a busy port still exits 0, so trust only the health endpoint
                try:
                    if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                assert time.monotonic() < deadline, (logs / "server.log").read_text()[-3000:]
                time.sleep(1)
            with temporary_settings(updates={PREFECT_API_URL: url}):
                yield env, processes
        finally:
            processes.stop()


@pytest.fixture
def server(tmp_path, s3_endpoint):
    """A Prefect server for this test alone; yields (env, processes)."""
    with prefect_server(tmp_path) as started:
        yield started


class Scenario(threading.Thread):
    """A test's whole scenario on its own server, run in a thread from the start of this module.

    The scenarios below mostly wait (on a worker that never comes, on the crash automation's heartbeat timeout),
    so they overlap the busy test instead of adding their waits to the suite. Their assertions run in the thread;
    `result()` raises the first one that failed, in the test the scenario belongs to.
    """

    def __init__(self, body: Callable[[dict[str, str], Processes, Path], None], folder: Path):
        super().__init__(name=body.__name__, daemon=True)
        self.body, self.folder, self.error = body, folder, None
        self.context = contextvars.copy_context()  # Prefect's settings live in context variables

    def run(self) -> None:
        self.context.run(self._run)

    def _run(self) -> None:
        try:
            with prefect_server(self.folder) as (env, processes):
                self.body(env, processes, self.folder)
        except BaseException as error:  # noqa: BLE001  re-raised by result()
            self.error = error

    def result(self, timeout: float) -> None:
        self.join(timeout)
        assert not self.is_alive(), f"{self.name} still running after {timeout:.0f} s (logs in {self.folder})"
        if self.error is not None:
            raise self.error


@pytest.mark.timeout(SCENARIO_TIMEOUT)  # the background scenarios share the machine with it
def test_deployment_run_uses_gpu_pool_for_capture_and_cpu_pool_for_sae(bucket, server, tmp_path, cli_steps_run):
    """Capture and the steering evaluation run as deployments on the gpu pool, the SAE phase on the cpu pool, the
    rollouts on the sim pool: three workers as on three machines (no folder in common), every input and output in
    the bucket. The outputs equal, byte for byte, those of the seed's steps run locally on the same inputs."""
    env, processes = server

    def edit(raw: dict) -> None:
        # two capture runs (4 shard groups each) so the gpu pool has work to share
        raw["orchestration"] = {"shards_per_capture_run": 4, "poll_seconds": 2}
        # the smallest evaluation: where it runs is under test here, not what it measures
        raw["evaluate"] |= {"max_frames": 2, "noise_seeds": 1, "alphas": [-1.0, 0.0, 1.0], "bootstrap": 20}

    config_url = bucket_demo(tmp_path, bucket, edit)
    config = load_run_config(config_url)  # this test's own mirror: a fourth machine, reading the bucket

    output = run_cli(env, LATENT_STEERING, "deploy", "--config", config_url, "--storage", f"{bucket}/data",
                     "--gpu-slots", "1")
    assert f"{bucket}/data/.prefect-cache" in output
    with get_client(sync_client=True) as client:
        assert {p.name for p in client.read_work_pools()} >= {"gpu", "cpu", "sim"}
        assert client.read_concurrency_limit_by_tag("gpu").concurrency_limit == 1
        deployments = {d.name: d for d in client.read_deployments()}
        assert {"pipeline", "gpu", "scheduled", "sim-rollout", "gpu-train-sae"} <= set(deployments)
        assert deployments["sim-rollout"].work_pool_name == "sim" and deployments["gpu-train-sae"].work_pool_name == "gpu"
        assert deployments["scheduled"].schedules and deployments["gpu"].work_pool_name == "gpu"
        assert deployments["pipeline"].parameters["config_path"] == config_url
        # no scheduled refresh may start during the test (an hour boundary can fall inside it);
        # pausing deletes its auto-scheduled runs, manual runs still work
        client.pause_deployment(deployments["scheduled"].id)

    machines = {pool: tmp_path / f"machine-{pool}" for pool in ("gpu", "cpu", "sim")}
    for pool, folder in machines.items():
        start_machine(processes, f"worker-{pool}", pool, folder)
    parent = run_deployment_and_wait(env, "latent-steering/pipeline", tmp_path / "logs" / "worker-cpu.log")
    with get_client(sync_client=True) as client:
        assert parent.work_pool_name == "cpu"

        captures = client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=["latent-steering-capture"])))
        assert len(captures) == 2  # each also captures the action expert's decision rows of its episodes
        assert {(r.work_pool_name, r.state.name) for r in captures} == {("gpu", "Completed")}
        assert {r.parent_task_run_id is not None for r in captures} == {True}  # linked to the parent
        # phase 4: one evaluation run per (pair, layer), the expert's layers included, on the gpu pool too
        evaluations = client.read_flow_runs(
            flow_filter=FlowFilter(name=FlowFilterName(any_=["latent-steering-evaluate"])))
        assert len(evaluations) == 2 * (len(config.layers) + len(config.expert_layers))
        assert {(r.work_pool_name, r.state.name) for r in evaluations} == {("gpu", "Completed")}
        # phase 5: one rollout run per (pair, layer, side) on the sim pool, a chunk task per cell in each
        rollouts = client.read_flow_runs(
            flow_filter=FlowFilter(name=FlowFilterName(any_=["latent-steering-rollout"])))
        assert len(rollouts) == len(config.rollout_targets()) * len(config.rollout.sides)
        assert {(r.work_pool_name, r.state.name) for r in rollouts} == {("sim", "Completed")}
        # the SAE trained on layer 1's residuals: one run on the gpu pool, training then judging on the gpu tag
        trainings = client.read_flow_runs(
            flow_filter=FlowFilter(name=FlowFilterName(any_=["latent-steering-train-sae"])))
        assert [(r.work_pool_name, r.state.name) for r in trainings] == [("gpu", "Completed")]
        trained = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[trainings[0].id])))
        assert sorted((t.name, t.tags) for t in trained) == [("judge SAE layer01", ["gpu"]),
                                                              ("train SAE layer 1", ["gpu"])]
        chunks = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[r.id for r in rollouts])))
        # the negative side: α = 0 and every rolled-out method in both modes at the push
        assert sum(t.name.startswith("rollout open_vs_close layer 1 ") for t in chunks) == 1 + 2 * len(DEMO_ROLLOUT_METHODS)

        runs = {r.id: r for r in [parent, *captures]}
        tasks = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=list(runs))))
        pool_of = {t.name: runs[t.flow_run_id].work_pool_name for t in tasks if t.id not in
                   {r.parent_task_run_id for r in captures}}
    assert {pool_of[f"capture {kind}episodes {episodes}"] for kind in ("", "decision ")
            for episodes in ("0-3", "4-7")} == {"gpu"}
    sae_tasks = [name for name in pool_of if name.split(" ")[0] in ("slice", "encode", "directions", "pairwise")]
    # slices (+ the decision slices per pair and expert layer), encodes, directions, pairwise per layer
    assert len(sae_tasks) == 2 * 2 + 2 * len(config.expert_layers) + 2 * 2 * 2 + 2 * 2 + 2
    assert {pool_of[name] for name in sae_tasks} == {"cpu"}
    assert pool_of["features layer01"] == "cpu"  # the trained SAE's feature page: after the SAE phase, on the cpu pool

    # the tag limit of one GPU slot kept the two capture tasks from overlapping
    spans = sorted((t.start_time, t.end_time) for t in tasks if t.name.startswith("capture episodes"))
    assert spans[0][1] <= spans[1][0]

    # every output is in the bucket, published; no staging is left; the machines shared nothing else
    data = f"{bucket}/data"
    assert len(bucket_files(f"{data}/residuals/demo", "**/shard-*.safetensors")) == 8 * len(config.layers)
    for layer in config.layers:
        assert published(config.layer_path(layer) / "summary.md")
        assert published(config.layer_path(layer) / "on_vs_off" / "residual_direction.pt")
        assert published(config.eval_layer_path(layer) / "on_vs_off" / "dose_response.json")
        assert published(config.eval_layer_path(layer) / "summary.md")
    for layer in config.expert_layers:
        assert published(config.eval_layer_path(layer, "expert") / "on_vs_off" / "dose_response.json")
    assert published(config.eval_root / "pathways.md")
    assert published(config.rollout_layer_path(1) / "summary.md")
    assert publish.staging_files(bucket) == []
    assert not list(machines["cpu"].glob("mirror/**/shard-*.safetensors"))  # slicing read them by ranges
    assert not (tmp_path / "demo").exists()
    assert_equal_to_local_steps(config, cli_steps_run[1])

    # the refresh deployment sees the sources of that successful run: it ends without a pipeline run
    refreshed = run_deployment_and_wait(env, "latent-steering-refresh/scheduled", tmp_path / "logs" / "worker-cpu.log")
    with get_client(sync_client=True) as client:
        pipelines = client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=["latent-steering"])))
        deadline = time.monotonic() + LOG_TIMEOUT
        while True:
            logs = [log.message for log in client.read_logs(
                log_filter=LogFilter(flow_run_id=LogFilterFlowRunId(any_=[refreshed.id])))]
            if any("nothing to do" in message for message in logs):
                break
            assert time.monotonic() < deadline, logs
            time.sleep(1)
    assert refreshed.work_pool_name == "cpu" and [r.id for r in pipelines] == [parent.id]


def assert_equal_to_local_steps(config, local: Path) -> None:
    """Check the run's outputs in the bucket (pulled into this test's mirror) against the seed's steps run locally
    on the same inputs (`cli_steps_run`): shards, slices, statistics and directions byte for byte, JSON equal."""
    publish.pull(config.output_root)
    for pair in config.pairs:
        for ours, theirs in ((config.manifest_path(pair), local / "manifests" / f"{pair.name}.json"),
                             (config.concept_map_path(pair), local / "manifests" / f"{pair.name}_concept_map.json")):
            assert read_json(ours)["segments" if "segments" in read_json(ours) else "concepts"] == read_json(
                theirs)["segments" if "segments" in read_json(theirs) else "concepts"], ours
    for run, name in ((config.run_dir, "demo"), (config.decision_run_dir, "demo_decision")):
        shards = [(r.file, r.sha256) for r in read_run_metadata(run).shards]
        assert shards == [(r.file, r.sha256) for r in read_run_metadata(local / "residuals" / name).shards]
        fs, first = filesystems.object_path(mirrors.url_of(run / shards[0][0]))
        assert hashlib.sha256(fs.cat_file(first)).hexdigest() == shards[0][1]  # the object holds those bytes
    for layer in config.layers:
        for pair in config.pairs:
            slices = config.slices_dir(pair) / layer_dir(layer)
            for file in sorted(p.name for p in (local / "residuals" / f"{pair.name}_slices" / layer_dir(layer)).iterdir()
                               if p.suffix in (".pt", ".safetensors")):
                assert (slices / file).read_bytes() == (
                    local / "residuals" / f"{pair.name}_slices" / layer_dir(layer) / file).read_bytes(), file
            ours, theirs = config.layer_path(layer) / pair.name, local / "latent_steering" / layer_dir(layer) / pair.name
            for stem in ("latent_direction", "residual_direction", "positive_latent_mean", "negative_latent_mean"):
                assert (ours / f"{stem}.safetensors").read_bytes() == (theirs / f"{stem}.safetensors").read_bytes()
        assert (read_json(config.layer_path(layer) / "pairwise_stats.json")["entries"]
                == read_json(local / "latent_steering" / layer_dir(layer) / "pairwise_stats.json")["entries"])


def no_gpu_worker(env: dict[str, str], processes: Processes, tmp_path: Path) -> None:
    """Only the cpu worker runs: the parent gives up on its capture runs after the wait, naming the pool."""
    config_path = build_demo(tmp_path / "demo", demos_per_task=2)
    raw = yaml.safe_load(config_path.read_text())
    raw["orchestration"] = {"poll_seconds": 1, "worker_wait_seconds": 10}
    config_path.write_text(yaml.safe_dump(raw))
    run_cli(env, LATENT_STEERING, "deploy", "--config", str(config_path))
    with get_client(sync_client=True) as client:
        scheduled = next(d for d in client.read_deployments() if d.name == "scheduled")
        client.pause_deployment(scheduled.id)
    processes.start("worker-cpu", *PREFECT, "worker", "start", "--pool", "cpu")

    run = run_deployment_until_final(env, "latent-steering/pipeline", tmp_path / "logs" / "worker-cpu.log")
    with get_client(sync_client=True) as client:
        assert run.state.is_failed()
        assert "no worker is polling pool 'gpu'" in run.state.message, run.state.message
        captures = client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=["latent-steering-capture"])))
        assert captures and {r.state.name for r in captures} == {"Cancelled"}  # never left to start later


def wait_until(check, what: str, timeout: float, log: Path):
    """Poll `check()` every half second until it returns a true value; return that value."""
    deadline = time.monotonic() + timeout
    while not (found := check()):
        assert time.monotonic() < deadline, f"{what} not seen within {timeout:.0f} s:\n{log.read_text()[-3000:]}"
        time.sleep(0.5)
    return found


def capture_runs(client) -> list:
    return client.read_flow_runs(flow_filter=FlowFilter(name=FlowFilterName(any_=["latent-steering-capture"])))


def dying_machines(env: dict[str, str], processes: Processes, tmp_path: Path) -> None:
    """Every root in the bucket, each worker on its own machine. The gpu machine dies with its flow-run processes
    while capture runs are running: the parent marks them Crashed when their heartbeats stopped for a window while
    its own were recorded (flows/heartbeats.py), starts them again on a new gpu machine, and shards published before
    the crash are kept. Then the cpu machine dies, with the parent, as slicing starts: the deploy automation marks the
    silent parent Crashed, and a pipeline run on a new cpu machine finishes the work, starting no capture run (all
    cached in the bucket). Nothing half-written is visible and no staging object is left."""
    name = f"dying-{os.getpid()}-{time.monotonic_ns()}"
    filesystems.filesystem("s3").mkdir(name)
    bucket = f"s3://{name}"

    def edit(raw: dict) -> None:
        # four capture runs; the parent's watch needs no more than its minimum window: its evidence rules out stalls
        raw["orchestration"] = {"shards_per_capture_run": 2, "poll_seconds": 2, "heartbeat_timeout_seconds": 60}
        raw["evaluate"] = raw["rollout"] = None  # what follows slicing is not under test here
        raw["layers"], raw["sae"] = [1], {"1": raw["sae"]["1"] | {"train": None}}  # one layer, no training

    config_url = bucket_demo(tmp_path, bucket, edit)
    logs = tmp_path / "logs"
    run_cli(env, LATENT_STEERING, "deploy", "--config", config_url, "--storage", f"{bucket}/data",
            "--heartbeat-timeout", str(AUTOMATION_WINDOW))
    with get_client(sync_client=True) as client:
        assert [a.trigger.within.total_seconds() for a in client.read_automations_by_name(
            "latent-steering: crash flow runs whose heartbeats stopped")] == [AUTOMATION_WINDOW]
        client.pause_deployment(next(d for d in client.read_deployments() if d.name == "scheduled").id)
    cpu = start_machine(processes, "worker-cpu-1", "cpu", tmp_path / "machine-cpu-1")
    dying = start_machine(processes, "worker-gpu-1", "gpu", tmp_path / "machine-gpu-1")
    output = run_cli(env, *PREFECT, "deployment", "run", "latent-steering/pipeline")
    parent_id = re.search(r"UUID: ([0-9a-f-]{36})", output).group(1)

    def mid_capture():  # all four started, at least one complete and one still running
        with get_client(sync_client=True) as client:
            states = [r.state.name for r in capture_runs(client)]
        return (len(states) == 4 and set(states) <= {"Running", "Completed"} and "Completed" in states
                and "Running" in states)

    wait_until(mid_capture, "capture runs both complete and running", RUN_TIMEOUT, logs / "worker-gpu-1.log")
    kill_machine(dying)
    start_machine(processes, "worker-gpu-2", "gpu", tmp_path / "machine-gpu-2")
    with get_client(sync_client=True) as client:  # nothing can change them now but the parent's heartbeat watch
        before = {r.name: r.state.name for r in capture_runs(client)}
    fs = filesystems.filesystem("s3")
    kept = {path: fs.info(path)["ETag"] for path in bucket_files(f"{bucket}/data/residuals/demo", "**/shard-*.safetensors")}
    assert kept  # the completed capture runs published their shards

    def slicing_started():
        with get_client(sync_client=True) as client:
            return [t for t in client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[parent_id])))
                    if t.name.startswith("slice ") and t.state is not None and t.state.name in ("Running", "Completed")]

    wait_until(slicing_started, "slicing", RUN_TIMEOUT, logs / "worker-cpu-1.log")
    kill_machine(cpu)  # the parent flow dies with it, mid-slice
    start_machine(processes, "worker-cpu-2", "cpu", tmp_path / "machine-cpu-2")
    with get_client(sync_client=True) as client:
        runs = capture_runs(client)
        crashed = [r for r in runs if r.state.name == "Crashed"]
        assert sorted(r.name for r in crashed) == sorted(name for name, state in before.items() if state == "Running")
        assert {"no heartbeat" in r.state.message for r in crashed} == {True}  # marked by the parent's watch
        completed = sorted(r.name for r in runs if r.state.is_completed())
        assert completed == sorted(before)  # each capture run completed once: the first time or on its new attempt
        parent_logs = client.read_logs(log_filter=LogFilter(flow_run_id=LogFilterFlowRunId(any_=[parent_id])))
        messages = [log.message for log in parent_logs]
        assert any("crashed" in m and "starting it again, attempt 2 of 3" in m for m in messages), messages
        # the library's INFO lines (slicing, conversion) reach the run's log under Prefect's logging setup
        assert any(log.name.startswith("steering_core.") and log.level == 20 for log in parent_logs)
    assert {path: fs.info(path)["ETag"] for path in kept} == kept  # shards published before the crash kept

    # the rerun on the new cpu machine finishes, starting no capture run: all are cached in the bucket
    second = run_deployment_and_wait(env, "latent-steering/pipeline", logs / "worker-cpu-2.log")
    with get_client(sync_client=True) as client:
        assert len(capture_runs(client)) == len(runs)
        messages = [log.message for log in client.read_logs(
            log_filter=LogFilter(flow_run_id=LogFilterFlowRunId(any_=[second.id])))]
    assert any("4 of 4 capture run(s) cached: not started" in m for m in messages), messages
    assert len(bucket_files(f"{bucket}/data/residuals/demo", "**/shard-*.safetensors")) == 8
    assert publish.is_published(f"{bucket}/data/latent_steering/layer01/summary.md")
    assert publish.staging_files(bucket) == []
    assert_nothing_half_written(bucket)


def kill_machine(worker: subprocess.Popen) -> None:
    """SIGKILL a worker and every flow-run process it started (they start their own sessions: found first)."""
    family = descendants(worker.pid)
    os.killpg(worker.pid, signal.SIGKILL)
    for pid in family:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


def assert_nothing_half_written(bucket: str) -> None:
    """Every output a record publishes is whole (each file there, with the record's size and ETag), and every
    object under the outputs belongs to a published output, or is a cache record, lock or shared config."""
    fs = filesystems.filesystem("s3")
    listed = set()
    for parent, record in publish.records_under(f"{bucket}/data"):
        for relative, entry in record["files"].items():
            info = fs.info(filesystems.object_path(f"{parent}/{relative}")[1])
            assert (info["size"], info["ETag"]) == (entry["size"], entry["etag"]), (parent, relative)
            listed.add(f"{parent}/{relative}")
    bookkeeping = ("/.prefect-cache/", "/.runs/", "/.locks/")
    stray = [p for p in fs.find(f"{bucket[5:]}/data") if f"s3://{p}" not in listed and not p.endswith(".published.json")
             and not any(part in f"/{p}" for part in bookkeeping)]
    assert stray == [], stray


# test -> the scenario it checks, started in the background by `scenarios` when the test is selected
SCENARIOS = {
    "test_capture_runs_fail_with_a_clear_message_when_no_gpu_worker_polls": no_gpu_worker,
    "test_machines_dying_mid_capture_and_mid_slice_are_recovered_without_a_hand": dying_machines,
}


@pytest.fixture(scope="module", autouse=True)
def scenarios(request, tmp_path_factory, s3_endpoint) -> Iterator[dict[str, Scenario]]:
    """Start the scenario of every selected test of SCENARIOS before this module's first test; yield them by test.

    At the end, wait for each (its server and workers are stopped by then, whatever its test did)."""
    selected = {item.originalname for item in request.session.items if item.module is request.module}
    started = {name: Scenario(body, tmp_path_factory.mktemp(body.__name__)) for name, body in SCENARIOS.items()
               if name in selected}
    for scenario in started.values():
        scenario.start()
    yield started
    for scenario in started.values():
        scenario.join(SCENARIO_TIMEOUT)


def test_capture_runs_fail_with_a_clear_message_when_no_gpu_worker_polls(scenarios):
    """Only the cpu worker runs: the parent gives up on its capture runs after the wait, naming the pool."""
    scenarios["test_capture_runs_fail_with_a_clear_message_when_no_gpu_worker_polls"].result(SCENARIO_TIMEOUT)


@pytest.mark.timeout(SCENARIO_TIMEOUT + 60)
def test_machines_dying_mid_capture_and_mid_slice_are_recovered_without_a_hand(scenarios):
    """The gpu machine dies mid-capture, then the cpu machine mid-slice; the pipeline recovers on new machines
    without a hand, from the bucket alone (see `dying_machines`)."""
    scenarios["test_machines_dying_mid_capture_and_mid_slice_are_recovered_without_a_hand"].result(SCENARIO_TIMEOUT)
