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
split's total error over the learned run's, minus one (> 0: learning paid). Both are
`OverDrives`: one figure per drive and what they say together.

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
from numpy.typing import NDArray

from nodes.edgeloc.compare import SplitComparison, paired_noise_m


@dataclass(frozen=True)
class OverDrives:
    """One figure per drive (`per_drive`, > 0 meaning the premise's side) and what they say
    together: the mean, Student's 95% interval and the verdict."""

    per_drive: tuple[float, ...]

    @property
    def drives(self) -> int:
        return len(self.per_drive)

    @property
    def mean(self) -> float:
        return float(np.mean(self.per_drive)) if self.per_drive else math.nan

    @property
    def ci(self) -> float:
        """Half-width of Student's 95% interval for the mean (inf with fewer than 2 drives)."""
        return paired_noise_m(self.per_drive, [0.0] * self.drives)

    @property
    def verdict(self) -> str:
        """`holds` (the interval above 0), `reversed` (below 0) or `undecided`."""
        if self.mean - self.ci > 0:
            return "holds"
        if self.mean + self.ci < 0:
            return "reversed"
        return "undecided"

    @property
    def ahead(self) -> int:
        """Drives on the premise's side (> 0)."""
        return sum(d > 0 for d in self.per_drive)


@dataclass(frozen=True)
class PairEffect(OverDrives):
    """Phase `phase`, two splits adjacent in latency: per drive (`per_drive`) the slower one's
    mean error minus the faster one's (m)."""

    phase: int = 0
    faster: str = ""
    slower: str = ""


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
            out.append(PairEffect(tuple(diffs), j, fast, slow))
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
class LearnedEffect(OverDrives):
    """The learned run against fixed split `split`: per drive (`per_drive`), the fixed split's
    total error over the learned run's, minus one."""

    split: str = ""


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
        out.append(LearnedEffect(tuple(gains), k))
    return out


__all__ = [
    "LearnedEffect",
    "OverDrives",
    "PairEffect",
    "learned_effects",
    "pair_effects",
    "path_scale_error",
]
