"""Communication-change detector: KL divergence between consecutive Gaussian fits (paper §5.2).

For each arm (split point) the detector keeps that arm's last 2·window costs, fits a Gaussian to
the latest `window` of them (N1) and one to the `window` before (N2), and computes KL(N1 || N2).
When the KL exceeds `threshold` on `consecutive` consecutive updates of the same arm, the
network has changed: the detector returns a `ChangeEvent`, forgets all history (every arm's
costs predate the change) and the caller resets the learner.

Variance floor: a fitted standard deviation is raised to
``max(min_std, min_rel_std · max(|μ1|, |μ2|))`` before the KL is computed, for both fits. A
constant or near-constant window (quantised timers, a loss-free shaped link) would otherwise
give σ → 0 and an infinite or huge KL from a shift far below what can be measured. The defaults
are 1e-4 cost units (0.1 ms when the cost is a latency in seconds, about the timer oversleep
measured on our VMs) and 1 % of the larger mean, so a pure mean shift between two noise-free
windows reads as the shift in units of 1 % of the mean.

Fit (`fit`): "mle" (the default, the paper's wording) fits mean and standard deviation; "robust"
fits the same Gaussian with the median and 1.4826 · MAD (the normal-consistent median absolute
deviation). Why robust exists: one retransmitted request (+200 ms RTO on a ~30 ms path) inside
a window of 30 raises the MLE σ about tenfold, and KL(N1 || N2) ≈ σ1²/(2σ2²) then reads ~75-180
— far above what a real bandwidth shift gives (~1-5) — so no threshold separates the two and
the learner is reset every time a packet is lost. The median/MAD fit ignores such a lone spike
and still moves with a shift of the bulk of the window.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from nodes.edgeloc.robust import median

FITS = ("mle", "robust")
MAD_TO_STD = 1.4826  # σ of a normal distribution = 1.4826 · its median absolute deviation


def kl_gaussian(mu1: float, s1: float, mu2: float, s2: float) -> float:
    """KL(N(mu1, s1²) || N(mu2, s2²)) in nats, closed form; `s1`, `s2` are standard deviations."""
    if not (s1 > 0 and s2 > 0):
        raise ValueError(f"standard deviations must be > 0, got s1={s1!r}, s2={s2!r}")
    return math.log(s2 / s1) + (s1 * s1 + (mu1 - mu2) ** 2) / (2.0 * s2 * s2) - 0.5


def finite_cost(arm: str, cost: object) -> float:
    """`cost` as a float, or a ValueError naming the arm: a NaN would poison every statistic."""
    try:
        value = float(cost)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"cost of arm {arm!r} must be a number, got {cost!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"cost of arm {arm!r} must be a finite number, got {cost!r}")
    return value


@dataclass(frozen=True)
class ChangeEvent:
    """A detected change: which arm's costs moved, the KL that confirmed it, and when.

    `at_play` counts every update the detector has seen since it was built (1-based), so it is
    the play index of the triggering play when the caller feeds every play.
    """

    arm: str
    kl: float
    at_play: int


class KLChangeDetector:
    """Watches each arm's cost distribution and reports a change confirmed on C updates."""

    def __init__(
        self,
        window: int = 10,
        threshold: float = 1.0,
        consecutive: int = 3,
        min_std: float = 1e-4,
        min_rel_std: float = 0.01,
        fit: str = "mle",
    ) -> None:
        if isinstance(window, bool) or not isinstance(window, int) or window < 2:
            raise ValueError(f"detector window must be an integer >= 2 samples, got {window!r}")
        if not (math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"KL threshold must be a positive number, got {threshold!r}")
        if isinstance(consecutive, bool) or not isinstance(consecutive, int) or consecutive < 1:
            raise ValueError(f"consecutive must be an integer >= 1, got {consecutive!r}")
        if not (min_std > 0 and min_rel_std >= 0):
            raise ValueError(
                f"variance floor needs min_std > 0 and min_rel_std >= 0, "
                f"got {min_std!r}, {min_rel_std!r}"
            )
        if fit not in FITS:
            raise ValueError(f"detector fit must be one of {', '.join(FITS)}, got {fit!r}")
        self.fit = fit
        self.window = window
        self.threshold = float(threshold)
        self.consecutive = consecutive
        self.min_std = float(min_std)
        self.min_rel_std = float(min_rel_std)
        self.plays = 0
        self._costs: dict[str, deque[float]] = {}
        self._streak: dict[str, int] = {}
        self._last_kl: dict[str, float] = {}

    def update(self, arm: str, cost: float) -> ChangeEvent | None:
        """Add one cost of `arm`; returns the event when this update confirms a change."""
        cost = finite_cost(arm, cost)
        self.plays += 1
        costs = self._costs.setdefault(arm, deque(maxlen=2 * self.window))
        costs.append(cost)
        if len(costs) < 2 * self.window:
            return None
        x = np.fromiter(costs, dtype=np.float64, count=len(costs))
        kl = self.divergence(x[self.window :], x[: self.window])
        self._last_kl[arm] = kl
        streak = self._streak.get(arm, 0) + 1 if kl > self.threshold else 0
        self._streak[arm] = streak
        if streak < self.consecutive:
            return None
        event = ChangeEvent(arm=arm, kl=kl, at_play=self.plays)
        self.reset()
        return event

    def divergence(self, latest: np.ndarray, previous: np.ndarray) -> float:
        """KL(N_latest || N_previous) of Gaussian fits (see `fit`), variance floored."""
        (mu1, sd1), (mu2, sd2) = self._fit(latest), self._fit(previous)
        floor = max(self.min_std, self.min_rel_std * max(abs(mu1), abs(mu2)))
        return kl_gaussian(mu1, max(sd1, floor), mu2, max(sd2, floor))

    def _fit(self, x: np.ndarray) -> tuple[float, float]:
        """(mean, standard deviation) of the Gaussian fitted to `x`."""
        if self.fit == "robust":
            values = x.tolist()
            med = median(values)
            return med, MAD_TO_STD * median([abs(v - med) for v in values])
        return float(np.mean(x)), float(np.std(x))

    def last_kl(self, arm: str) -> float | None:
        """The latest KL computed for `arm` (None until it has 2·window costs)."""
        return self._last_kl.get(arm)

    def reset(self) -> None:
        """Forget every arm's costs and streaks (the play counter keeps counting)."""
        self._costs.clear()
        self._streak.clear()
        self._last_kl.clear()
