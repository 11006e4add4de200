"""Simulation workers (steering_core.rollout.workers): jobs in spawned processes, a dead worker costing only its job,
Ctrl-C and the end of the phase stopping every process, the worker count, and the shared policy failing to start."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from pydantic import ValidationError

from steering_core.rollout import workers as workers_module
from steering_core.rollout.settings import RolloutSettings
from steering_core.rollout.workers import (
    PolicyStartError,
    SimulationWorkers,
    WorkerDied,
    WorkersStopped,
    run_jobs,
    simulation,
    worker_count,
)


def pid_of(_: object = None) -> int:
    return os.getpid()


def die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def job(folder: str, name: str) -> str:
    """Record an attempt in `folder`; the job "dies" kills its worker on its first attempt, "bad" raises, "slow"
    sleeps long, "after-slow" waits until "slow" has started; the others return their name."""
    attempts = len(list(Path(folder).glob(f"{name}.*")))
    Path(folder, f"{name}.{attempts}").write_text(str(os.getpid()))
    if name == "dies" and attempts == 0:
        die()
    if name == "bad":
        raise ValueError("bad job")
    if name == "slow":
        time.sleep(600)
    while name == "after-slow" and not Path(folder, "slow.0").exists():
        time.sleep(0.05)
    return name.upper()


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2]


def wait_gone(pid: int, seconds: float = 60) -> bool:
    """Return True once `pid` has ended (a generous bound for a loaded machine; ending is prompt when it works)."""
    deadline = time.monotonic() + seconds
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not alive(pid)


@pytest.mark.parametrize("count", [0, -1, 257])
def test_a_worker_count_outside_1_to_256_is_one_line(count):
    with pytest.raises(ValidationError) as err:
        RolloutSettings(workers=count)
    assert f"workers {count}: expected 1 to 256 simulation processes" in str(err.value)
    assert RolloutSettings(workers=256).workers == 256 and RolloutSettings().workers is None


def test_the_default_count_is_one_per_core_within_memory_and_chunks(monkeypatch, caplog):
    monkeypatch.setattr(workers_module, "usable_cores", lambda: 16)
    monkeypatch.setattr(workers_module, "available_memory", lambda: 10 * workers_module.WORKER_MEMORY_BYTES + 1)
    assert worker_count(None, 100) == 10  # memory for 10
    assert worker_count(None, 4) == 4     # no more than the chunks
    monkeypatch.setattr(workers_module, "available_memory", lambda: 100 * workers_module.WORKER_MEMORY_BYTES)
    assert worker_count(None, 100) == 16  # cores
    monkeypatch.setattr(workers_module, "available_memory", lambda: 1)
    assert worker_count(None, 100) == 1
    monkeypatch.setattr(workers_module, "available_memory", lambda: None)
    assert worker_count(None, 100) == 16
    with caplog.at_level(logging.WARNING, logger=workers_module.__name__):
        assert worker_count(4, 100) == 4 and not caplog.records
        assert worker_count(32, 100) == 32
    assert "rollout.workers 32 on 16 usable cores" in caplog.text
    assert worker_count(32, 3) == 3


def test_jobs_run_in_reused_worker_processes_and_a_dead_one_is_replaced():
    with SimulationWorkers(1) as workers:
        first = workers.run(pid_of)
        assert first != os.getpid() and workers.run(pid_of) == first and workers.pids() == [first]
        with pytest.raises(WorkerDied, match=rf"process {first}\) died while running die"):
            workers.run(die)
        assert wait_gone(first)
        second = workers.run(pid_of)
        assert second != first and workers.pids() == [second]
    assert wait_gone(second)
    with pytest.raises(WorkersStopped):
        workers.run(pid_of)


def test_a_dead_worker_costs_only_its_job_which_is_retried(tmp_path):
    names = ["a", "dies", "b", "c"]
    done = []
    with SimulationWorkers(2) as workers:
        results = run_jobs(workers, job_in, [(str(tmp_path), name) for name in names],
                           on_done=lambda item, result: done.append(item[1]))
    assert results == ["A", "DIES", "B", "C"]
    assert sorted(done) == sorted(names)
    attempts = {name: len(list(tmp_path.glob(f"{name}.*"))) for name in names}
    assert attempts == {"a": 1, "dies": 2, "b": 1, "c": 1}


def job_in(item: tuple[str, str]) -> str:
    return job(*item)


def test_a_failed_job_is_raised_after_the_running_ones_end(tmp_path):
    with SimulationWorkers(2) as workers, pytest.raises(ValueError, match="bad job"):
        run_jobs(workers, job_in, [(str(tmp_path), "bad"), (str(tmp_path), "a")])
    assert (tmp_path / "a.0").exists() and len(list(tmp_path.glob("bad.*"))) == 1  # not retried


def test_a_worker_that_keeps_dying_fails_its_job_after_the_retries(tmp_path):
    with SimulationWorkers(1) as workers, pytest.raises(WorkerDied):
        run_jobs(workers, die_job, [1], retries=2)


def die_job(_: int) -> None:
    die()


def test_ctrl_c_stops_the_running_jobs_and_their_processes(tmp_path):
    """on_done raises KeyboardInterrupt as the first job ends, while the other (started before it) sleeps for 600 s:
    its worker is killed and run_jobs returns at once."""
    def interrupt(item, result):
        raise KeyboardInterrupt

    with SimulationWorkers(2) as workers:
        with pytest.raises(KeyboardInterrupt):
            run_jobs(workers, job_in, [(str(tmp_path), "slow"), (str(tmp_path), "after-slow")],
                     on_done=interrupt)
        slow_pid = int((tmp_path / "slow.0").read_text())
        assert wait_gone(slow_pid) and workers.pids() == []


def test_workers_die_with_the_process_that_started_them(tmp_path):
    script = textwrap.dedent(f"""
        import sys, time
        sys.path[:0] = {[str(Path(__file__).parent), *sys.path]!r}
        from steering_core.rollout.workers import SimulationWorkers
        from test_rollout_workers import pid_of
        workers = SimulationWorkers(1)
        print(workers.run(pid_of), flush=True)
        time.sleep(600)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    worker = int(parent.stdout.readline())
    assert alive(worker)
    parent.kill()
    parent.wait()
    assert wait_gone(worker)


def test_a_policy_that_cannot_start_stops_the_phase_before_any_worker(monkeypatch, tmp_path):
    def broken(*_):
        raise FileNotFoundError("/models/pi05/model.safetensors: no such file")

    monkeypatch.setattr("steering_core.evaluate.run.load_policy", broken)
    monkeypatch.setattr(workers_module, "usable_cores", lambda: 4)
    started = []
    monkeypatch.setattr(workers_module.SimulationWorkers, "__init__", lambda *a: started.append(a))
    settings = RolloutSettings(workers=2)
    with pytest.raises(PolicyStartError) as err, simulation(settings, SimpleNamespace(model="m"), tmp_path, None, chunks=5):
        pass
    assert str(err.value) == ("rollout: the policy shared by 2 simulation workers did not start: FileNotFoundError: "
                              "/models/pi05/model.safetensors: no such file")
    assert not started


def test_one_worker_or_one_chunk_runs_in_this_process(tmp_path):
    for settings, chunks in ((RolloutSettings(workers=1), 5), (RolloutSettings(workers=4), 1)):
        with simulation(settings, None, tmp_path, "key", chunks) as (workers, same, key):
            assert workers is None and same is settings and key == "key"


def log_line(message: str) -> None:
    logging.getLogger("steering_core.rollout.test").info(message)
    logging.getLogger("steering_core.rollout.test").debug("not at INFO")


def test_a_worker_logs_on_stderr_at_the_level_of_its_parent(capfd):
    library = logging.getLogger("steering_core")
    level = library.level
    library.setLevel(logging.INFO)
    try:
        with SimulationWorkers(1) as workers:
            workers.run(log_line, "hello")
            pid = workers.pids()[0]
    finally:
        library.setLevel(level)
    err = capfd.readouterr().err
    assert f"| INFO    | worker {pid} | steering_core.rollout.test - hello" in err
    assert "not at INFO" not in err
