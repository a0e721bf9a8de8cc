"""Zero-time stages: a `Gate` lets each packet through or drops it as it arrives.

`Outage` drops everything entering the link while an outage is on; `Segment` drops nothing but
splits super-packets into wire packets where a later stage acts per wire packet. The loss gates
are `netem.stages.loss`'s.
"""

from __future__ import annotations

import math
from typing import Any

from netem.gso import Frame, split
from netem.profile import LinkProfile
from netem.stages.base import Instant, wire_packets

#: A super-packet is split before a link on which it would be on the wire longer than this:
#: its first segment would otherwise wait for its last. TCP sizes its bursts to ~1 ms of its
#: pacing rate (tcp_tso_autosize), so from ~20 Mbit/s up most stay whole, and a packet is
#: at most 2 ms late for the wire time of the ones sent with it. (tc's netem and tbf on a
#: TSO device serialise a super-packet whole at any rate; at 1 ms instead of 2 the relay
#: splits most of a 100 Mbit/s TCP flow, one write per wire packet.)
SPLIT_ABOVE_S = 0.002


class Gate(Instant):
    """A zero-time stage that lets each packet through or drops it when it arrives.

    A gate decides on a whole packet (`verdict`: an outage) or on each wire packet
    (`losses`: which of a super-packet's `n` wire packets are lost). A super-packet that
    loses none passes whole; one that loses some is split, and only those are dropped. So
    loss stays per wire packet while most super-packets of a lightly lossy link stay whole.
    """

    loss_reason = "loss"

    def verdict(self, packet: bytes, now: float) -> str | None:
        """The drop reason for the whole of `packet`, or None (default: none)."""
        return None

    def losses(self, n: int) -> list[int]:
        """Which of the next `n` wire packets are lost, in order (default: none)."""
        return []

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        n, size = wire_packets(packet), len(packet)
        c.packets_in += n
        c.bytes_in += size
        reason = self.verdict(packet, now)
        if reason is not None:
            c.drop(reason, size, n)
            return
        lost = self.losses(n)
        if not lost:
            self._passed.append((now, packet))
        elif len(lost) == n:
            c.drop(self.loss_reason, size, n)
        else:
            gone = set(lost)
            for i, part in enumerate(split(packet)):  # type: ignore[arg-type]
                if i in gone:
                    c.drop(self.loss_reason, len(part))
                else:
                    self._passed.append((now, part))  # type: ignore[arg-type]


class Outage(Gate):
    """Drops every packet entering the link while an outage is on (a dead radio, a lost cell).

    It acts where packets enter, so what was already inside still arrives; a handover, which
    interrupts what leaves, is `HandoverGap`'s.
    """

    name = "outage"

    def __init__(self) -> None:
        super().__init__()
        self.since = self.until = -math.inf

    def start(self, now: float, seconds: float) -> None:
        """Drop everything from `now` for `seconds` (math.inf: until `stop`)."""
        self.since, self.until = now, now + seconds

    def stop(self) -> None:
        self.since = self.until = -math.inf

    def verdict(self, packet: bytes, now: float) -> str | None:
        return "outage" if self.since <= now < self.until else None

    def losses(self, n: int) -> list[int]:
        return []


class Segment(Instant):
    """Splits super-packets (`netem.gso.Frame`) into wire packets where that matters.

    A later stage acts per wire packet when a trace plays (each waits for its own delivery
    opportunity), on a radio (each takes its place in the transport blocks of the slots) and
    when the rate would keep a super-packet on the wire longer than
    `SPLIT_ABOVE_S`. (Loss gates split for themselves, only a super-packet that loses some
    of its packets.) Elsewhere a super-packet moves whole, which is what makes offloads pay.
    Zero time; drops nothing.
    """

    name = "segment"

    def __init__(self) -> None:
        super().__init__()
        self.tracing = False
        self.radio = False
        self.split_above_bytes = math.inf

    def configure(self, profile: LinkProfile) -> None:
        rate = profile.rate_bps
        self.split_above_bytes = math.inf if rate is None else rate * SPLIT_ABOVE_S / 8.0
        # On a radio each wire packet takes its place in the transport blocks.
        self.radio = profile.radio is not None

    def splits(self, packet: Any) -> bool:
        """Whether `packet` leaves this stage as its wire packets."""
        return (
            type(packet) is Frame
            and packet.segments > 1
            and (self.tracing or self.radio or packet.wire_len > self.split_above_bytes)
        )

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        c.packets_in += wire_packets(packet)
        c.bytes_in += len(packet)
        if self.splits(packet):
            for part in split(packet):  # type: ignore[arg-type]
                self._passed.append((now, part))  # type: ignore[arg-type]
        else:
            self._passed.append((now, packet))
