"""The trace stage: delivery opportunities from a bandwidth trace (Mahimahi's link_queue)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterator

from netem.profile import LinkProfile
from netem.stages.base import Stage, pop_timed, wire_packets
from netem.traces import OPPORTUNITY_BYTES, Trace


class TraceLink(Stage):
    """Delivers packets only at a trace's delivery opportunities (Mahimahi's link_queue).

    Each opportunity carries up to 1500 bytes: several small packets, or part of a large one
    (a 9000-byte packet needs six). Opportunities that find the queue empty are lost. With no
    trace playing the stage is transparent. A trace that does not loop ends after its last
    period; `on_end` is then called (the pipeline gives the rate back to the profile) and any
    queued packets leave at once. The drop-tail limits: `queue_packets`, and `queue_time_s`
    as the longest time the head packet may have waited when a new one arrives.
    """

    name = "trace"

    def __init__(self) -> None:
        super().__init__()
        self.trace: Trace | None = None
        self.loop = False
        self.queue_packets: int | None = None
        self.queue_time_s: float | None = None
        self.on_end: Callable[[], None] | None = None
        self._times: Iterator[float] = iter(())
        self._next: float | None = None
        self._end = math.inf
        self._queue: deque[tuple[float, bytes]] = deque()  # (arrival, packet)
        self._head_left = 0  # bytes of the head packet still to deliver
        self._left: deque[tuple[float, bytes]] = deque()

    def configure(self, profile: LinkProfile) -> None:
        self.queue_packets = profile.queue_packets
        self.queue_time_s = profile.queue_time_s

    def play(self, trace: Trace, now: float, loop: bool) -> None:
        """Start replaying `trace` at `now` (a trace already playing is replaced)."""
        self._advance(now)
        self.trace, self.loop = trace, loop
        self._times = trace.opportunities(now, loop)
        self._next = next(self._times, None)
        self._end = math.inf if loop else now + trace.duration_s

    def stop(self, now: float) -> None:
        """Stop the trace; queued packets leave at `now`."""
        self._advance(now)
        self._finish(now)

    def _finish(self, at: float) -> None:
        self.trace, self._next, self._end = None, None, math.inf
        self._times = iter(())
        while self._queue:
            self._left.append((at, self._queue.popleft()[1]))
        self._head_left = 0
        if self.on_end is not None:
            self.on_end()

    def _advance(self, now: float) -> None:
        if self.trace is None:
            return
        q = self._queue
        while self._next is not None and self._next <= now:
            opportunity = self._next
            budget = OPPORTUNITY_BYTES
            while q and budget > 0:
                if self._head_left <= budget:
                    budget -= self._head_left
                    self._left.append((opportunity, q.popleft()[1]))
                    self._head_left = len(q[0][1]) if q else 0
                else:
                    self._head_left -= budget
                    budget = 0
            self._next = next(self._times, None)
        if self._next is None and self._end <= now:
            self._finish(self._end)

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        size, n = len(packet), wire_packets(packet)
        c.packets_in += n
        c.bytes_in += size
        self._advance(now)
        if self.trace is None:
            self._left.append((now, packet))
            return
        q = self._queue
        if self.queue_packets is not None and len(q) >= self.queue_packets:
            c.drop("queue_full", size, n)
            return
        if self.queue_time_s is not None and q and now - q[0][0] > self.queue_time_s:
            c.drop("queue_time", size, n)
            return
        q.append((now, packet))
        if len(q) == 1:
            self._head_left = size

    def pop_ready(self, now: float) -> list[bytes]:
        self._advance(now)
        return pop_timed(self._left, now, self.counters)

    def next_due(self) -> float | None:
        if self._left:
            return self._left[0][0]
        if self._queue:
            return self._next if self._next is not None else self._end
        return None

    def queued(self) -> int:
        return len(self._queue) + len(self._left)
