"""Success counts as proportions with Wilson 95% score intervals (the interval recent VLA steering work reports),
the exact McNemar test of two cells on the same episodes, and Holm's adjustment of a family of p-values.

Wilson's interval solves (p̂ − p)² = z² p(1 − p) / n for p: unlike p̂ ± z·√(p̂(1 − p̂)/n) it stays inside [0, 1]
and does not collapse to a point at 0/n or n/n, which 10-episode cells often give.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch

from steering_core.evaluate.metrics import holm as holm_tensor

WILSON_Z = 1.959963984540054  # the standard normal's 97.5% quantile: a two-sided 95% interval


@dataclass(frozen=True)
class Proportion:
    """`k` successes of `n` episodes: `rate` = k/n (None when n = 0) and its Wilson interval [`low`, `high`].

    With no episodes nothing is known: the interval is the whole [0, 1].
    """

    k: int
    n: int
    rate: float | None
    low: float
    high: float

    def to_json(self) -> dict:
        """Return the JSON-ready dict (k, n, rate, low, high)."""
        return asdict(self)

    def text(self) -> str:
        """Return e.g. `3/10 [0.11, 0.60]`, or `0/0` for no episodes."""
        return f"{self.k}/{self.n}" + ("" if self.n == 0 else f" [{self.low:.2f}, {self.high:.2f}]")


def wilson_interval(k: int, n: int, z: float = WILSON_Z) -> tuple[float, float]:
    """Return the Wilson score interval (low, high) of `k` successes in `n` trials; (0, 1) for n = 0."""
    if isinstance(k, bool) or isinstance(n, bool) or int(k) != k or int(n) != n or not 0 <= k <= n:
        raise ValueError(f"success count {k!r} of {n!r} episodes: expected integers with 0 <= k <= n")
    if n == 0:
        return 0.0, 1.0
    p = k / n
    scale = 1 + z * z / n
    center = (p + z * z / (2 * n)) / scale
    half = z / scale * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    # at k = 0 (k = n) the low (high) end is exactly 0 (1); the formula gives it only up to rounding
    return 0.0 if k == 0 else center - half, 1.0 if k == n else center + half


def proportion(k: int, n: int) -> Proportion:
    """Return `k` of `n` with its rate and Wilson 95% interval."""
    low, high = wilson_interval(k, n)
    return Proportion(int(k), int(n), k / n if n else None, low, high)


@dataclass(frozen=True)
class Paired:
    """Two cells' successes on the same `n` episodes (same initial state and seed): `both` succeeded, `only_a`
    (a succeeded, b failed), `only_b`, and the exact McNemar p-values of the discordant episodes."""

    n: int
    both: int
    only_a: int
    only_b: int
    p_greater: float  # one-sided: P(X >= only_a), X ~ Binomial(only_a + only_b, 1/2): evidence a beats b
    p_two_sided: float

    def to_json(self) -> dict:
        """Return the JSON-ready dict."""
        return asdict(self)


def _binomial_tail(k: int, n: int) -> float:
    """Return P(X >= k) for X ~ Binomial(n, 1/2), exactly (integer counts, one division)."""
    return sum(math.comb(n, i) for i in range(k, n + 1)) / 2**n


def mcnemar(a: Sequence[bool], b: Sequence[bool]) -> Paired:
    """Return the exact McNemar test of paired outcomes `a` and `b` (episode i of each is the same episode).

    Only discordant episodes carry evidence: under "a and b succeed alike" each is a's win with probability
    1/2, so the one-sided p is the binomial tail of a's wins; the two-sided p doubles the smaller tail (at most 1).
    """
    if len(a) != len(b):
        raise ValueError(f"paired outcomes: {len(a)} and {len(b)} episodes, expected the same episodes in both")
    only_a = sum(bool(x) and not bool(y) for x, y in zip(a, b))
    only_b = sum(bool(y) and not bool(x) for x, y in zip(a, b))
    discordant = only_a + only_b
    greater, less = _binomial_tail(only_a, discordant), _binomial_tail(only_b, discordant)
    return Paired(n=len(a), both=sum(bool(x) and bool(y) for x, y in zip(a, b)), only_a=only_a, only_b=only_b,
                  p_greater=greater, p_two_sided=min(1.0, 2 * min(greater, less)))


def holm(p_values: Sequence[float]) -> list[float]:
    """Return Holm's step-down adjusted p-values of a family (same order, each at most 1): the i-th smallest of m
    is multiplied by m − i (i from 0), and each kept at least the one before it."""
    if not p_values:
        return []
    return holm_tensor(torch.tensor(p_values, dtype=torch.float64)).tolist()
