"""The paper's premise across drives: does a faster split give lower error in expectation, and
on which drives does it show?

`compare.SplitComparison` judges one drive: in each bandwidth phase, are the fixed splits, ordered
by latency, ordered by error too? That is a noisy yes or no. This module pools many drives of
one scenario (different seeds: other streets, light, VO biases) and asks it of each pair of
splits adjacent in latency in a phase, in expectation: per drive, d = (the slower split's mean
error) − (the faster's), > 0 being the premise's order; the mean of d over the drives, with
Student's 95% interval, says whether the premise holds on average (`PairEffect.verdict`: the
interval above 0), is reversed (below 0) or cannot be told from these drives (across 0). The
learned run against each fixed split the same way (`LearnedEffect`): per drive, the fixed
split's total error over the learned run's, minus one (> 0: learning paid).

What makes drives differ is measurable on each drive: `path_scale_error`, the VO's path length
over ground truth's, minus one. A DNN answer is worth what the VO drifted since the last one;
on a drive whose VO barely drifts, a faster split's extra answers mostly add the DNN's noise.

Pure numpy/scipy, no ROS; `tests/bench/bench_premise.py` prints it for many seeds.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from nodes.edgeloc.compare import SplitComparison


def _mean_ci(values: Sequence[float]) -> tuple[float, float]:
    """Mean and the half-width of Student's 95% interval (inf with fewer than 2 values)."""
    x = np.asarray(values, dtype=np.float64)
    if len(x) < 2:
        return (float(x.mean()) if len(x) else math.nan), math.inf
    half = scipy.stats.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x))
    return float(x.mean()), float(half)


def _verdict(mean: float, half: float) -> str:
    if mean - half > 0:
        return "holds"
    if mean + half < 0:
        return "reversed"
    return "undecided"


@dataclass(frozen=True)
class PairEffect:
    """Phase j, two splits adjacent in latency: per drive the slower one's mean error minus the
    faster one's (m)."""

    phase: int
    faster: str
    slower: str
    diffs_m: tuple[float, ...]

    @property
    def drives(self) -> int:
        return len(self.diffs_m)

    @property
    def mean_m(self) -> float:
        return _mean_ci(self.diffs_m)[0]

    @property
    def ci_m(self) -> float:
        """Half-width of Student's 95% interval for the mean over drives."""
        return _mean_ci(self.diffs_m)[1]

    @property
    def verdict(self) -> str:
        """`holds` (interval above 0), `reversed` (below 0) or `undecided`."""
        return _verdict(self.mean_m, self.ci_m)

    @property
    def in_order(self) -> int:
        """Drives on which the slower split was strictly less accurate."""
        return sum(d > 0 for d in self.diffs_m)


def pair_effects(comparisons: Sequence[SplitComparison]) -> list[PairEffect]:
    """Every phase's pairs of fixed splits adjacent in latency (their mean latency over all the
    drives), with each drive's difference in mean error."""
    if not comparisons:
        return []
    first = comparisons[0]
    if any(c.bounds != first.bounds or set(c.fixed) != set(first.fixed) for c in comparisons):
        raise ValueError("the drives must share their phases and their fixed splits")
    out = []
    for j in range(len(first.bounds)):
        latency: dict[str, list[float]] = {}
        for c in comparisons:
            for k, f in c.by_latency(j):
                latency.setdefault(k, []).append(f.mean_latency_s)  # type: ignore[arg-type]
        order = sorted(latency, key=lambda k: float(np.mean(latency[k])))
        for fast, slow in itertools.pairwise(order):
            diffs = []
            for c in comparisons:
                f, g = c.fixed[fast].phases[j], c.fixed[slow].phases[j]
                if not (math.isfinite(f.mean_error_m) and math.isfinite(g.mean_error_m)):
                    continue
                diffs.append(g.mean_error_m - f.mean_error_m)
            out.append(PairEffect(j, fast, slow, tuple(diffs)))
    return out


def path_scale_error(gt: NDArray[np.float64], vo: NDArray[np.float64]) -> float:
    """The VO's scale error on one drive: its path length over ground truth's, minus one
    (poses (N, 3) [x, y, yaw], the same frames)."""
    gt, vo = np.asarray(gt, dtype=np.float64), np.asarray(vo, dtype=np.float64)
    if gt.shape != vo.shape or gt.ndim != 2 or gt.shape[0] < 2:
        raise ValueError(f"need two (N >= 2, 3) pose arrays, got {gt.shape} and {vo.shape}")
    length = float(np.hypot(*np.diff(gt[:, :2], axis=0).T).sum())
    if length <= 0.0:
        raise ValueError("ground truth does not move: the VO's scale error is undefined")
    return float(np.hypot(*np.diff(vo[:, :2], axis=0).T).sum()) / length - 1.0


@dataclass(frozen=True)
class LearnedEffect:
    """The learned run against one fixed split: per drive, fixed total / learned total − 1."""

    split: str
    gains: tuple[float, ...]

    @property
    def mean(self) -> float:
        return _mean_ci(self.gains)[0]

    @property
    def ci(self) -> float:
        return _mean_ci(self.gains)[1]

    @property
    def verdict(self) -> str:
        """`holds` (learning pays on average), `reversed` or `undecided`."""
        return _verdict(self.mean, self.ci)


def learned_effects(comparisons: Sequence[SplitComparison]) -> list[LearnedEffect]:
    """The learned run against each fixed split over the drives that have both."""
    if not comparisons:
        return []
    out = []
    for k in comparisons[0].fixed:
        gains = [
            c.fixed[k].total_m / c.learned.total_m - 1.0
            for c in comparisons
            if c.learned is not None and k in c.fixed and c.learned.total_m > 0
        ]
        out.append(LearnedEffect(k, tuple(gains)))
    return out


__all__ = [
    "LearnedEffect",
    "PairEffect",
    "learned_effects",
    "pair_effects",
    "path_scale_error",
]
