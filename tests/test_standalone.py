"""The tests stand alone: every fixture they read lives inside the repository."""

import re
from pathlib import Path

from reference_formats import FORMATS

TESTS = Path(__file__).resolve().parent


def test_reference_formats_live_in_tests():
    assert FORMATS.resolve().is_relative_to(TESTS)
    for name in ("open_vs_close.json", "open_vs_close_concept_map.json", "layer12_pairs.json"):
        assert (FORMATS / name).is_file(), name


def test_no_test_module_reaches_outside_the_repository():
    # `shared/` beside the checkout exists only on the research machine; a fresh clone has no such folder
    escaping = re.compile(r"__file__\).*parents\[[2-9]\]|\.\./shared|/work/shared")
    offenders = [p.name for p in TESTS.glob("*.py") if p.name != Path(__file__).name and escaping.search(p.read_text())]
    assert offenders == []


def test_prefect_tests_share_one_server():
    """Only conftest.py starts a Prefect test server; modules and their subprocesses use it."""
    starting = [p.name for p in TESTS.glob("*.py") if p.name != Path(__file__).name and "prefect_test_harness(" in p.read_text()]
    assert starting == ["conftest.py"]
    assert "PREFECT_API_URL" in (TESTS / "test_bench.py").read_text()
