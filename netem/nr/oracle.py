"""The closed-form one-way delay of an idle NR direction (`DelayOracle`).

For an idle link whose packets fit one window, the distribution of the delay from a packet's
arrival (uniform over the period) to the end of the first window that starts at least `lead_s`
after it (a grant decided before the slot: K2, or a configured grant); with a scheduling
request, that of an SR's first grant and the grants its buffer status report brings.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from netem.directions import Direction
from netem.nr.phy import Carrier, NrError, Occasion, TddPattern, occasions


class DelayOracle:
    """Closed-form one-way delay of an idle NR direction, a mixture of uniform pieces.

    A packet arrives at `t`, uniform over the period (an idle UE's traffic is not locked to
    the slot grid). Which cut `c_k` of the period it falls before decides when it leaves: the
    arrivals in `(c_{k-1}, c_k]` all leave at the same time `T` (or, with HARQ, at one of
    a few times with known probabilities), so their delay is uniform on
    `[T - c_k, T - c_{k-1})`. `fixed_s` is the wired part of the link. `cdf` and `quantile`
    are exact; they describe the delivered packets (a residual HARQ loss is not a delay).

    - The scheduled model (`DelayOracle(...)`, the downlink, a configured grant, or an uplink
      whose buffer the gNB sees at once): cut `k` is occasion `k`'s start minus `lead_s`, and
      a packet that fits one window leaves at that occasion's end.
    - Scheduling request (`DelayOracle.scheduling_request`): cut `k` is the start of SR
      window `k`; the SR's small first grant comes `grant_delay_s` after the SR window ends,
      and, when the packet is larger, the buffer status report in it brings grants for the
      rest after the same delay from its decoding (TS 38.321 §5.4.4, §5.4.5).
    """

    def __init__(
        self,
        starts_ends: Sequence[tuple[float, float]],
        period_s: float,
        lead_s: float = 0.0,
        fixed_s: float = 0.0,
        bler: float = 0.0,
        max_retx: int = 0,
        harq_s: float = 0.0,
    ) -> None:
        if not starts_ends:
            raise NrError("no occasion in the period: this direction never sends")
        grid = _Windows([(s, e, 1) for s, e in starts_ends], period_s)
        harq = _Harq(bler, max_retx, harq_s, grid)
        cuts = [start - lead_s for start, _, _ in grid.windows]
        # An idle link's small packet fits any window, so a retransmission takes the first.
        outcomes = [harq.decodes(end) for _, end, _ in grid.windows]
        self._build(cuts, outcomes, period_s, fixed_s)

    @classmethod
    def scheduling_request(
        cls,
        occasions: Sequence[Occasion],
        sr_windows: Sequence[tuple[float, float]],
        period_s: float,
        grant_delay_s: float,
        first_grant_bytes: int,
        size_bytes: int,
        fixed_s: float = 0.0,
        bler: float = 0.0,
        max_retx: int = 0,
        harq_s: float = 0.0,
    ) -> DelayOracle:
        """An idle UE's `size_bytes` packet that must ask for its grant with an SR.

        Exact while the packet's blocks and their retransmissions do not compete for one
        occasion (an idle UE, a packet of a few blocks).
        """
        if not occasions or not sr_windows:
            raise NrError("no uplink occasion or no SR window in the period")
        grid = _Windows([(o.start_s, o.end_s, o.capacity_bytes) for o in occasions], period_s)
        harq = _Harq(bler, max_retx, harq_s, grid)
        srs = sorted(sr_windows)
        outcomes = []
        for _, sr_end in srs:
            _, end, capacity = grid.first(sr_end + grant_delay_s)
            first = min(size_bytes, first_grant_bytes, capacity)
            mixture: dict[float, float] = {}
            for t1, p1 in harq.decodes(end):
                # The rest goes in the occasions its buffer status report is granted.
                rest = [
                    harq.decodes(e) for e in grid.carrying(t1 + grant_delay_s, size_bytes - first)
                ]
                for t, p in _max_of([[(t1, p1)], *rest]):
                    mixture[t] = mixture.get(t, 0.0) + p
            outcomes.append(sorted(mixture.items()))
        inst = cls.__new__(cls)
        inst._build([start for start, _ in srs], outcomes, period_s, fixed_s)
        return inst

    def _build(
        self,
        cuts: Sequence[float],
        outcomes: Sequence[Sequence[tuple[float, float]]],
        period_s: float,
        fixed_s: float,
    ) -> None:
        self.period_s = period_s
        self.fixed_s = fixed_s
        self.pieces: list[tuple[float, float, float]] = []  # (low, high, weight)
        delivered = 0.0
        for k, cut in enumerate(cuts):
            previous = cuts[k - 1] - (period_s if k == 0 else 0.0)
            for leave, p in outcomes[k]:
                self.pieces.append((leave - cut + fixed_s, leave - previous + fixed_s, p))
                delivered += (cut - previous) * p
        #: The share of packets delivered (the rest is lost after the last retransmission).
        self.delivered = delivered / period_s

    @classmethod
    def for_direction(
        cls,
        pattern: TddPattern,
        direction: Direction,
        carrier: Carrier,
        lead_s: float = 0.0,
        fixed_s: float = 0.0,
        bler: float = 0.0,
        max_retx: int = 0,
        harq_s: float = 0.0,
    ) -> DelayOracle:
        windows = [(o.start_s, o.end_s) for o in occasions(pattern, direction, carrier)]
        return cls(windows, pattern.period_s, lead_s, fixed_s, bler, max_retx, harq_s)

    def cdf(self, x: float) -> float:
        """P(delay <= x) of a delivered packet."""
        total = 0.0
        for low, high, weight in self.pieces:
            if x >= high:
                total += (high - low) * weight
            elif x > low:
                total += (x - low) * weight
        return total / (self.period_s * self.delivered)

    def quantile(self, q: float) -> float:
        """The delay below which a fraction `q` of packets fall (bisection on the exact cdf)."""
        lo = min(p[0] for p in self.pieces)
        hi = max(p[1] for p in self.pieces)
        for _ in range(60):
            mid = (lo + hi) / 2
            if self.cdf(mid) < q:
                lo = mid
            else:
                hi = mid
        return hi

    def mean(self) -> float:
        total = sum((h - lo) * (h + lo) / 2 * w for lo, h, w in self.pieces)
        return total / (self.period_s * self.delivered)

    @property
    def minimum(self) -> float:
        return min(p[0] for p in self.pieces if p[2] > 0)

    @property
    def maximum(self) -> float:
        return max(p[1] for p in self.pieces if p[2] > 0)


class _Windows:
    """Windows `(start, end, capacity)` of one period, repeating every `period_s`."""

    def __init__(self, windows: Sequence[tuple[float, float, int]], period_s: float) -> None:
        self.windows = sorted(windows)
        self.period_s = period_s

    def first(self, t: float) -> tuple[float, float, int]:
        """The first window that starts at or after `t`."""
        n = math.floor(t / self.period_s)
        while True:
            for start, end, capacity in self.windows:
                if n * self.period_s + start >= t - 1e-12:
                    base = n * self.period_s
                    return base + start, base + end, capacity
            n += 1

    def carrying(self, t: float, size: int) -> list[float]:
        """The ends of the windows from `t` on that carry `size` bytes, each filled whole."""
        ends: list[float] = []
        while size > 0:
            start, end, capacity = self.first(t)
            ends.append(end)
            size -= capacity
            t = start + 1e-9
        return ends


class _Harq:
    """When a block sent in a window ending at `end` is decoded, with its probabilities."""

    def __init__(self, bler: float, max_retx: int, harq_s: float, grid: _Windows) -> None:
        self.bler, self.max_retx, self.harq_s, self.grid = bler, max_retx, harq_s, grid

    def decodes(self, end: float) -> list[tuple[float, float]]:
        """(decoded at, probability) per attempt; they add up to less than 1 by the loss."""
        if self.bler <= 0.0:
            return [(end, 1.0)]
        out, t = [], end
        for attempt in range(self.max_retx + 1):
            if attempt:
                t = self.grid.first(t + self.harq_s)[1]
            out.append((t, self.bler**attempt * (1.0 - self.bler)))
        return out


def _max_of(blocks: Sequence[Sequence[tuple[float, float]]]) -> list[tuple[float, float]]:
    """The distribution of the latest decoding of independent blocks (all of them decoded)."""
    times = sorted({t for block in blocks for t, _ in block})
    out, before = [], 0.0
    for t in times:
        upto = 1.0
        for block in blocks:
            upto *= sum(p for u, p in block if u <= t)
        out.append((t, upto - before))
        before = upto
    return [(t, p) for t, p in out if p > 0]
