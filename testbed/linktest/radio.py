"""Judging a radio link against its oracle: the closed-form delay distribution and the BLER.

A radio direction's measured one-way delays are compared with `netem.nr.oracle.DelayOracle`
(`oracle_comparison`: Wasserstein-1 and Kolmogorov-Smirnov), beside how far that many probes
of the oracle fall from it by chance (`sampling_chance`); the relay's counters give the HARQ
shares against the BLER (`harq_shares`) and what a slot carried while saturated
(`slot_goodput`).
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from netem.directions import Direction
from netem.profile import LinkProfile
from testbed.linktest.measure import percentile

if TYPE_CHECKING:
    from netem.nr.oracle import DelayOracle
    from netem.nr.radio import Grid

#: A radio direction's delay distribution may be this far from the oracle (Wasserstein-1),
#: the sum of two parts (W1 obeys the triangle inequality). The host's: the relay's timer
#: lateness and the receiving stack add ~0.1-0.3 ms here, so RADIO_TOL_S, or RADIO_TOL_MARGIN_S
#: over the 99th percentile of this host's timed wake-ups (measured at the start of the test,
#: `hostload.timer_floor`, and printed) or over the baseline probes' mean deviation from their
#: median, where either is larger (`LinkTest.host_tolerance_s`). The probes': a finite sample
#: of the oracle itself is this far from it, by chance; its 99th percentile over
#: SAMPLING_DRAWS draws of as many probes (`sampling_chance`; `testbed link-test` prints it:
#: 0.757 ms for 100 probes of OAI's uplink, whose 10% HARQ tail is 5 ms away).
RADIO_TOL_S = 0.0003
RADIO_TOL_MARGIN_S = 0.00025
SAMPLING_DRAWS = 400
#: Probabilities at which a radio direction's measured and closed-form CDFs are kept.
CDF_QUANTILES = tuple(k / 100 for k in range(1, 100))
#: A measured HARQ share may be this many binomial standard deviations from the BLER (4:
#: a false alarm once in ~16,000 directions).
HARQ_SIGMAS = 4.0
#: Below this many transport blocks the HARQ shares are printed but not judged.
HARQ_MIN_BLOCKS = 200


def oracle_comparison(net_ms: list[float], oracle: DelayOracle) -> dict[str, Any]:
    """Measured one-way delays (ms, net of everything but the radio) against the closed form:
    both CDFs at `CDF_QUANTILES`, the Wasserstein-1 distance (the mean gap between their
    quantile functions) and the Kolmogorov-Smirnov statistic (the largest gap between the
    CDFs)."""
    ordered = sorted(net_ms)
    n = len(ordered)
    w1 = statistics.fmean(
        abs(x - oracle.quantile((i + 0.5) / n) * 1000) for i, x in enumerate(ordered)
    )
    ks = 0.0
    for i, x in enumerate(ordered):
        f = oracle.cdf(x / 1000)
        ks = max(ks, (i + 1) / n - f, f - i / n)
    return {
        "samples": n,
        "w1_ms": w1,
        "ks": ks,
        "quantiles": list(CDF_QUANTILES),
        "measured_ms": [percentile(ordered, q) for q in CDF_QUANTILES],
        "oracle_ms": [oracle.quantile(q) * 1000 for q in CDF_QUANTILES],
    }


@dataclass(frozen=True)
class Chance:
    """How far `n` delays drawn from an oracle fall from it by chance (seconds): the 99th
    percentile over SAMPLING_DRAWS draws of their Wasserstein-1 distance from it, and of
    their median's distance from its median."""

    w1_s: float
    median_s: float


def sampling_chance(oracle: DelayOracle, n: int, q: float = 0.99, seed: int = 0) -> Chance:
    """`Chance` of `n` probes of `oracle`. W1 is the area between the CDFs, integrated on a
    fine grid; the oracle's pieces are uniform, so a draw picks a piece by its mass and a
    point in it."""
    pieces = np.array([p for p in oracle.pieces if p[2] > 0 and p[1] > p[0]])
    low, high, weight = pieces[:, 0], pieces[:, 1], pieces[:, 2]
    mass = (high - low) * weight
    mass /= mass.sum()
    xs = np.linspace(low.min(), high.max(), 4001)
    cdf = (np.clip(xs[:, None] - low, 0.0, high - low) * weight).sum(axis=1)
    cdf /= cdf[-1]
    median = oracle.quantile(0.5)
    rng = np.random.default_rng(seed)
    distances, medians = [], []
    for _ in range(SAMPLING_DRAWS):
        k = rng.choice(len(mass), size=n, p=mass)
        drawn = np.sort(low[k] + rng.random(n) * (high[k] - low[k]))
        empirical = np.searchsorted(drawn, xs, side="right") / n
        distances.append(np.abs(empirical - cdf).sum() * (xs[1] - xs[0]))
        medians.append(abs(float(np.median(drawn)) - median))
    return Chance(float(np.quantile(distances, q)), float(np.quantile(medians, q)))


def _tries_between(before: dict[str, Any], after: dict[str, Any]) -> list[int]:
    """Blocks by the HARQ retransmissions they needed, between two reads of a radio's
    counters (the last entry: given up on after all of them)."""
    was = before["retransmissions"]
    return [a - (was[k] if k < len(was) else 0) for k, a in enumerate(after["retransmissions"])]


def harq_shares(
    before: dict[str, Any], after: dict[str, Any], bler: float, max_retx: int
) -> dict[str, Any]:
    """Transport blocks by the HARQ retransmissions they needed between two reads of a radio's
    counters (the last share: given up on), beside the shares a first-transmission BLER
    implies (retry k: bler^k (1 - bler)); `bound` is HARQ_SIGMAS binomial deviations of the
    share of blocks whose first transmission failed."""
    tries = _tries_between(before, after)
    blocks = sum(tries)
    expected = [bler**k * (1 - bler) for k in range(max_retx + 1)] + [bler ** (max_retx + 1)]
    shares = [t / blocks if blocks else 0.0 for t in tries]
    return {
        "blocks": blocks,
        "shares": shares,
        "expected": expected[: len(shares)],
        "first_failed": 1 - shares[0] if blocks else 0.0,
        "bound": HARQ_SIGMAS * math.sqrt(bler * (1 - bler) / max(blocks, 1)) + 1 / max(blocks, 1),
    }


def slot_goodput(
    before: dict[str, Any], after: dict[str, Any], grid: Grid, bler: float
) -> dict[str, Any]:
    """What a slot carried while the rate test saturated the direction.

    A saturated UE fills every occasion it gets with one transport block: a new one or a
    retransmission of an earlier one (which takes the whole occasion, its block being full).
    So the occasions it used are its new blocks plus their retransmissions, and the bytes
    delivered per occasion used should be the mean transport block less the share `bler`
    of them that goes to resends (1 - bler: each new block takes 1 / (1 - bler) tries on
    average). Also: bytes per new block (a whole block), and, from the times of the two
    reads, the share of the direction's occasions in that time the UE used.
    """
    blocks = after["blocks"] - before["blocks"]
    tries = _tries_between(before, after)
    resends = sum(k * t for k, t in enumerate(tries[:-1])) + (len(tries) - 2) * tries[-1]
    used = blocks + resends
    delivered = after["bytes_out"] - before["bytes_out"]
    capacity = statistics.fmean(o.capacity_bytes for o in grid.occasions)
    per_s = len(grid.occasions) / grid.period_s
    seconds = after.get("t", 0.0) - before.get("t", 0.0)
    return {
        "blocks": blocks,
        "occasions": used,
        "bytes_per_occasion": delivered / used if used else None,
        "expected_bytes_per_occasion": capacity * (1 - bler),
        "bytes_per_block": delivered / blocks if blocks else None,
        "block_bytes": capacity,
        "occasions_per_s": per_s,
        "seconds": seconds,
        "used_share": used / (seconds * per_s) if seconds > 0 else None,
    }


def _radio_capped(profile: LinkProfile, direction: Direction) -> LinkProfile:
    """`profile` with the rate its radio's transport blocks allow (IP bytes per second)."""
    if profile.radio is None:
        return profile
    cap = profile.radio.goodput_bps(direction)
    return profile.replace(rate_bps=cap if profile.rate_bps is None else min(cap, profile.rate_bps))
