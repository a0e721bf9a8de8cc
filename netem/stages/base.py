"""The stage protocol of the userspace link: small queues that each do one impairment.

This is Mahimahi's design (`delay_queue`, `link_queue`, `loss_queue`): every impairment is a
`Stage` with one interface,

    push(packet, now)      a packet enters the stage at time `now` (seconds, any clock)
    pop_ready(now)         the packets that have left the stage by `now`, in order
    next_due()             when the next packet will leave (None: nothing will on its own)

and a `Pipeline` (`netem.stages.pipeline`) chains stages into one direction of a link. The
pipeline is itself a stage, so a relay only ever sees push/pop_ready/next_due. Stages never
read a clock: the caller passes `now`, which makes them exact and testable with a fake clock.

A packet moves from one stage to the next at the instant it left (its due time), not when the
relay happened to wake up, so timer lateness is paid once, at the link's exit, never per stage.

A packet is anything whose `len()` is its size on the wire in bytes: `bytes`, or a
`netem.gso.Frame`, the super-packet of an offloading TUN, which also says how many wire packets
it stands for (`segments`); counters and queue limits count wire packets.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from netem.gso import Frame
from netem.profile import LinkProfile


def wire_packets(packet: Any) -> int:
    """How many packets `packet` is on the wire (a super-packet is several)."""
    return packet.segments if type(packet) is Frame else 1


@dataclass
class StageCounters:
    """What one stage saw: packets and bytes in, out, and dropped by reason."""

    packets_in: int = 0
    bytes_in: int = 0
    packets_out: int = 0
    bytes_out: int = 0
    dropped_packets: dict[str, int] = field(default_factory=dict)
    dropped_bytes: dict[str, int] = field(default_factory=dict)

    def drop(self, reason: str, size: int, packets: int = 1) -> None:
        self.dropped_packets[reason] = self.dropped_packets.get(reason, 0) + packets
        self.dropped_bytes[reason] = self.dropped_bytes.get(reason, 0) + size

    @property
    def dropped(self) -> int:
        return sum(self.dropped_packets.values())

    def to_dict(self) -> dict[str, Any]:
        return {
            "packets_in": self.packets_in,
            "bytes_in": self.bytes_in,
            "packets_out": self.packets_out,
            "bytes_out": self.bytes_out,
            "dropped_packets": dict(self.dropped_packets),
            "dropped_bytes": dict(self.dropped_bytes),
        }


class Stage:
    """One impairment: packets go in with `push`, come out with `pop_ready`.

    Subclasses keep packets in their own queue; `configure(profile)` takes the fields of a
    `LinkProfile` the stage cares about, in place (queued packets are kept).
    """

    name = "stage"

    def __init__(self) -> None:
        self.counters = StageCounters()

    def push(self, packet: bytes, now: float) -> None:
        raise NotImplementedError

    def pop_ready(self, now: float) -> list[bytes]:
        raise NotImplementedError

    def next_due(self) -> float | None:
        raise NotImplementedError

    def queued(self) -> int:
        """Packets inside the stage now."""
        raise NotImplementedError

    def min_hold_s(self) -> float:
        """The least time any packet spends in this stage (a lower bound; default 0)."""
        return 0.0

    def configure(self, profile: LinkProfile) -> None:
        """Take the settings of `profile` that concern this stage (default: none)."""

    def report(self) -> tuple[str, dict[str, Any]] | None:
        """What this stage adds to its direction's `Pipeline.snapshot`: (key, figures), or
        None (default: nothing)."""
        return None


class Instant(Stage):
    """A stage that holds no packet: what enters at `now` is ready at `now`, in order."""

    def __init__(self) -> None:
        super().__init__()
        self._passed: deque[tuple[float, bytes]] = deque()

    def pop_ready(self, now: float) -> list[bytes]:
        return pop_timed(self._passed, now, self.counters)

    def next_due(self) -> float | None:
        return self._passed[0][0] if self._passed else None

    def queued(self) -> int:
        return len(self._passed)


def pop_timed(queue: deque[tuple[float, bytes]], now: float, c: StageCounters) -> list[bytes]:
    """Pop every `(due, packet)` at the head of `queue` with due <= now, counting them."""
    out: list[bytes] = []
    while queue and queue[0][0] <= now:
        packet = queue.popleft()[1]
        out.append(packet)
        c.bytes_out += len(packet)
        c.packets_out += wire_packets(packet)
    return out
