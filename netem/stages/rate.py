"""The rate stage: serialisation at the link's rate behind a drop-tail queue."""

from __future__ import annotations

import math
from collections import deque

from netem.gso import split
from netem.profile import LinkProfile
from netem.stages.base import Stage, pop_timed, wire_packets


class Rate(Stage):
    """A link of `rate_bps` with a drop-tail queue: each packet leaves after its serialisation.

    The packet at the head is "on the wire" for `8 * len / rate_bps` seconds after the
    previous one left (or after it arrived, if the link was idle). A new packet is dropped
    when `queue_packets` packets are already inside, or when it would wait longer than
    `queue_time_s` before its turn. `rate_bps=None` means no limit (a packet leaves at once).
    Bytes are IP packet bytes, what a TUN device carries.
    """

    name = "rate"

    def __init__(
        self,
        rate_bps: float | None = None,
        queue_packets: int | None = None,
        queue_time_s: float | None = None,
    ) -> None:
        super().__init__()
        self.profile_rate_bps = rate_bps
        self.suspended = False  # True while a trace sets the rate instead
        self.queue_packets = queue_packets
        self.queue_time_s = queue_time_s
        self._queue: deque[bytes] = deque()  # waiting + the head on the wire
        self._queued_bytes = 0
        self._queued_packets = 0  # wire packets: a super-packet counts for its segments
        self._head_start = 0.0
        self._head_finish = math.inf
        self._last_finish = -math.inf  # when the previous packet left the wire
        self._left: deque[tuple[float, bytes]] = deque()  # (time it left, packet)

    @property
    def rate_bps(self) -> float | None:
        """The rate in force (None: unlimited, also while a trace is playing)."""
        return None if self.suspended else self.profile_rate_bps

    def _serialise(self, size: int) -> float:
        rate = self.rate_bps
        if rate is None:
            return 0.0
        if rate <= 0:
            return math.inf
        return size * 8.0 / rate

    def configure(self, profile: LinkProfile) -> None:
        self.queue_packets = profile.queue_packets
        self.queue_time_s = profile.queue_time_s
        self.set_rate(profile.rate_bps)

    def set_rate(self, rate_bps: float | None, suspended: bool | None = None) -> None:
        """Change the rate in place; the head packet's wire time is recomputed from its start."""
        self.profile_rate_bps = rate_bps
        if suspended is not None:
            self.suspended = suspended
        if self._queue:
            self._head_finish = self._head_start + self._serialise(len(self._queue[0]))

    def backlog_s(self, now: float) -> float:
        """How long a packet arriving at `now` would wait before its turn on the wire."""
        if not self._queue:
            return 0.0
        rest = self._queued_bytes - len(self._queue[0])
        return max(0.0, self._head_finish - now) + self._serialise(rest)

    def _advance(self, now: float) -> None:
        q = self._queue
        while q and self._head_finish <= now:
            packet = q.popleft()
            self._queued_bytes -= len(packet)
            self._queued_packets -= wire_packets(packet)
            finish = self._head_finish
            self._left.append((finish, packet))
            self._last_finish = finish
            if q:
                self._head_start = finish
                self._head_finish = finish + self._serialise(len(q[0]))
            else:
                self._head_finish = math.inf

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        size, n = len(packet), wire_packets(packet)
        c.packets_in += n
        c.bytes_in += size
        self._advance(now)
        if self.rate_bps is not None:
            if self.queue_packets is not None and self._queued_packets + n > self.queue_packets:
                if n > 1:
                    # A super-packet at the queue's edge: as many of its segments get in as
                    # there is room for, as on a wire.
                    c.packets_in -= n
                    c.bytes_in -= size
                    for part in split(packet):  # type: ignore[arg-type]
                        self.push(part, now)
                    return
                c.drop("queue_full", size, n)
                return
            if self.queue_time_s is not None and self.backlog_s(now) > self.queue_time_s:
                c.drop("queue_time", size, n)
                return
        self._queue.append(packet)
        self._queued_bytes += size
        self._queued_packets += n
        if len(self._queue) == 1:
            # The wire is free from `now`, or from when the last packet left if a caller ran
            # the stage a little ahead of time.
            self._head_start = max(now, self._last_finish)
            self._head_finish = self._head_start + self._serialise(size)

    def pop_ready(self, now: float) -> list[bytes]:
        self._advance(now)
        return pop_timed(self._left, now, self.counters)

    def next_due(self) -> float | None:
        if self._left:
            return self._left[0][0]
        if self._queue and self._head_finish < math.inf:
            return self._head_finish
        return None

    def queued(self) -> int:
        return len(self._queue) + len(self._left)
