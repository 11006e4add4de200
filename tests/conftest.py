"""Session-wide test settings: one intra-op thread per process, offline hub access, quiet telemetry, a private digest
cache, the modules' order, one Prefect server, the S3 endpoint, and the runs several test modules read."""

import os
import tempfile

# One thread for torch (OpenMP, MKL), numpy (OpenBLAS) and MuJoCo's software renderer (llvmpipe), set before they
# are imported, here and in every subprocess a test starts: the suite runs on two pytest-xdist workers
# (pyproject.toml), and two processes each spinning two OpenMP threads on two cores used 1.2x the CPU time (3,208 s
# against 2,604). Every process of a test agrees on the count, so float32 bits compared across processes agree.
for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "LP_NUM_THREADS"):
    os.environ.setdefault(variable, "1")

import pytest  # noqa: E402
from helpers_s3 import bucket, s3_endpoint  # noqa: E402, F401  the S3 endpoint fixtures

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
# large files' digests are remembered across processes; tests keep theirs out of the user cache
os.environ.setdefault("LATENT_STEERING_DIGEST_CACHE", tempfile.mkdtemp(prefix="latent-steering-digests-"))


# The longest modules, first (with --no-loadscope-reorder, xdist hands modules out in this order), so that the two
# workers finish together instead of one starting the server deployments when the other is nearly done.
LONGEST_FIRST = ("test_server_deployments.py", "test_flows.py", "test_bench.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the modules: the longest first, then those holding `slow` tests, then the rest; within a module, and
    otherwise, the collection order stays."""
    slow_modules = {item.path for item in items if item.get_closest_marker("slow")}

    def rank(item: pytest.Item) -> int:
        name = item.path.name
        if name in LONGEST_FIRST:
            return LONGEST_FIRST.index(name)
        return len(LONGEST_FIRST) + (item.path not in slow_modules)

    items.sort(key=rank)


def pytest_terminal_summary(terminalreporter) -> None:
    """Say which database the tests' own Prefect servers used (tests/test_server_deployments.py), under -q too."""
    from helpers_prefect_db import backend

    ran = [report for reports in terminalreporter.stats.values() for report in reports
           if getattr(report, "nodeid", "").startswith("tests/test_server_deployments.py")]
    if ran:
        terminalreporter.write_line(f"Prefect servers started by tests/test_server_deployments.py: {backend()}")


@pytest.fixture(autouse=True)
def torch_threads_put_back():
    """Fail a test that leaves torch on another intra-op thread count: the float32 bits of what runs after it in this
    process depend on the count (a benchmark that left one thread once made the session's CLI steps write other
    decision rows than a worker's)."""
    import torch

    before = torch.get_num_threads()
    yield
    assert torch.get_num_threads() == before, f"the test left torch on {torch.get_num_threads()} threads, not {before}"


@pytest.fixture(scope="session")
def prefect_server():
    """One Prefect test server for the whole session, started when the first test that needs it runs.

    Yields its API URL, which subprocesses get as PREFECT_API_URL instead of starting their own embedded
    server (each start took up to 90 s on a loaded 2-core machine).
    """
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=300):
        yield PREFECT_API_URL.value()


@pytest.fixture(scope="session")
def attack_world(tmp_path_factory):
    """The finished tiny run the bad-input table attacks (`helpers_attack`); built once, never changed."""
    from helpers_attack import make_world

    return make_world(tmp_path_factory.mktemp("attack"))


@pytest.fixture(scope="session")
def cli_steps_run(tmp_path_factory):
    """The demo inputs (2 demos per task) and the seed's steps run on them one by one through the CLI
    (`helpers_pipeline.run_cli_steps`), once for the session (a worker); return (run config, output folder). Read
    only: the demo flow and the deployment run compare their outputs with it."""
    from helpers_pipeline import run_cli_steps

    from steering_core.config import load_run_config
    from steering_core.demo import build_demo

    root = tmp_path_factory.mktemp("cli_steps")
    config = load_run_config(build_demo(root / "demo", demos_per_task=2))
    run_cli_steps(config, root / "out")
    return config, root / "out"
