"""Split-point learner: sliding-window UCB1-normal (paper §5.1, Auer et al. 2002, Fig. 4).

The learner's arms are the DNN split points; a play is one inference request and its cost is
what the caller measured for it (end-to-end latency by default, or the localization error in
experiments). The learner minimises cost, so where the paper maximises a reward we use
reward = -cost, which flips the sign of the mean and keeps the variance.

The index, exactly as Auer et al. (2002) print UCB1-Normal, in reward form::

    x̄_j + sqrt(16 · (q_j − n_j x̄_j²) / (n_j − 1) · ln(t − 1) / n_j)

with x̄_j the mean reward of arm j, q_j the sum of its squared rewards and n_j its plays. In cost
form the learner plays ``argmin_j  mean_j − sqrt(16 · var_j · ln(t − 1) / (n_j − 1))``, which is
SPEC §4's written form, and it is the same number as the textbook's: with the *population*
variance var_j = q_j/n_j − x̄_j² (the paper's appendix defines σ̂² this way),
var_j / (n_j − 1) = (q_j − n_j x̄_j²) / (n_j (n_j − 1)), i.e. the textbook's extra ``/n`` is
folded into the variance. (Reading var_j as the unbiased n/(n−1)-corrected variance would widen
the bonus by sqrt(n/(n−1)); we do not.)

What ``t`` is: Auer's loop numbers the *current* play ``n = 1, 2, …``, so ``ln(n − 1)`` is the log
of the plays already made; the paper's ``I_t`` uses statistics "up to time t−1" in the same way.
With a sliding window the plays already made are the ones the window still holds, so here
``t − 1 = len(window)`` = min(plays since the last reset, W), and ``t`` is the index of the play
being chosen (Garivier & Moulines' SW-UCB likewise uses log min(t, W)). n_j, mean_j and var_j
come from the same window.

Exploration: an arm with fewer than 2 samples in the window has no variance, so it is played
first (fewest samples first) — the paper's rule. Because samples leave the window, every arm is
re-played whenever it drops below 2 samples, so in steady state each non-best arm costs at least
2 plays per W: the best arm can get at most 1 − 2(K−1)/W of the plays. Auer's extra rule (play
any arm with n_j < ⌈8 ln t⌉) is available as ``forced_exploration=True`` but is off by default
because the paper does not use it and, inside a window, it degenerates into round-robin as soon
as K·⌈8 ln W⌉ > W (K ≥ 2 for W = 50).

Fit (`fit`), BEYOND THE PAPER when "robust": UCB1-normal assumes Gaussian costs, and latency is
not: a request that loses one packet waits for a retransmission (+200 ms), and an arm that
sends more packets (the raw image: 27 packets) meets one every few dozen plays. One such
sample in an arm's window inflates its variance ~100x, and because the index is
mean − bonus(variance), the *slowest* arm then looks most promising: it is replayed until the
spike leaves the window or ~50 plays dilute it, and with the next spike the cycle repeats
(measured in a replay of the default scenario with a 6 Mbit/s middle phase: the raw-image
arm, 18 ms slower than the best, took most plays for 15 s). "robust" fits the same Gaussian
with the median and 1.4826 · MAD, which equal the mean and the standard deviation for
Gaussian costs and ignore a lone spike (the median-based estimator that Bubeck, Cesa-Bianchi
and Lugosi 2013 use for heavy-tailed bandits; the change detector has the same option, see
`detector`). "mle" (mean and population variance) is the paper's and stays the default of
this class.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from nodes.edgeloc.detector import (
    FITS,
    MAD_TO_STD,
    ChangeEvent,
    KLChangeDetector,
    finite_cost,
)
from nodes.edgeloc.robust import median

MIN_SAMPLES = 2  # UCB1-normal needs a variance, hence two samples per arm


@dataclass(frozen=True)
class ArmStats:
    """One arm's view for the decision topic: window samples, mean, variance and index.

    `var` is the population variance (ddof = 0) used in the index. `mean` and `var` are NaN with
    no samples; `index` is -inf while the arm still must be explored (n < 2, or below Auer's
    forced-exploration count when that rule is on), so "lowest index is played" stays true.
    """

    arm: str
    n: int
    mean: float
    var: float
    index: float


class SlidingWindowUCB1Normal:
    """Chooses a split point per request from the costs of the last `window` plays.

    `window=None` keeps every play since the last reset (plain UCB1-normal, memory grows with
    the plays: for reference runs). Exact ties of the index are broken by a generator seeded
    with `rng_seed` (reproducible for a given seed), or by the order of `arms` when `rng_seed`
    is None.
    """

    def __init__(
        self,
        arms: Sequence[str],
        window: int | None = 50,
        rng_seed: int | None = 0,
        forced_exploration: bool = False,
        fit: str = "mle",
    ) -> None:
        if fit not in FITS:
            raise ValueError(f"learner fit must be one of {', '.join(FITS)}, got {fit!r}")
        self.fit = fit
        arms = list(arms)
        if not arms:
            raise ValueError("the learner needs at least one arm (split point)")
        if any(not isinstance(a, str) or not a for a in arms):
            raise ValueError(f"arms must be non-empty strings, got {arms!r}")
        if len(set(arms)) != len(arms):
            dupes = sorted({a for a in arms if arms.count(a) > 1})
            raise ValueError(f"arm names must be unique, repeated: {', '.join(dupes)}")
        if window is not None:
            if isinstance(window, bool) or not isinstance(window, int):
                raise ValueError(f"window must be an integer number of plays, got {window!r}")
            if window < MIN_SAMPLES * len(arms):
                raise ValueError(
                    f"window={window} cannot hold {MIN_SAMPLES} samples of each of the "
                    f"{len(arms)} arms: use window >= {MIN_SAMPLES * len(arms)}"
                )
        self.arms: tuple[str, ...] = tuple(arms)
        self.window = window
        self.forced_exploration = forced_exploration
        self._slot = {a: i for i, a in enumerate(self.arms)}
        self._rng = np.random.default_rng(rng_seed) if rng_seed is not None else None
        # The window keeps which arm each remembered play went to; each arm keeps its own
        # costs in play order, so evicting the window's oldest play pops that arm's oldest cost.
        self._plays: deque[int] = deque()
        self._costs: list[deque[float]] = [deque() for _ in self.arms]
        self.total_plays = 0  # every update since construction, resets included
        # `select` and `stats` of one request see the same figures: computed once (the
        # medians are most of a vehicle's learner CPU), again after an update or a reset.
        self._version = 0
        self._cached: tuple[int, list[ArmStats]] | None = None

    # ---- learning ---------------------------------------------------------------------------

    @property
    def t(self) -> int:
        """Index of the play about to be chosen: plays the window holds, plus one."""
        return len(self._plays) + 1

    def select(self) -> str:
        """The split point to play next (does not change the statistics)."""
        stats = self._arm_stats()
        idx = np.array([s.index for s in stats])
        if np.isneginf(idx).any():
            # Exploration first: among arms that must be played, the least-sampled ones.
            need = [i for i, s in enumerate(stats) if np.isneginf(s.index)]
            fewest = min(stats[i].n for i in need)
            return self.arms[self._pick([i for i in need if stats[i].n == fewest])]
        best = float(idx.min())
        return self.arms[self._pick([i for i in range(len(idx)) if idx[i] == best])]

    def update(self, arm: str, cost: float) -> None:
        """Record the cost measured for one play of `arm`."""
        slot = self._slot_of(arm)
        cost = finite_cost(arm, cost)
        self._version += 1
        self._plays.append(slot)
        self._costs[slot].append(cost)
        if self.window is not None and len(self._plays) > self.window:
            self._costs[self._plays.popleft()].popleft()
        self.total_plays += 1

    def reset(self) -> None:
        """Forget every play ("retrain" after a change was detected)."""
        self._version += 1
        self._plays.clear()
        for costs in self._costs:
            costs.clear()

    def stats(self) -> list[ArmStats]:
        """Per-arm n, mean, var and index as `select` sees them now, in `arms` order."""
        return self._arm_stats()

    # ---- internals --------------------------------------------------------------------------

    def _slot_of(self, arm: str) -> int:
        try:
            return self._slot[arm]
        except (KeyError, TypeError):
            raise ValueError(
                f"unknown arm {arm!r}; the learner's arms are: {', '.join(self.arms)}"
            ) from None

    def _must_explore(self, n: int, t: int) -> bool:
        if n < MIN_SAMPLES:
            return True
        return self.forced_exploration and n < math.ceil(8.0 * math.log(t))

    def _arm_stats(self) -> list[ArmStats]:
        if self._cached is None or self._cached[0] != self._version:
            self._cached = (self._version, self._fit_arms())
        return list(self._cached[1])

    def _fit_arms(self) -> list[ArmStats]:
        t = self.t
        log_term = math.log(t - 1) if t > 1 else 0.0
        out = []
        for arm, costs in zip(self.arms, self._costs, strict=True):
            n = len(costs)
            if n == 0:
                out.append(ArmStats(arm, 0, math.nan, math.nan, -math.inf))
                continue
            if self.fit == "robust":  # median and normal-consistent MAD (see the module doc)
                mean = median(costs)
                var = (MAD_TO_STD * median([abs(c - mean) for c in costs])) ** 2
            else:
                x = np.fromiter(costs, dtype=np.float64, count=n)
                mean = float(x.mean())
                var = float(np.mean((x - mean) ** 2))  # two-pass population variance
            if self._must_explore(n, t):
                index = -math.inf
            else:
                index = mean - math.sqrt(16.0 * var * log_term / (n - 1))
            out.append(ArmStats(arm, n, mean, var, index))
        return out

    def _pick(self, candidates: list[int]) -> int:
        if len(candidates) == 1 or self._rng is None:
            return candidates[0]
        return candidates[int(self._rng.integers(len(candidates)))]


class AdaptiveSplitLearner:
    """The learner the vehicle runs: SW-UCB1-normal plus the KL change detector (paper §5).

    Each update feeds both; when the detector fires, the bandit forgets everything and the
    event is returned so the caller can record it. `detector=None` runs the bandit alone.
    """

    def __init__(
        self,
        arms: Sequence[str],
        window: int | None = 50,
        detector: KLChangeDetector | None = None,
        rng_seed: int | None = 0,
        fit: str = "mle",
    ) -> None:
        self.bandit = SlidingWindowUCB1Normal(arms, window=window, rng_seed=rng_seed, fit=fit)
        self.detector = detector
        self.events: list[ChangeEvent] = []

    @classmethod
    def from_settings(
        cls,
        arms: Sequence[str],
        window: int = 50,
        detector: bool = True,
        kl_threshold: float = 1.0,
        consecutive: int = 3,
        detector_window: int = 10,
        rng_seed: int | None = 0,
        detector_fit: str = "mle",
        fit: str = "mle",
    ) -> AdaptiveSplitLearner:
        """Build from the plain numbers a scenario's `Learner` settings hold."""
        det = None
        if detector:
            det = KLChangeDetector(detector_window, kl_threshold, consecutive, fit=detector_fit)
        return cls(arms, window=window, detector=det, rng_seed=rng_seed, fit=fit)

    def select(self) -> str:
        return self.bandit.select()

    def update(self, arm: str, cost: float) -> ChangeEvent | None:
        """Record a play; returns the change event when this play triggered a reset."""
        self.bandit.update(arm, cost)
        if self.detector is None:
            return None
        event = self.detector.update(arm, cost)
        if event is not None:
            self.bandit.reset()
            self.events.append(event)
        return event

    def stats(self) -> list[ArmStats]:
        return self.bandit.stats()


def lead_for_good(splits: Sequence[str], best: str | None) -> tuple[int | None, float | None]:
    """(plays until `best` leads for good, its share of the plays after that).

    `best` leads after play i when it has been played more often than any other split over
    plays 0..i, and it leads for good from the first play after which it never falls behind
    again. This is the issue's "after convergence the learner plays the best split >= 90% of
    the time; it re-converges within 2·W plays"; (None, None) when it never leads.
    """
    if best is None or not splits:
        return None, None
    counts = {a: np.cumsum([s == a for s in splits]) for a in {*splits, best}}
    others = [v for a, v in counts.items() if a != best] or [np.zeros(len(splits))]
    behind = np.flatnonzero(counts[best] <= np.max(others, axis=0))
    lead = 0 if behind.size == 0 else int(behind[-1]) + 1
    after = splits[lead:]
    if not after:
        return None, None
    return lead, sum(s == best for s in after) / len(after)
