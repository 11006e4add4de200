"""Output and shard-group locks between processes: no false deadlock, no overlap, no stale lock; and two
`latent-steering run --config X` started together on one root, each output computed once."""

from __future__ import annotations

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

import pytest
import yaml
from helpers_locks import hold_output_lock, python

from steering_core.demo import build_demo
from steering_core.remote.locks import group_locks, output_lock
from tasks.cache_records import CACHE_DIR

LATENT_STEERING = str(Path(sys.executable).parent / "latent-steering")  # the console script of this venv

# Holds `mine` in a thread; on "go" asks for `theirs` in the main thread while still holding `mine`; on
# "release" (read by a third thread) lets `mine` go. Two of these, crossed, wait on each other's outputs.
CROSSED = """
import sys, threading
from steering_core.remote.locks import output_lock
mine, theirs = sys.argv[1:]
held, release = threading.Event(), threading.Event()
def hold():
    with output_lock(mine):
        held.set()
        release.wait()
holder = threading.Thread(target=hold)
holder.start()
held.wait()
print('holding', flush=True)
sys.stdin.readline()
threading.Thread(target=lambda: (sys.stdin.readline(), release.set())).start()
with output_lock(theirs):
    print('took', flush=True)
holder.join()
"""

# Takes the shard groups argv[2:] of run folder argv[1] 20 times, logging start and end of each hold.
GROUPS = """
import os, sys, time
from steering_core.remote.locks import group_locks
run_dir, groups = sys.argv[1], [int(g) for g in sys.argv[2:]]
for _ in range(20):
    with group_locks(run_dir, groups):
        with open(os.path.join(run_dir, 'log'), 'a') as log:
            log.write(f'start {os.getpid()}\\n')
        time.sleep(0.005)
        with open(os.path.join(run_dir, 'log'), 'a') as log:
            log.write(f'end {os.getpid()}\\n')
"""


def test_two_processes_whose_threads_wait_on_each_others_outputs_both_finish(tmp_path):
    """Process A holds X and asks for Y, process B holds Y and asks for X, each from another thread than the
    one holding. Not a deadlock (the holding threads let go later), but per-process record locks saw a cycle and
    failed one wait with EDEADLK ("Resource deadlock avoided")."""
    x, y = tmp_path / "out" / "x", tmp_path / "out" / "y"
    procs = [python(CROSSED, str(x), str(y)), python(CROSSED, str(y), str(x))]
    for proc in procs:
        assert proc.stdout.readline().strip() == "holding"
    tell(procs, "go")
    time.sleep(2)  # both main threads are now waiting on the other's output
    assert [proc.poll() for proc in procs] == [None, None], [proc.communicate() for proc in procs]
    tell(procs, "release")
    results = [proc.communicate(timeout=60) for proc in procs]
    assert [proc.returncode for proc in procs] == [0, 0], results
    assert [out.strip() for out, _ in results] == ["took", "took"], results
    assert [p.name for p in tmp_path.rglob("*") if p.is_file()] == []  # no output written: no lock file left


def tell(procs, line: str) -> None:
    """Send `line` to every process."""
    for proc in procs:
        proc.stdin.write(line + "\n")
        proc.stdin.flush()


def test_groups_asked_for_in_opposite_orders_never_overlap_or_deadlock(tmp_path):
    """Three processes take shard groups 1 and 2 (asked for as [1, 2], [2, 1], [2, 1]) 20 times each: every
    hold is alone (start and end of one process follow each other) and all finish. The lock files are
    removed at each release, so waiters on a removed file must notice it and lock the path afresh."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    procs = [python(GROUPS, str(run_dir), *groups) for groups in (("1", "2"), ("2", "1"), ("2", "1"))]
    results = [proc.communicate(timeout=120) for proc in procs]
    assert [proc.returncode for proc in procs] == [0, 0, 0], results
    lines = (run_dir / "log").read_text().split()
    events = list(zip(lines[::2], lines[1::2], strict=True))
    assert len(events) == 120
    for start, end in zip(events[::2], events[1::2], strict=True):
        assert start[0] == "start" and end == ("end", start[1]), events
    assert sorted(p.name for p in run_dir.iterdir()) == ["log"]  # no lock file left behind


def test_a_killed_holder_leaves_no_lock_behind(tmp_path):
    """kill -9 of the holder ends its lock: the next caller gets it at once."""
    output = tmp_path / "data" / "out"
    holder = hold_output_lock(output)
    holder.send_signal(signal.SIGKILL)
    holder.wait(timeout=30)
    waiter = threading.Thread(target=_take_and_release, args=(output,))
    waiter.start()
    waiter.join(timeout=10)
    assert not waiter.is_alive(), "the killed holder's lock outlived it"


FORKS = """
import os, sys, time
from steering_core.remote.locks import output_lock
with output_lock(sys.argv[1]):
    child = os.fork()
    if child == 0:
        time.sleep(120)
        os._exit(0)
    print(child, flush=True)
    sys.stdin.readline()
"""


def test_a_forked_child_does_not_keep_its_parents_lock(tmp_path):
    """A child forked while the lock is held (a data-loader worker, say) outlives its killed parent: the lock
    still ends with the parent."""
    output = tmp_path / "out"
    parent = python(FORKS, str(output))
    child = int(parent.stdout.readline())
    try:
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
        os.kill(child, 0)  # still alive
        waiter = threading.Thread(target=_take_and_release, args=(output,))
        waiter.start()
        waiter.join(timeout=10)
        assert not waiter.is_alive(), "the forked child kept the lock"
    finally:
        os.kill(child, signal.SIGKILL)


def _take_and_release(output) -> None:
    with output_lock(output):
        pass


def test_a_lock_out_of_order_is_refused_not_waited_for(tmp_path):
    """A folder before what it holds: the other way round (or the same output twice) raises at once."""
    folder = tmp_path / "layer01"
    with output_lock(folder), output_lock(folder / "concept.json"):  # in order
        pass
    with output_lock(folder / "concept.json"):
        with pytest.raises(RuntimeError, match=r"lock order: .*layer01.* requested while holding .*concept.json"):
            with output_lock(folder):
                pass
        with pytest.raises(RuntimeError, match="lock order"):
            with output_lock(folder / "concept.json"):
                pass
    with output_lock(folder):  # the refused attempts left nothing held
        with group_locks(tmp_path / "run", [2, 1]):
            pass


def start_run(config: Path, api_url: str, log: Path) -> subprocess.Popen:
    """Start `latent-steering run --config` on the shared Prefect server, its output (merged) into `log`."""
    with open(log, "w") as out:
        return subprocess.Popen([LATENT_STEERING, "run", "--config", str(config)], stdout=out, stderr=subprocess.STDOUT,
                                env=os.environ | {"PREFECT_API_URL": api_url}, cwd=config.parent)


def finish(runs: list[tuple[subprocess.Popen, Path]]) -> list[str]:
    """Wait for every run; return their logs (each must have succeeded)."""
    logs = []
    for proc, log in runs:
        proc.wait(timeout=1800)
        logs.append(log.read_text())
        assert proc.returncode == 0, logs[-1][-3000:]
    return logs


def computed(logs: list[str]) -> dict[str, list[str]]:
    """Return, per locked step, what the runs' logs say they computed (one entry per output written)."""
    text = "\n".join(logs)
    groups = {kind: sum(int(n) for n in re.findall(rf"\[capture {kind}episodes [^]]*\]: [^:]*: (\d+) shard group", text))
              for kind in ("", "decision ")}
    return {
        "convert": re.findall(r"libero_demo_lerobot: (created|rebuilt|appended)", text),
        "capture": [f"{kind or 'main '}{n}" for kind, n in groups.items()],
        "slice": sorted(re.findall(r"wrote \d+ concept slices to (\S+)", text)),
        "encode": sorted(re.findall(r"concept_stats: (.+): \d+ rows", text)),
        "evaluate": sorted(re.findall(r"dose-response of \d+ directions on \d+ frames in (\S+)", text)),
        "train": sorted(re.findall(r"(\S+): trained in [\d.]+ s", text)),
    }


def tree(root: Path) -> dict[str, bytes]:
    """Return every file under `root` (relative path -> bytes)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_two_runs_started_together_compute_each_output_once(prefect_server, tmp_path):
    """The issue's trial: two `run --config X` at once. Neither fails (no "Resource deadlock avoided"), every
    output is computed by one of them (the other waits, then reuses it: evaluations included), and the root holds
    the same bytes as after a single run."""
    config = yaml.safe_load(build_demo(tmp_path / "demo", demos_per_task=2).read_text())
    del config["rollout"]  # LIBERO's closed loop is not locked output; it would only add minutes
    # one layer and no expert pathway: every kind of locked step still runs, in a third of the time
    config["layers"], config["sae"] = [1], {"1": config["sae"]["1"]}
    config["evaluate"]["expert_layers"] = []
    config_path = tmp_path / "demo" / "two_runs.yaml"
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    root = Path(config["output_root"])

    single = computed(finish([(start_run(config_path, prefect_server, tmp_path / "single.log"), tmp_path / "single.log")]))
    assert len(single["evaluate"]) == 2 and len(single["encode"]) == 4  # 2 pairs (x 2 concepts)
    assert len(single["train"]) == 1  # layer 1's SAE, trained on the run's residuals
    alone = tree(root)
    shutil.rmtree(root)

    logs = finish([(start_run(config_path, prefect_server, tmp_path / f"run{i}.log"), tmp_path / f"run{i}.log")
                   for i in (1, 2)])
    assert not any("Resource deadlock" in log or "Traceback" in log for log in logs)
    # each output once, whichever run computed it; whether the other run waited on a lock ("already holds this
    # evaluation; reused") or found the output already cached depends on the machine's timing, so either passes
    assert computed(logs) == single
    together = tree(root)
    assert together.keys() == alone.keys()
    # the same task records (same cache keys); their summaries say what each run did there (a dataset created or
    # found unchanged, shard groups written or skipped), so the outputs are what is compared byte for byte
    records = {name for name in alone if name.startswith(f"{CACHE_DIR}/")}
    differ = sorted(name for name in alone.keys() - records if alone[name] != together[name])
    # meta/stats.json changes key order on every convert (issue 26 item 8, fixed with the inputs): same content
    assert [name for name in differ if not name.endswith("meta/stats.json")] == []
    assert all(json.loads(alone[name]) == json.loads(together[name]) for name in differ)
