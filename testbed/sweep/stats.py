"""Seeds and statistics of a sweep: the seed of each repetition, and each metric's mean with
its 95% confidence interval across the repetitions of one variant.

A variant run with `--seeds N` is repeated with the scenario's seed, then seed+1, ... seed+N-1
(`derived_seed`): every random choice of a run (the synthetic world, loss and jitter draws, the
DNN's corrupted requests) follows its seed, so the N rows of a variant differ only by chance.
`mean_ci` is the Student-t interval of the mean of N values (t quantile of N-1 degrees of
freedom, `t975`); `output.across_seeds` pools the rows of each (variant, vehicle) into those
figures for the report.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

#: The 97.5% quantile of Student's t for 1..30 degrees of freedom (a two-sided 95% interval).
_T975 = (
    12.7062, 4.3027, 3.1824, 2.7764, 2.5706, 2.4469, 2.3646, 2.3060, 2.2622, 2.2281,
    2.2010, 2.1788, 2.1604, 2.1448, 2.1314, 2.1199, 2.1098, 2.1009, 2.0930, 2.0860,
    2.0796, 2.0739, 2.0687, 2.0639, 2.0595, 2.0555, 2.0518, 2.0484, 2.0452, 2.0423,
)  # fmt: skip
_Z975 = 1.959963984540054
#: The seeds a sweep may repeat each variant with.
MAX_SEEDS = 100


def derived_seed(base: int, repetition: int) -> int:
    """The seed of repetition `repetition` (0: the scenario's own) of a variant."""
    return (base + repetition) % 2**32


def t975(df: int) -> float:
    """Student's t 97.5% quantile: the table up to 30 degrees of freedom, then the
    Cornish-Fisher expansion around the normal quantile (error below 1e-4 there)."""
    if df < 1:
        raise ValueError(f"degrees of freedom must be >= 1, got {df}")
    if df <= len(_T975):
        return _T975[df - 1]
    z = _Z975
    return (
        z
        + (z**3 + z) / (4 * df)
        + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * df**3)
    )


def mean_ci(values: Sequence[float | None]) -> dict[str, Any] | None:
    """{mean, ci95 (half width; None for one value), n, values} of the finite values."""
    xs = [float(x) for x in values if x is not None and math.isfinite(x)]
    if not xs:
        return None
    n = len(xs)
    mean = sum(xs) / n
    half = None
    if n > 1:
        sd = math.sqrt(sum((x - mean) ** 2 for x in xs) / (n - 1))
        half = t975(n - 1) * sd / math.sqrt(n)
    return {"mean": mean, "ci95": half, "n": n, "values": xs}
