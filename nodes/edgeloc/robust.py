"""The median of a small window, as `np.median` gives it, in plain Python.

The learner's robust fit (bandit and change detector) and the fusion's robust scale take medians
of a few dozen numbers for every answer; numpy's per-call cost on so few was most of a replay's
time. The answers are the same bit for bit: the middle value, or the mean of the middle two
(their sum halved, as numpy's mean of two does), and NaN if any value is NaN.
"""

from __future__ import annotations

import math
from collections.abc import Iterable


def median(values: Iterable[float]) -> float:
    """The median of `values` (NaN for none, or if any is NaN)."""
    s = sorted(values)
    n = len(s)
    if n == 0 or any(v != v for v in s):
        return math.nan
    mid = n // 2
    return s[mid] if n % 2 else (s[mid - 1] + s[mid]) / 2
