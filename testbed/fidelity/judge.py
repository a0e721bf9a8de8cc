"""Ours against theirs: a case's measured delays beside what its source published, each figure
within its tolerance or not, and the case's verdict.

Tolerances (`TOLERANCES`): a median within 10% or 0.5 ms, whichever is larger; a p90, p95 or
p99 within 20% or 1 ms; a mean within 10%; a minimum as a median. Where the source gave its
samples (per packet, or a histogram), the Wasserstein-1 distance between the two distributions
must be within what the source's own sampling spread allows for as many probes as ours (the
99th percentile of W1 between `draws` resamples and the data, `sampling_w1`: per-packet data
in runs of BLOCK_S of consecutive packets, since a queue's delays are correlated; a histogram
one by one) plus the host's 0.3 ms; Kolmogorov-Smirnov is printed beside it. Components: a
HARQ share within 3 binomial sigmas (over our transport blocks) of the source's, its step
within the source's range; a segmented share within 10 points. A floor: our minimum above it.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from testbed.fidelity.case import Case

#: figure -> (relative, absolute ms): within the larger of the two.
TOLERANCES: dict[str, tuple[float, float]] = {
    "min": (0.10, 0.5),
    "p50": (0.10, 0.5),
    "mean": (0.10, 0.0),
    "p90": (0.20, 1.0),
    "p95": (0.20, 1.0),
    "p99": (0.20, 1.0),
}
#: W1 tolerance: the host's part (the relay's timer and the receiving stack, as the link test).
HOST_W1_MS = 0.3
HARQ_SIGMAS = 3.0
#: Per-packet data is resampled in runs this long (of the source's probes): EDAF's near-full
#: uplink stays busy for seconds, so its delays are correlated over runs of packets, and
#: resampling them one by one would understate the data's own spread (the W1 tolerance
#: `testbed fidelity oai-usrp-edaf` prints is this spread plus HOST_W1_MS).
BLOCK_S = 1.0
SEGMENTED_POINTS = 0.10


@dataclass(frozen=True)
class Check:
    """One figure: ours, theirs, the tolerance, and whether it holds."""

    what: str
    ours: float
    theirs: float | str
    tolerance: str
    ok: bool

    def to_dict(self) -> dict[str, Any]:
        return {
            "what": self.what,
            "ours": self.ours,
            "theirs": self.theirs,
            "tolerance": self.tolerance,
            "ok": self.ok,
        }


@dataclass
class Judged:
    """A variant's checks, our figures per measure, and the samples behind them."""

    case: str
    variant: str
    checks: list[Check] = field(default_factory=list)
    ours: dict[str, dict[str, float]] = field(default_factory=dict)
    samples: dict[str, list[float]] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.checks)


@dataclass
class CaseResult:
    case: Case
    variants: list[Judged]
    real: bool

    @property
    def ok(self) -> bool:
        return all(v.ok for v in self.variants)


def _sorted_cdf(
    values: Sequence[float], weights: Sequence[float] | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples sorted, their weights, and the weighted CDF at each."""
    v = np.asarray(values, dtype=float)
    w = np.ones_like(v) if weights is None else np.asarray(weights, dtype=float)
    order = np.argsort(v)
    v, w = v[order], w[order]
    return v, w, np.cumsum(w) / w.sum()


def _at(v: np.ndarray, cum: np.ndarray, p: np.ndarray | float) -> np.ndarray:
    return v[np.minimum(len(v) - 1, np.searchsorted(cum, p))]


def figures(values: Sequence[float], weights: Sequence[float] | None = None) -> dict[str, float]:
    """min / p50 / mean / p90 / p95 / p99 / max (ms) of samples, weighted or not."""
    v, w, cum = _sorted_cdf(values, weights)
    mask = w > 0
    return {
        "n": float(w.sum()),
        "min": float(v[mask][0]),
        "p50": float(_at(v, cum, 0.5)),
        "mean": float((v * w).sum() / w.sum()),
        "p90": float(_at(v, cum, 0.9)),
        "p95": float(_at(v, cum, 0.95)),
        "p99": float(_at(v, cum, 0.99)),
        "max": float(v[mask][-1]),
    }


def _quantiles(values: Sequence[float], weights: Sequence[float] | None, n: int) -> np.ndarray:
    v, _, cum = _sorted_cdf(values, weights)
    return _at(v, cum, (np.arange(n) + 0.5) / n)


def w1_ms(ours: Sequence[float], theirs: Sequence[float], weights: Sequence[float] | None) -> float:
    """Wasserstein-1 between our samples and theirs: the mean gap of the quantile functions."""
    n = 2000
    return float(np.mean(np.abs(_quantiles(ours, None, n) - _quantiles(theirs, weights, n))))


def ks(ours: Sequence[float], theirs: Sequence[float], weights: Sequence[float] | None) -> float:
    """Kolmogorov-Smirnov: the largest gap between the two CDFs."""
    a = np.sort(np.asarray(ours, dtype=float))
    v = np.asarray(theirs, dtype=float)
    w = np.ones_like(v) if weights is None else np.asarray(weights, dtype=float)
    order = np.argsort(v)
    v, w = v[order], np.cumsum(w[order]) / w.sum()
    grid = np.union1d(a, v)
    fa = np.searchsorted(a, grid, side="right") / len(a)
    fb = np.concatenate([[0.0], w])[np.searchsorted(v, grid, side="right")]
    return float(np.max(np.abs(fa - fb)))


def sampling_w1(
    theirs: Sequence[float],
    weights: Sequence[float] | None,
    n: int,
    draws: int = 200,
    block: int = 1,
) -> float:
    """How far `n` draws from their own distribution fall from it (W1, 99th percentile).

    Per-packet data is a time series: a queue's delays are correlated over its busy periods,
    so it is resampled in runs of `block` consecutive packets (a moving-block bootstrap);
    a histogram (no order) one sample at a time."""
    rng = random.Random(0)
    v = list(theirs)
    w = None if weights is None else list(weights)
    out = []
    for _ in range(draws):
        if block <= 1 or w is not None:
            sample = rng.choices(v, weights=w, k=n)
        else:
            sample = []
            while len(sample) < n:
                i = rng.randrange(0, max(1, len(v) - block + 1))
                sample.extend(v[i : i + block])
            sample = sample[:n]
        out.append(w1_ms(sample, v, w))
    out.sort()
    return out[min(len(out) - 1, math.ceil(0.99 * len(out)) - 1)]


def tolerance(name: str, theirs: float) -> float:
    rel, absolute = TOLERANCES[name]
    return max(rel * theirs, absolute)


def judge_figures(measure: str, ours: dict[str, float], published: dict[str, float]) -> list[Check]:
    out = []
    for name, theirs in published.items():
        tol = tolerance(name, theirs)
        rel, absolute = TOLERANCES[name]
        text = f"±{rel:.0%}" + (f" or {absolute:g} ms" if absolute else "")
        out.append(
            Check(f"{measure} {name}", ours[name], theirs, text, abs(ours[name] - theirs) <= tol)
        )
    return out


def judge_data(
    measure: str,
    ours: Sequence[float],
    theirs: Sequence[float],
    weights: Sequence[float] | None,
    block: int = 1,
) -> list[Check]:
    chance = sampling_w1(theirs, weights, len(ours), block=block)
    allowed = chance + HOST_W1_MS
    w1 = w1_ms(ours, theirs, weights)
    how = f"runs of {block}" if block > 1 and weights is None else "one by one"
    return [
        Check(
            f"{measure} W1 (ms)",
            w1,
            0.0,
            f"<= {allowed:.3f} (sampling {chance:.3f}, {how}, + host {HOST_W1_MS})",
            w1 <= allowed,
        ),
        Check(f"{measure} KS", ks(ours, theirs, weights), 0.0, "printed, not judged", True),
    ]


def judge_floor(measure: str, ours_min: float, floor: float) -> Check:
    return Check(f"{measure} min above floor", ours_min, floor, f"> {floor:g} ms", ours_min > floor)


def judge_harq(counters: dict[str, Any], share: float) -> Check:
    """The share of transport blocks sent again at least once, against the source's."""
    tries = list(counters.get("retransmissions", []))
    blocks = sum(tries)
    again = blocks - (tries[0] if tries else 0)
    ours = again / blocks if blocks else 0.0
    sigma = math.sqrt(share * (1 - share) / blocks) if blocks else float("inf")
    return Check(
        "HARQ share of blocks",
        ours,
        share,
        f"±{HARQ_SIGMAS:g} sigma ({HARQ_SIGMAS * sigma:.3f}) over {blocks} blocks",
        abs(ours - share) <= HARQ_SIGMAS * sigma,
    )


def judge_segmented(counters: dict[str, Any], packets: int, share: float) -> Check:
    ours = counters.get("segmented_packets", 0) / packets if packets else 0.0
    return Check(
        "segmented share of packets",
        ours,
        share,
        f"±{SEGMENTED_POINTS * 100:g} points",
        abs(ours - share) <= SEGMENTED_POINTS,
    )
