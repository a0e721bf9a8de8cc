"""A handover's interruption as a stage: what would leave the link meanwhile is held or lost.

The last stage of a direction (`HandoverGap`), which `Pipeline.interrupt` starts; the limits of
a gap (`check_gap`) are also what the relay's control protocol checks an `interrupt` against.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

from netem.errors import ProfileError
from netem.stages.base import Stage, pop_timed, wire_packets

#: How a handover treats what would leave the link during its interruption (`HandoverGap`).
HANDOVER_MODES = ("hold", "drop")
#: The longest handover interruption: a held packet stays in memory for all of it, and a
#: handover that takes longer than this is a radio link failure (an `outage`), not a gap.
MAX_GAP_S = 10.0


def check_gap(seconds: object, mode: object) -> None:
    """Raise `ProfileError` (a ValueError) naming what is wrong with a handover gap."""
    if mode not in HANDOVER_MODES:
        raise ProfileError(f"handover gap `mode` = {mode!r}: must be hold or drop")
    if (
        isinstance(seconds, bool)
        or not isinstance(seconds, int | float)
        or not 0.0 <= seconds <= MAX_GAP_S  # (NaN fails this too)
    ):
        raise ProfileError(
            f"handover gap `seconds` = {seconds!r}: must be a number of seconds in 0..{MAX_GAP_S:g}"
        )


class HandoverGap(Stage):
    """The interruption of a handover: what would leave the link meanwhile is held or lost.

    While the UE moves to its target cell no data crosses the air (the interruption time, TS
    38.300 §9.2.3.2 and TS 38.133). `start(now, seconds, mode)` makes every packet that reaches
    this stage, i.e. would leave the link, in [now, now + seconds) either wait for the end
    ("hold": lossless handover, the source forwards its PDCP SDUs to the target, which
    delivers them in order once the UE is there) or be dropped, counted with reason "handover"
    ("drop": a lossy one, what was in flight is gone). Packets that reach it later pass at
    once, but never ahead of held ones. Without a gap it is a pass-through: a packet leaves
    when it arrives.

    Last in a pipeline, after `Delay`, so the gap cuts the link where packets leave it: a
    packet sent just before the handover but still in flight is caught by it, one that had
    left is not. (`Outage`, at the chain's start, is the other kind: it drops what enters.)

    A gap started while one is on makes one gap of the two (their union: it ends at the
    later end); the new `mode` applies from its start, and held packets wait for the end of
    the whole. Super-packets are held or dropped whole and counted as their wire packets.
    """

    name = "handover"

    def __init__(self) -> None:
        super().__init__()
        self._passed: deque[tuple[float, bytes]] = deque()  # (leaves at, packet)
        self._held: deque[tuple[float, bytes]] = deque()  # (arrived, packet): leave at `until`
        self.since = self.until = -math.inf
        self.mode = "hold"
        self.gaps = 0  # gaps started (one that extends another counts too)
        self.held_packets = 0  # wire packets held, counted as they are held
        self.held_s = 0.0  # the time they were held, summed over wire packets as they leave

    def start(self, now: float, seconds: float, mode: str = "hold") -> None:
        """Interrupt the link from `now` for `seconds`: hold (`mode` "hold") or drop ("drop")
        what reaches the stage meanwhile. Raises `ProfileError` for a bad mode or duration."""
        check_gap(seconds, mode)
        if self._held and now >= self.until:
            self._release()  # the previous gap is over: its packets left at its end
        if now < self.until:
            # One is on: both are one interruption, which the later end closes.
            self.since = min(self.since, now)
            self.until = max(self.until, now + seconds)
        else:
            self.since, self.until = now, now + seconds
        self.mode = mode
        self.gaps += 1

    def _release(self) -> None:
        """Held packets leave at the gap's end, in the order they came."""
        until = self.until
        for arrived, packet in self._held:
            n = wire_packets(packet)
            self.held_s += n * (until - arrived)
            self._passed.append((until, packet))
        self._held.clear()

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        n = wire_packets(packet)
        c.packets_in += n
        c.bytes_in += len(packet)
        if now < self.until:  # (without a gap `until` is -inf: the common case is one test)
            if now >= self.since and self.mode == "drop":
                c.drop("handover", len(packet), n)
                return
            if now >= self.since or self._held:  # (a packet never overtakes a held one)
                self.held_packets += n
                self._held.append((now, packet))
                return
        elif self._held:
            self._release()
        self._passed.append((now, packet))

    def pop_ready(self, now: float) -> list[bytes]:
        if self._held and now >= self.until:
            self._release()
        return pop_timed(self._passed, now, self.counters)

    def next_due(self) -> float | None:
        # Every packet that passed came before the held ones, so it leaves first.
        if self._passed:
            return self._passed[0][0]
        return self.until if self._held else None

    def queued(self) -> int:
        return len(self._passed) + len(self._held)

    def handover_counters(self) -> dict[str, Any]:
        """What the gaps did: how many were started, the last one's mode and window, wire
        packets held (and for how long, summed over those that have left) or dropped."""
        return {
            "gaps": self.gaps,
            "mode": self.mode,
            "since": self.since,
            "until": self.until,
            "held_packets": self.held_packets,
            "held_s": self.held_s,
            "dropped_packets": self.counters.dropped_packets.get("handover", 0),
        }

    def report(self) -> tuple[str, dict[str, Any]] | None:
        return ("handover", self.handover_counters()) if self.gaps else None
