"""Every core simulating: the rollout phase's chunks in worker processes, one policy for all of them.

`SimulationWorkers(count)` runs chunks in up to `count` spawned processes at once. Each worker is a one-process
`ProcessPoolExecutor` (the standard library's engine: spawn, pickling, a dead process noticed as
`BrokenProcessPool`), reused for the chunks it runs; a shared `ProcessPoolExecutor(count)` would not do, since one
dead process breaks that whole pool and every chunk running in it. Here a worker that dies (a MuJoCo crash,
kill -9) costs only its chunk: `run` raises `WorkerDied` and the next chunk gets a fresh process. Workers ignore
Ctrl-C (the phase's process stops them) and die with it (Linux parent-death signal).

`shared_policy` loads π0.5 once in this process and serves it to the workers from a thread: the batching
`PolicyServer` on 127.0.0.1 with a fresh API key, so concurrent replans of every worker share one policy call.

`run_jobs` runs a list of jobs on the workers from a thread each (the `rollout` command; the flow uses Prefect's
thread task runner and retries instead), retrying a job whose worker died.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import secrets
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from steering_core.devices import usable_cores
from steering_core.processes import children_ignore_ctrl_c, die_with_parent, ignore_ctrl_c

if TYPE_CHECKING:
    from steering_core.capture import CaptureSettings
    from steering_core.rollout.settings import RolloutSettings

logger = logging.getLogger(__name__)

T = TypeVar("T")

MAX_WORKERS = 256
# Peak resident memory of one simulation worker: 5.4 GB (RSS, shared pages included) running the default chunk of 5
# lockstep envs (bench.rollout_throughput, BENCHMARKS.md §12): LIBERO, MuJoCo, robosuite, torch's import and the
# scenes. The default worker count leaves room for this much per worker in the memory the machine has available.
WORKER_MEMORY_BYTES = 6 * 2**30
CHUNK_RETRIES = 2  # attempts after the first of a chunk whose worker died (the flow's task retries, the same)
# The shared server's own limits: its clients are this phase's workers, whose env resets and scene builds leave a
# connection quiet for minutes, and whose batched calls of the real model on the CPU can take that long too.
SHARED_TIMEOUT_S = 3600.0
ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "LP_NUM_THREADS": "1"}


class WorkerDied(RuntimeError):
    """A simulation worker process ended while running a job (crashed or killed)."""


class WorkersStopped(RuntimeError):
    """The simulation workers were stopped (the phase ends: Ctrl-C or a failure); jobs are not retried."""


class PolicyStartError(RuntimeError):
    """The policy the workers share could not be loaded or served."""


def available_memory() -> int | None:
    """Return the bytes of memory the machine has available (Linux MemAvailable), or None when unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def worker_count(requested: int | None, chunks: int) -> int:
    """Return how many workers run `chunks` chunks: `requested`, or one per usable core within the available
    memory (WORKER_MEMORY_BYTES each); never more than the chunks. Warns when `requested` exceeds the cores."""
    cores = usable_cores()
    if requested is None:
        memory = available_memory()
        by_memory = max(1, memory // WORKER_MEMORY_BYTES) if memory is not None else cores
        requested = min(cores, by_memory)
    elif requested > cores:
        logger.warning("rollout.workers %d on %d usable cores: the workers share the cores, each chunk runs slower, "
                       "and more than one worker per core adds nothing", requested, cores)
    return max(1, min(requested, chunks))


def _start_worker(level: int) -> None:
    """Set up a worker process: Ctrl-C is the parent's to handle, die with the parent, one thread per library, and
    steering_core's log lines at the parent's `level` on the shared stderr, marked with the worker's process id."""
    ignore_ctrl_c()
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s.%(msecs)03d | %(levelname)-7s | worker %(process)d | "
                                           "%(name)s - %(message)s", datefmt="%H:%M:%S"))
    root = logging.getLogger("steering_core")
    root.addHandler(handler)
    root.setLevel(level)
    die_with_parent()
    os.environ.update(ONE_THREAD)


class SimulationWorkers:
    """Up to `count` worker processes running jobs; a context manager that stops them all on exit."""

    def __init__(self, count: int) -> None:
        if not 1 <= count <= MAX_WORKERS:
            raise ValueError(f"workers {count}: expected 1 to {MAX_WORKERS} simulation processes")
        self.count = count
        self._idle: queue.SimpleQueue[ProcessPoolExecutor | None] = queue.SimpleQueue()
        for _ in range(count):
            self._idle.put(None)  # started on entry (`with`), else on first use
        self._started: dict[ProcessPoolExecutor, int] = {}  # executor -> its process id
        self._lock = threading.Lock()
        self._closed = False

    def __enter__(self) -> SimulationWorkers:
        """Start every worker now, from this thread: from the main one, they ignore Ctrl-C from exec on
        (`processes.children_ignore_ctrl_c`), not only once their start-up imports are done (`_start_worker`); a
        worker that dies while starting is started again on first use."""
        spawned = [self._spawn() for _ in range(self.count)]
        try:
            for executor, started in spawned:
                self._idle.get()  # a slot with no process yet (None): it gets this one
                try:
                    self._idle.put(self._ready(executor, started))
                except WorkerDied:
                    self._idle.put(None)
        except BaseException:
            self.close()
            for executor, _ in spawned:
                executor.shutdown(wait=False, cancel_futures=True)
            raise
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def _spawn(self) -> tuple[ProcessPoolExecutor, Future[int]]:
        """Start a worker process; return its executor and the future of its process id."""
        executor = ProcessPoolExecutor(1, mp_context=get_context("spawn"), initializer=_start_worker,
                                       initargs=(logging.getLogger("steering_core").getEffectiveLevel(),))
        with children_ignore_ctrl_c():  # the process starts here; its imports run after
            return executor, executor.submit(os.getpid)

    def _ready(self, executor: ProcessPoolExecutor, started: Future[int]) -> ProcessPoolExecutor:
        """Return the executor of a spawned worker once it runs (WorkerDied if it ended while starting)."""
        try:
            pid = started.result()
        except BrokenProcessPool:
            executor.shutdown(wait=True, cancel_futures=True)
            raise WorkerDied("a simulation worker process ended while starting") from None
        with self._lock:
            self._started[executor] = pid
            closed = self._closed  # closed while it started
        if closed:
            self._stop(executor)
            raise WorkersStopped("simulation workers stopped")
        return executor

    def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Return fn(*args) computed in a worker process (waiting for a free worker); raise WorkerDied if that
        process ended meanwhile (its replacement starts with the next job)."""
        executor = self._idle.get()
        try:
            if self._closed:
                raise WorkersStopped("simulation workers stopped")
            executor = executor or self._ready(*self._spawn())
            try:
                return executor.submit(fn, *args).result()
            except BrokenProcessPool:
                pid = self._started.get(executor)
                self._stop(executor)
                executor = None
                if self._closed:
                    raise WorkersStopped("simulation workers stopped") from None
                raise WorkerDied(f"simulation worker (process {pid}) died while running {_describe(fn, args)}; "
                                 "its job is lost, the others go on") from None
        finally:
            self._idle.put(executor)

    def pids(self) -> list[int]:
        """Return the process ids of the workers running now."""
        with self._lock:
            return list(self._started.values())

    def _stop(self, executor: ProcessPoolExecutor) -> None:
        """Kill `executor`'s process and shut it down, once: close() and the job that saw it die may both get here,
        and two concurrent shutdowns close its result queue twice (EBADF)."""
        with self._lock:
            pid = self._started.pop(executor, None)
        if pid is None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
        executor.shutdown(wait=True, cancel_futures=True)

    def close(self) -> None:
        """Stop every worker now (a job running in one fails with WorkerDied); no process is left behind."""
        with self._lock:
            self._closed = True
            executors = list(self._started)
        for executor in executors:
            self._stop(executor)


def _describe(fn: Callable, args: Sequence[Any]) -> str:
    """Return the job's `label` (a RolloutJob's), else the function's name."""
    return getattr(args[0] if args else None, "label", None) or getattr(fn, "__name__", repr(fn))


def run_jobs(workers: SimulationWorkers, fn: Callable[..., T], jobs: Sequence[Any], *args: Any,
             on_done: Callable[[Any, T], None] | None = None, retries: int = CHUNK_RETRIES) -> list[T]:
    """Return [fn(job, *args) for job in jobs], computed on `workers` (one thread per worker feeding them); a job
    whose worker died is run again up to `retries` times. `on_done(job, result)` is called in this thread as each
    job ends. The first failure is raised once the jobs already running have ended (Ctrl-C: `workers` is closed
    first, which ends them)."""
    def attempt(job: Any) -> T:
        for tries_left in range(retries, -1, -1):
            try:
                return workers.run(fn, job, *args)
            except WorkerDied as err:
                if tries_left == 0:
                    raise
                logger.warning("%s; retrying (%d attempt(s) left)", err, tries_left)
        raise AssertionError("unreachable")

    results: dict[int, T] = {}
    with ThreadPoolExecutor(workers.count, thread_name_prefix="rollout-worker") as pool, stop_on_interrupt(workers):
        futures = {pool.submit(attempt, job): index for index, job in enumerate(jobs)}
        try:
            for future in as_completed(futures):
                index = futures[future]
                results[index] = future.result()
                if on_done is not None:
                    on_done(jobs[index], results[index])
        except BaseException:
            for future in futures:
                future.cancel()
            raise
    return [results[index] for index in range(len(jobs))]


@contextlib.contextmanager
def stop_on_interrupt(workers: SimulationWorkers | None) -> Iterator[None]:
    """Close `workers` at once when the block ends by Ctrl-C (or another non-Exception), so the jobs running on
    them end now rather than being waited for; a failed job leaves the others running to their end."""
    try:
        yield
    except Exception:
        raise
    except BaseException:
        if workers is not None:
            workers.close()
        raise


@contextlib.contextmanager
def shared_policy(settings: RolloutSettings, model: CaptureSettings, vectors_root: Path,
                  workers: int) -> Iterator[tuple[RolloutSettings, str]]:
    """Load the in-process policy of `settings` once and serve it on 127.0.0.1 from a thread while the block runs;
    yield the settings pointing at it and its fresh API key. Raises PolicyStartError naming the cause when the
    model cannot be loaded or the server cannot listen."""
    from steering_core.evaluate.run import load_policy
    from steering_core.serve import PolicyServer, SteeredPi05Policy, VectorCatalog
    from steering_core.serve.server import DEFAULT_MAX_CONNECTIONS, serving_in_thread

    api_key = secrets.token_urlsafe(32)
    with contextlib.ExitStack() as stack:
        try:
            policy = load_policy(model.model, settings.device, settings.dtype, settings.compiled)
            catalog = VectorCatalog.scan(vectors_root) if vectors_root.is_dir() else VectorCatalog()
            server = PolicyServer(SteeredPi05Policy(policy, noise_seed=settings.noise_seed), catalog,
                                  host="127.0.0.1", port=0, api_key=api_key, max_alpha=float("inf"),
                                  max_connections=max(DEFAULT_MAX_CONNECTIONS, workers),
                                  inference_timeout_s=SHARED_TIMEOUT_S, idle_timeout_s=SHARED_TIMEOUT_S)
            served = stack.enter_context(serving_in_thread(server))
        except Exception as err:
            raise PolicyStartError(f"rollout: the policy shared by {workers} simulation workers did not start: "
                                   f"{type(err).__name__}: {err}") from err
        logger.info("rollout: %d simulation workers share one policy, served at ws://127.0.0.1:%d", workers,
                    served.port)
        yield settings.model_copy(update={"policy": f"ws://127.0.0.1:{served.port}"}), api_key



@contextlib.contextmanager
def simulation(settings: RolloutSettings, model: CaptureSettings, vectors_root: Path, api_key: str | None,
               chunks: int) -> Iterator[tuple[SimulationWorkers | None, RolloutSettings, str | None]]:
    """Yield (workers, settings, api key) to run `chunks` chunks with: no workers (in this process, as given) when
    one is enough, else `worker_count` workers reaching the policy of `settings` (the shared one for "local")."""
    count = worker_count(settings.workers, chunks)
    if count == 1:
        yield None, settings, api_key
        return
    logger.info("rollout: %d chunks on %d simulation workers (%d usable cores)", chunks, count, usable_cores())
    with contextlib.ExitStack() as stack:
        if settings.policy == "local":
            settings, api_key = stack.enter_context(shared_policy(settings, model, vectors_root, count))
        yield stack.enter_context(SimulationWorkers(count)), settings, api_key
