"""Success counts as proportions with Wilson 95% score intervals (the interval recent VLA steering work reports).

Wilson's interval solves (p̂ − p)² = z² p(1 − p) / n for p: unlike p̂ ± z·√(p̂(1 − p̂)/n) it stays inside [0, 1]
and does not collapse to a point at 0/n or n/n, which 10-episode cells often give.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

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


def exceeds(a: Proportion, b: Proportion) -> bool:
    """Return True when `a`'s interval lies wholly above `b`'s (no overlap): evidence that a's rate is higher."""
    return a.n > 0 and b.n > 0 and a.low > b.high
