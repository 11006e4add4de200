"""Smoke test of the opt-in real-size policy benchmark at its --quick (tiny) size: same code path, tiny checkpoint.

Kept apart from test_bench.py, whose module fixtures start a Prefect server this benchmark does not need.
"""

from __future__ import annotations

import pytest
from test_bench import run_quick  # also puts the repository root on sys.path for `bench`

from bench import policy_real_size  # noqa: E402
from steering_core.synthetic.pi05 import checkpoint_tensor_shapes, tiny_arch


@pytest.mark.slow
def test_policy_real_size_quick_loads_and_acts(tmp_path):
    result = run_quick(policy_real_size, tmp_path / "cache", tmp_path)
    assert result.checks == {"finite": True, "tensors": len(checkpoint_tensor_shapes(tiny_arch())),
                             "expected_tensors": len(checkpoint_tensor_shapes(tiny_arch()))}
    assert result.table[0]["actions"] == [10, 7]


def test_real_layout_has_openpis_812_tensors():
    from steering_core.pi05 import Pi05Arch

    assert len(checkpoint_tensor_shapes(Pi05Arch())) == 812
