"""Wilson intervals: hand-solved values (the quadratic's roots by numpy), n = 0, bad counts, and coverage."""

from __future__ import annotations

import numpy as np
import pytest

from steering_core.rollout.stats import WILSON_Z, exceeds, proportion, wilson_interval


def roots(k: int, n: int) -> tuple[float, float]:
    """Solve (p̂ − p)² = z² p (1 − p) / n for p: (1 + z²/n) p² − (2p̂ + z²/n) p + p̂² = 0."""
    p, c = k / n, WILSON_Z**2 / n
    low, high = sorted(np.roots([1 + c, -(2 * p + c), p * p]).real)
    return low, high


@pytest.mark.parametrize(("k", "n"), [(0, 10), (10, 10), (5, 10), (1, 3), (7, 50)])
def test_wilson_interval_solves_the_score_equation(k, n):
    np.testing.assert_allclose(wilson_interval(k, n), roots(k, n), rtol=0, atol=1e-12)


def test_known_values_and_edges():
    assert wilson_interval(0, 10)[0] == 0.0 and wilson_interval(10, 10)[1] == 1.0
    assert wilson_interval(0, 10)[1] == pytest.approx(0.27753, abs=1e-5)  # the textbook 0/10 upper bound
    low, high = wilson_interval(5, 10)
    assert low == pytest.approx(1 - high, abs=1e-15) and low == pytest.approx(0.23659, abs=1e-5)


def test_no_episodes_is_the_whole_interval_and_bad_counts_are_refused():
    none = proportion(0, 0)
    assert (none.rate, none.low, none.high, none.text()) == (None, 0.0, 1.0, "0/0")
    assert proportion(3, 10).text() == "3/10 [0.11, 0.60]"
    for k, n in ((3, 2), (-1, 5), (1.5, 4), (True, 2)):
        with pytest.raises(ValueError, match="expected integers with 0 <= k <= n"):
            wilson_interval(k, n)


def test_exceeds_needs_intervals_apart():
    assert exceeds(proportion(9, 10), proportion(0, 10))
    assert not exceeds(proportion(6, 10), proportion(3, 10))  # overlapping: no evidence
    assert not exceeds(proportion(0, 0), proportion(0, 10))


@pytest.mark.parametrize("n", [10, 20, 50])
def test_coverage_near_95_percent(n):
    p = 0.3
    draws = np.random.default_rng(n).binomial(n, p, size=20_000)
    cover = {k: low <= p <= high for k in range(n + 1) for low, high in [wilson_interval(k, n)]}
    coverage = np.mean([cover[k] for k in draws])
    assert 0.92 <= coverage <= 0.98, coverage  # Wilson's coverage oscillates around 95% with n
