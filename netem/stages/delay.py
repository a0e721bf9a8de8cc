"""The delay stage: propagation delay plus jitter, in order unless the profile reorders."""

from __future__ import annotations

import heapq
import math
import random
from collections import deque

from netem.profile import LinkProfile
from netem.stages.base import Stage, pop_timed, wire_packets

# Pareto jitter: shape 3 has a finite variance; samples are shifted and scaled to mean 0 and
# standard deviation 1, so `jitter_s` is the standard deviation for pareto as for normal.
_PARETO_SHAPE = 3.0
_PARETO_MEAN = _PARETO_SHAPE / (_PARETO_SHAPE - 1.0)
_PARETO_SD = math.sqrt(_PARETO_SHAPE / ((_PARETO_SHAPE - 1.0) ** 2 * (_PARETO_SHAPE - 2.0)))


def jitter_sd(profile: LinkProfile) -> float:
    """Standard deviation of the per-packet delay that `profile`'s jitter gives.

    Same meaning as netem: for `normal` and `pareto` the jitter is the standard deviation;
    for `uniform` the delay is spread evenly over `delay ± jitter` (sd = jitter / √3).
    """
    if profile.jitter_distribution == "uniform":
        return profile.jitter_s / math.sqrt(3.0)
    return profile.jitter_s


class Delay(Stage):
    """Holds each packet for `delay_s` plus a random jitter (propagation delay).

    Jitter follows `distribution` (see `jitter_sd`); a negative total is clamped to 0. Unless
    `reorder` is set, a packet never leaves before its predecessor (it waits for it), as on a
    real path that does not reorder; with `reorder` each packet leaves at its own time.
    """

    name = "delay"

    def __init__(
        self,
        delay_s: float = 0.0,
        jitter_s: float = 0.0,
        distribution: str = "normal",
        reorder: bool = False,
        seed: int | str = 0,
    ) -> None:
        super().__init__()
        self.delay_s = delay_s
        self.jitter_s = jitter_s
        self.distribution = distribution
        self.reorder = reorder
        self._rng = random.Random(f"{seed}:{self.name}")
        self._fifo: deque[tuple[float, bytes]] = deque()
        self._heap: list[tuple[float, int, bytes]] = []
        self._seq = 0
        self._last_due = -math.inf

    def configure(self, profile: LinkProfile) -> None:
        self.delay_s = profile.fixed_delay_s
        self.jitter_s = profile.jitter_s
        self.distribution = profile.jitter_distribution
        if profile.reorder != self.reorder:
            self._switch_order(profile.reorder)

    def _switch_order(self, reorder: bool) -> None:
        if reorder:
            for due, packet in self._fifo:
                heapq.heappush(self._heap, (due, self._seq, packet))
                self._seq += 1
            self._fifo.clear()
        else:
            for due, _, packet in sorted(self._heap):
                self._fifo.append((due, packet))
                self._last_due = max(self._last_due, due)
            self._heap.clear()
        self.reorder = reorder

    def min_hold_s(self) -> float:
        if self.jitter_s <= 0.0:
            return self.delay_s
        if self.distribution == "uniform":
            return max(0.0, self.delay_s - self.jitter_s)
        return 0.0  # normal and pareto jitter are unbounded below (clamped at 0)

    def sample(self) -> float:
        """One packet's delay in seconds (delay + jitter, never negative)."""
        if self.jitter_s <= 0.0:
            return self.delay_s
        rng = self._rng
        if self.distribution == "uniform":
            z = rng.uniform(-1.0, 1.0)
        elif self.distribution == "pareto":
            z = (rng.paretovariate(_PARETO_SHAPE) - _PARETO_MEAN) / _PARETO_SD
        else:
            z = rng.gauss(0.0, 1.0)
        return max(0.0, self.delay_s + self.jitter_s * z)

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        c.packets_in += wire_packets(packet)
        c.bytes_in += len(packet)
        due = now + self.sample()
        if self.reorder:
            heapq.heappush(self._heap, (due, self._seq, packet))
            self._seq += 1
        else:
            if due < self._last_due:
                due = self._last_due
            self._last_due = due
            self._fifo.append((due, packet))

    def pop_ready(self, now: float) -> list[bytes]:
        if not self.reorder:
            return pop_timed(self._fifo, now, self.counters)
        out: list[bytes] = []
        heap = self._heap
        while heap and heap[0][0] <= now:
            packet = heapq.heappop(heap)[2]
            out.append(packet)
            self.counters.bytes_out += len(packet)
            self.counters.packets_out += wire_packets(packet)
        # Packets still in the FIFO from before a switch to `reorder` leave too.
        return out + pop_timed(self._fifo, now, self.counters) if self._fifo else out

    def next_due(self) -> float | None:
        if self._heap:
            return self._heap[0][0]
        return self._fifo[0][0] if self._fifo else None

    def queued(self) -> int:
        return len(self._fifo) + len(self._heap)
