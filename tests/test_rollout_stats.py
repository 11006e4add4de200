"""Wilson intervals (hand-solved values, n = 0, bad counts, coverage) and the exact McNemar test of paired cells."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binomtest

from steering_core.rollout.stats import WILSON_Z, holm, mcnemar, proportion, wilson_interval


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


def test_mcnemar_counts_only_discordant_episodes_hand_computed():
    # a wins episodes 0 and 1, b wins episode 4, both win 2: 3 discordant, P(X >= 2 | 3, 1/2) = (3 + 1) / 8
    test = mcnemar([1, 1, 1, 0, 0], [0, 0, 1, 0, 1])
    assert (test.n, test.both, test.only_a, test.only_b) == (5, 1, 2, 1)
    assert test.p_greater == 0.5 and test.p_two_sided == 1.0  # 2 * min(1/2, 7/8), at most 1
    nine_one = mcnemar([1] * 9 + [0], [0] * 9 + [1])
    assert nine_one.p_greater == 11 / 1024 and nine_one.p_two_sided == 22 / 1024  # (C(10,9) + C(10,10)) / 2^10
    same = mcnemar([1, 0, 1], [1, 0, 1])
    assert (same.only_a, same.only_b, same.p_greater, same.p_two_sided) == (0, 0, 1.0, 1.0)  # no evidence either way


@pytest.mark.parametrize(("only_a", "only_b"), [(7, 0), (12, 3), (3, 12), (20, 20), (0, 5)])
def test_mcnemar_equals_scipys_exact_binomial_test(only_a, only_b):
    a = [True] * only_a + [False] * only_b + [True] * 4
    b = [False] * only_a + [True] * only_b + [True] * 4
    test = mcnemar(a, b)
    assert test.p_greater == pytest.approx(binomtest(only_a, only_a + only_b, 0.5, alternative="greater").pvalue,
                                           rel=1e-12)
    assert test.p_two_sided == pytest.approx(binomtest(only_a, only_a + only_b, 0.5).pvalue, rel=1e-12)


def test_mcnemar_refuses_unpaired_lengths():
    with pytest.raises(ValueError, match="3 and 2 episodes"):
        mcnemar([1, 0, 1], [1, 0])


@pytest.mark.parametrize("n", [10, 20, 50])
def test_coverage_near_95_percent(n):
    p = 0.3
    draws = np.random.default_rng(n).binomial(n, p, size=20_000)
    cover = {k: low <= p <= high for k in range(n + 1) for low, high in [wilson_interval(k, n)]}
    coverage = np.mean([cover[k] for k in draws])
    assert 0.92 <= coverage <= 0.98, coverage  # Wilson's coverage oscillates around 95% with n


def test_holm_multiplies_the_sorted_p_values_and_keeps_them_monotone():
    # sorted 0.01 x 4 = 0.04, 0.03 x 3 = 0.09, 0.04 x 2 = 0.08 -> 0.09 (at least the one before), 0.5 x 1
    assert holm([0.01, 0.04, 0.03, 0.5]) == pytest.approx([0.04, 0.09, 0.09, 0.5], abs=1e-15)
    assert holm([0.6, 0.7]) == [1.0, 1.0] and holm([0.2]) == [0.2] and holm([]) == []
