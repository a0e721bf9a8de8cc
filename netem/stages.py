"""Packet stages of the userspace link: small queues that each do one impairment.

This is Mahimahi's design (`delay_queue`, `link_queue`, `loss_queue`): every impairment is a
`Stage` with one interface,

    push(packet, now)      a packet enters the stage at time `now` (seconds, any clock)
    pop_ready(now)         the packets that have left the stage by `now`, in order
    next_due()             when the next packet will leave (None: nothing will on its own)

and a `Pipeline` chains stages into one direction of a link. The pipeline is itself a stage,
so a relay only ever sees push/pop_ready/next_due. Stages never read a clock: the caller
passes `now`, which makes them exact and testable with a fake clock.

A packet moves from one stage to the next at the instant it left (its due time), not when the
relay happened to wake up, so timer lateness is paid once, at the link's exit, never per stage.

A packet is anything whose `len()` is its size on the wire in bytes: `bytes`, or a
`netem.gso.Frame`, the super-packet of an offloading TUN, which also says how many wire packets
it stands for (`segments`); counters and queue limits count wire packets.

Stages built for a `LinkProfile` (in this order): `RrcStage` (holds the first packets after a
quiet spell while the UE's RRC connection resumes or is set up, `netem.rrc`; transparent
without `rrc`), `Outage` gate, `Segment` (splits super-packets where a later stage acts per
wire packet), `RandomLoss`, `GilbertElliottLoss`, `Rate` (serialisation + drop-tail queue),
`TraceLink` (delivery opportunities from a bandwidth trace; idle unless a trace plays), `Slots`
(the NR air interface of `netem.nr`: TDD windows and transport blocks; transparent without a
radio), `Delay` (+ jitter) and `HandoverGap` (holds or drops what would leave the link during a
handover's interruption, `Pipeline.interrupt`; transparent otherwise). `Pipeline.apply(profile)`
reconfigures the same stages in place, so queued packets stay queued.

Every stage belongs to one direction, except what `RrcStage` consults: the RRC state is the
UE's, so the two directions of a link share one `RrcLink` (`share_rrc`, which the relay calls
for each link it carries).
"""

from __future__ import annotations

import bisect
import heapq
import math
import random
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from netem.errors import ProfileError
from netem.gso import Frame, split
from netem.nr import Direction, Occasion
from netem.profile import LinkProfile, check_link, check_profile
from netem.rrc import Promotion, Rrc, RrcSettings, RrcState
from netem.traces import OPPORTUNITY_BYTES, Trace

#: A super-packet is split before a link on which it would be on the wire longer than this:
#: its first segment would otherwise wait for its last. TCP sizes its bursts to ~1 ms of its
#: pacing rate (tcp_tso_autosize), so from ~20 Mbit/s up most stay whole, and a packet is
#: at most 2 ms late for the wire time of the ones sent with it. (tc's netem and tbf on a
#: TSO device serialise a super-packet whole at any rate; at 1 ms instead of 2 the relay
#: splits most of a 100 Mbit/s TCP flow, one write per wire packet.)
SPLIT_ABOVE_S = 0.002

# Pareto jitter: shape 3 has a finite variance; samples are shifted and scaled to mean 0 and
# standard deviation 1, so `jitter_s` is the standard deviation for pareto as for normal.
_PARETO_SHAPE = 3.0
_PARETO_MEAN = _PARETO_SHAPE / (_PARETO_SHAPE - 1.0)
_PARETO_SD = math.sqrt(_PARETO_SHAPE / ((_PARETO_SHAPE - 1.0) ** 2 * (_PARETO_SHAPE - 2.0)))


def wire_packets(packet: Any) -> int:
    """How many packets `packet` is on the wire (a super-packet is several)."""
    return packet.segments if type(packet) is Frame else 1


def _ns(t: float) -> int:
    """A time as whole nanoseconds: the key of an occasion, whichever grid computed it."""
    return round(t * 1e9)


class SharedSlots(Protocol):
    """What a `Slots` stage needs of the cell it shares (`netem.cell.Cell`)."""

    def advance(self, now: float) -> None: ...

    def next_end(self) -> float | None: ...

    def free_share(self, start: float) -> float: ...


def jitter_sd(profile: LinkProfile) -> float:
    """Standard deviation of the per-packet delay that `profile`'s jitter gives.

    Same meaning as netem: for `normal` and `pareto` the jitter is the standard deviation;
    for `uniform` the delay is spread evenly over `delay ± jitter` (sd = jitter / √3).
    """
    if profile.jitter_distribution == "uniform":
        return profile.jitter_s / math.sqrt(3.0)
    return profile.jitter_s


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


class Instant(Stage):
    """A stage that holds no packet: what enters at `now` is ready at `now`, in order."""

    def __init__(self) -> None:
        super().__init__()
        self._passed: deque[tuple[float, bytes]] = deque()

    def pop_ready(self, now: float) -> list[bytes]:
        return _pop_timed(self._passed, now, self.counters)

    def next_due(self) -> float | None:
        return self._passed[0][0] if self._passed else None

    def queued(self) -> int:
        return len(self._passed)


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


def _pop_timed(queue: deque[tuple[float, bytes]], now: float, c: StageCounters) -> list[bytes]:
    """Pop every `(due, packet)` at the head of `queue` with due <= now, counting them."""
    out: list[bytes] = []
    while queue and queue[0][0] <= now:
        packet = queue.popleft()[1]
        out.append(packet)
        c.bytes_out += len(packet)
        c.packets_out += wire_packets(packet)
    return out


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


class RrcLink:
    """The RRC state of one UE, shared by the `RrcStage` of each direction of its link.

    Uplink and downlink packets are both traffic for the gNB's inactivity timer, and a
    downlink packet to a UE that is not connected pays the same promotion as the UE's own
    (paging, then the UE's resume or setup: TS 38.300 §9.2.2.4 and §9.2.5), so one `Rrc`
    machine sees the packets of both directions in time order. Its timers are the profile's
    `rrc` (`configure`; None: always connected). The UE is connected when the link comes up
    (it has just attached) or RRC states are switched on: whoever has the clock says when
    (`start`; the relay does). Without a `start` the UE is connected at its first packet.
    """

    def __init__(self) -> None:
        self.settings: RrcSettings | None = None
        self.machine: Rrc | None = None
        self.stages: list[RrcStage] = []
        self._last = -math.inf  # the latest packet time given to the machine

    def start(self, now: float) -> None:
        """The UE is connected at `now`: the link came up, or RRC states were switched on.
        No-op while the link has no RRC states or its machine already runs."""
        if self.settings is not None and self.machine is None:
            self._last = max(self._last, now)
            self.machine = self.settings.machine(self._last)

    def configure(self, settings: RrcSettings | None) -> None:
        """Take new timers in place: the state follows from the last packet under the new
        ones, and a promotion under way keeps its end. None (always connected) lets every
        packet held for a promotion go at once."""
        if settings == self.settings:
            return
        self.settings = settings
        if settings is None:
            self.machine = None
            for stage in self.stages:
                stage.release()
            return
        if self.machine is not None:
            m = self.machine
            m.inactivity_s, m.idle_after_s = settings.inactivity_s, settings.idle_after_s
            m.resume_s, m.setup_s = settings.resume_s, settings.setup_s

    def admit(self, now: float) -> tuple[float, Promotion | None]:
        """A packet of either direction at `now`: when it may go on, and the promotion it
        started (None: the UE was connected, or a promotion was already under way)."""
        if self.settings is None:
            return now, None
        # The relay reads one monotonic clock for both directions; a caller with two clocks a
        # hair apart must not make the machine refuse a packet.
        t = max(now, self._last)
        self._last = t
        if self.machine is None:
            self.machine = self.settings.machine(t)
        machine = self.machine
        wait = machine.on_packet(t)
        started = machine.promotions.pop() if machine.promotions else None  # (kept bounded)
        return t + wait, started

    def state(self, now: float) -> RrcState | None:
        """The UE's state at `now` (None: this link has no RRC states)."""
        if self.settings is None:
            return None
        if self.machine is None:
            return RrcState.CONNECTED
        return self.machine.state_at(max(now, self._last))

    def counters(self, now: float) -> dict[str, Any] | None:
        """The link's RRC figures: state now, promotions by the state they left, and how many
        a downlink packet started (paging); None when it never had RRC states."""
        promotions = {s.value: 0 for s in (RrcState.INACTIVE, RrcState.IDLE)}
        paging = 0
        for stage in self.stages:
            for state, n in stage.promotions.items():
                promotions[state] += n
            if stage.direction == "downlink":
                paging += sum(stage.promotions.values())
        if self.settings is None and not any(promotions.values()):
            return None
        state = self.state(now)
        return {
            "state": None if state is None else state.value,
            "settings": None if self.settings is None else self.settings.to_dict(),
            "promotions": promotions,
            "paging": paging,
        }


class RrcStage(Stage):
    """Holds the packets that find the UE not RRC-connected until its connection is back.

    The first packet after `inactivity_s` of quiet finds the UE INACTIVE (the gNB suspended
    it, TS 38.331 §5.3.8) and waits `resume_s` (RRC resume, §5.3.13); after a further
    `idle_after_s` it finds it IDLE and waits `setup_s` (random access and RRC setup,
    §5.3.3). Packets that come while a promotion runs wait for its end; later ones pass at
    once. Packets leave in the order they came. The state is its `link`'s, which the other
    direction's stage shares (`share_rrc`).

    First in a pipeline, so the wait adds to every later stage's: the resumed UE's packet then
    queues, is scheduled and propagates as any other. A packet a later stage drops (an outage,
    loss) still counted as traffic, as the UE's connection request does not know its fate.
    """

    name = "rrc"

    def __init__(self, link: RrcLink | None = None, direction: Direction = "uplink") -> None:
        super().__init__()
        self.direction = direction
        self.link = link if link is not None else RrcLink()
        self.link.stages.append(self)
        self._held: deque[tuple[float, bytes]] = deque()  # (may go at, packet)
        self._last_due = -math.inf
        self._seen = -math.inf  # the latest time this stage was given
        #: Promotions this direction's packets started, by the state they found the UE in.
        self.promotions = {s.value: 0 for s in (RrcState.INACTIVE, RrcState.IDLE)}
        self.waited_packets = 0  # wire packets held for a promotion (either direction's)
        self.waited_s = 0.0  # the time they were held for, summed over wire packets

    def configure(self, profile: LinkProfile) -> None:
        self.link.configure(profile.rrc)

    def release(self) -> None:
        """Let every held packet go now (the link has no RRC states any more)."""
        for due, packet in self._held:
            if due > self._seen:
                self.waited_s -= wire_packets(packet) * (due - self._seen)
        self._held = deque((min(due, self._seen), p) for due, p in self._held)
        self._last_due = min(self._last_due, self._seen)

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        n = wire_packets(packet)
        c.packets_in += n
        c.bytes_in += len(packet)
        if self.link.settings is None:  # always connected: the common case, kept short
            self._held.append((now, packet))
            return
        self._seen = max(self._seen, now)
        due, started = self.link.admit(now)
        if started is not None:
            self.promotions[started.from_state.value] += 1
        due = max(due, self._last_due)  # in order, whatever the timers did meanwhile
        self._last_due = due
        if due > now:
            self.waited_packets += n
            self.waited_s += n * (due - now)
        self._held.append((due, packet))

    def pop_ready(self, now: float) -> list[bytes]:
        self._seen = max(self._seen, now)
        return _pop_timed(self._held, now, self.counters)

    def next_due(self) -> float | None:
        return self._held[0][0] if self._held else None

    def queued(self) -> int:
        return len(self._held)

    def rrc_counters(self) -> dict[str, Any]:
        """What this direction's packets met: promotions they started, packets held."""
        return {
            "promotions": dict(self.promotions),
            "waited_packets": self.waited_packets,
            "waited_s": self.waited_s,
        }


def share_rrc(uplink: Pipeline, downlink: Pipeline) -> RrcLink | None:
    """Give the RRC stages of a link's two directions one state machine, that of `uplink`
    (None: the pipelines have no RRC stage). Call before packets flow: the downlink's own
    machine, and its state, are dropped. Raises `ProfileError` if the two profiles' `rrc`
    differ (`check_link`)."""
    check_link(uplink.profile, downlink.profile)
    try:
        up, down = uplink.stage("rrc"), downlink.stage("rrc")
    except KeyError:
        return None
    assert isinstance(up, RrcStage) and isinstance(down, RrcStage)
    if down.link is not up.link:
        if down.queued():
            raise ProfileError("share_rrc: the downlink already holds packets; share first")
        down.link.stages.remove(down)
        down.link = up.link
        up.link.stages.append(down)
    return up.link


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


class RandomLoss(Gate):
    """Drops each wire packet independently with probability `loss`.

    Instead of a draw per packet it draws how many packets pass before the next loss (a
    geometric number, which is the same process), so a super-packet costs one comparison.
    """

    name = "loss"

    def __init__(self, loss: float = 0.0, seed: int | str = 0) -> None:
        super().__init__()
        self._rng = random.Random(f"{seed}:{self.name}")
        self.loss = 0.0
        self._skip = 0  # wire packets that pass before the next loss
        self._set(loss)

    def _set(self, loss: float) -> None:
        if loss != self.loss:
            self.loss = loss
            self._skip = self._gap()  # memoryless: a fresh draw is as good as the old one

    def _gap(self) -> int:
        p = self.loss
        if p <= 0.0 or p >= 1.0:  # (no loss: never asked; certain loss: no gaps)
            return 0
        # P(gap = k) = (1-p)^k p; 1 - random() is in (0, 1], so the log is finite.
        return int(math.log(1.0 - self._rng.random()) / math.log1p(-p))

    def configure(self, profile: LinkProfile) -> None:
        # A Gilbert-Elliott model replaces the independent loss (netem's `loss gemodel`).
        self._set(0.0 if profile.gilbert_elliott is not None else profile.loss)

    def losses(self, n: int) -> list[int]:
        if self.loss <= 0.0:
            return []
        if self._skip >= n:
            self._skip -= n
            return []
        out: list[int] = []
        i = self._skip
        while i < n:
            out.append(i)
            i += 1 + self._gap()
        self._skip = i - n
        return out


class GilbertElliottLoss(Gate):
    """Bursty loss: a good/bad Markov chain stepped once per packet (netem's gemodel)."""

    name = "burst_loss"

    def __init__(self, model: Any = None, seed: int | str = 0) -> None:
        super().__init__()
        self.model = model
        self.bad = False
        self._rng = random.Random(f"{seed}:{self.name}")

    def configure(self, profile: LinkProfile) -> None:
        self.model = profile.gilbert_elliott
        if self.model is None:
            self.bad = False

    def losses(self, n: int) -> list[int]:
        m = self.model
        if m is None:
            return []
        rng = self._rng
        out: list[int] = []
        bad = self.bad
        for i in range(n):
            if rng.random() < (m.bad_loss if bad else m.good_loss):
                out.append(i)
            # Step the chain after deciding, so the first packet sees the good state.
            if bad:
                if rng.random() < m.r:
                    bad = False
            elif rng.random() < m.p:
                bad = True
        self.bad = bad
        return out


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
        return _pop_timed(self._left, now, self.counters)

    def next_due(self) -> float | None:
        if self._left:
            return self._left[0][0]
        if self._queue and self._head_finish < math.inf:
            return self._head_finish
        return None

    def queued(self) -> int:
        return len(self._queue) + len(self._left)


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
        return _pop_timed(self._left, now, self.counters)

    def next_due(self) -> float | None:
        if self._left:
            return self._left[0][0]
        if self._queue:
            return self._next if self._next is not None else self._end
        return None

    def queued(self) -> int:
        return len(self._queue) + len(self._left)


class Slots(Stage):
    """Sends only in the occasions of a TDD pattern, each carrying up to its transport block.

    The air link of one NR direction (`netem.nr`): `occasions` are the windows of one period
    that carry data, with their capacity in bytes; the pattern repeats every `period_s` from
    `epoch_s`. Packets are served in order; one larger than an occasion continues in the next
    ones, and a packet leaves at the end of the occasion that carried its last byte, as a
    transport block is decoded at the end of its slot. The buffer for the UE and direction
    is drop-tail at the profile's `queue_packets` and at the radio's `buffer_bytes`.

    Grants (`access`):
    - "ideal" (the downlink, where the gNB holds the data, and a configured grant, whose
      occasions are given): a packet may use an occasion that starts at least `lead_s` after
      it arrived (K2 and processing; 0 for a configured grant).
    - "sr" (a UE that must ask): data that no buffer status report (BSR) has announced
      triggers a scheduling request in the first SR window (`sr_windows`) that starts after
      it, unless a PUSCH goes first and carries the BSR. The SR brings a first grant of
      `first_grant_bytes` in the first occasion `grant_delay_s` after the SR window; every
      PUSCH carries a BSR of what had arrived when it started, and the gNB grants what BSRs
      announced in the occasions `grant_delay_s` after it decoded them (TS 38.321 §5.4.4-5).
      A PUSCH carries data that arrived before it started.

    HARQ: each transport block fails with probability `bler` and is sent again in the first
    occasion that starts `harq_s` after the failed one ended and has the block's bytes free
    (they are taken from its new data), at most `max_retx` times; a block that still fails is
    a residual loss (its BSR is lost too, and what it announced is asked for again). With
    RLC-AM (`rlc_am`, TS 38.322) every packet that had bytes in it comes back into the buffer
    `rlc_status_s` later (the receiver's status report) and is sent again, at most
    `rlc_max_retx` times (then it is lost: out of coverage, BLER near 1, a packet would
    otherwise come back for ever); with RLC-UM it is lost. Packets leave in order
    (`in_order`), as PDCP delivers them: one held back by a retransmission, or by RLC, holds
    back those behind it; without, each leaves when decoded.
    """

    name = "slots"

    def __init__(
        self,
        occasions: Sequence[Occasion] = (),
        period_s: float = 0.0,
        lead_s: float = 0.0,
        epoch_s: float = 0.0,
        direction: Direction = "uplink",
        seed: int | str = 0,
    ) -> None:
        super().__init__()
        self.direction = direction  # whose windows a radio profile gives this stage
        self.occasions: list[Occasion] = []
        self.period_s = period_s
        self.tdd_period_s = period_s  # the TDD pattern's (the grid may span several)
        self.lead_s = lead_s
        self.epoch_s = epoch_s
        # (arrival, packet, bytes that had arrived up to and with it)
        self._queue: deque[tuple[float, bytes, int]] = deque()
        self._head_left = 0  # bytes of the head packet still to send
        self._left: deque[tuple[float, bytes]] = deque()
        self._cursor = (0, 0)  # (period, index) of the next occasion not yet used
        self.queue_packets: int | None = None  # drop-tail limit of the gNB's buffer
        self.buffer_bytes: int | None = None  # the same in bytes (the radio's `buffer_bytes`)
        self._queued_packets = 0
        self.bler, self.max_retx, self.harq_s = 0.0, 0, 0.0
        self._rng = random.Random(f"{seed}:{self.name}")
        # Bytes of occasions that retransmissions have taken, by occasion.
        self._reserved: dict[int, int] = {}  # occasion start (ns) -> bytes
        self._head_floor = 0.0  # a retransmitted block that held some of the head's bytes
        self._head_lost: float | None = None  # when a block with some of the head was lost
        self._last_exit = -math.inf
        self._used_until = -math.inf  # just after the start of the last occasion visited
        self.blocks = 0
        # Blocks by the retransmissions they needed; the last entry counts those lost.
        self.retransmissions: list[int] = [0]
        # Scheduling requests and grants (access "sr"); byte counts are cumulative.
        self.access = "ideal"
        self.sr_windows: list[tuple[float, float]] = []
        self.grant_delay_s = 0.0
        self.first_grant_bytes = 0
        self._arrived = 0  # bytes that entered the buffer
        self._sent = 0  # bytes that left it in a transport block
        self._announced = 0  # bytes a BSR announced (decoded or on its way)
        self._granted = 0  # bytes the gNB has granted so far (announced and decoded)
        self._reports: list[tuple[float, int]] = []  # (grantable from, bytes announced)
        self._first_grant: float | None = None  # start of the occasion an SR was granted
        self._sr_floor = -math.inf  # no SR before this (a lost BSR is noticed after it)
        self.scheduling_requests = 0
        #: The cell whose occasions this UE shares with others (`netem.cell.Cell`), if any.
        self.cell: SharedSlots | None = None
        # RLC and PDCP.
        self.rlc_am, self.rlc_status_s, self.in_order = False, 0.0, True
        self._recovering: list[tuple[float, bytes]] = []  # (back in the buffer at, packet)
        self.rlc_max_retx = 32
        self._rlc_sent: dict[int, int] = {}  # times RLC-AM sent a packet again, by id
        # PDCP: each packet's place in the order it came (by id), and those decoded before
        # an earlier one (None: one that was lost, which nothing waits for).
        self._order: dict[int, int] = {}
        self._came = 0
        self._next = 0  # the place of the next packet to deliver in order
        self._reorder: dict[int, tuple[float, bytes] | None] = {}
        self._failed_at = 0.0  # when the last block that failed every try was given up
        self.recovered = 0  # packets RLC-AM sent again
        if occasions:
            self.set_occasions(occasions, period_s, lead_s)

    def set_occasions(self, occasions: Sequence[Occasion], period_s: float, lead_s: float) -> None:
        """Switch to another slot grid or capacity in place (MCS, PRBs, pattern changes).

        Queued packets stay; they continue in the new grid's first usable occasion.
        """
        self.occasions = sorted(occasions, key=lambda o: o.start_s)
        self.period_s, self.lead_s = period_s, lead_s
        self._reserved.clear()  # (occasions of the old grid)
        # Cursors of the old grid mean nothing in the new one: on from what was used.
        self._cursor = (0, 0)
        if self.occasions:
            after = self._used_until
            if self._queue:
                after = max(after, self._queue[0][0] + self._lead())
            self._cursor = self._first_at_or_after(after)

    def set_access(
        self,
        access: str,
        sr_windows: Sequence[tuple[float, float]] = (),
        grant_delay_s: float = 0.0,
        first_grant_bytes: int = 0,
    ) -> None:
        """How packets get occasions: "ideal" (after `lead_s`) or "sr" (see the class)."""
        if access == "sr" and self.access != "sr":
            # What waits now is announced: the gNB grants it from its next occasion on.
            self._announced = self._granted = self._arrived
            self._reports.clear()
            self._first_grant = None
        self.access = access
        self.sr_windows = sorted(sr_windows)
        self.grant_delay_s = grant_delay_s
        self.first_grant_bytes = first_grant_bytes

    def configure(self, profile: LinkProfile) -> None:
        radio = profile.radio
        self.queue_packets = profile.queue_packets
        if radio is None:
            self._radio_off()
            return
        grid = radio.grid(self.direction)
        self.buffer_bytes = radio.buffer_bytes
        self.tdd_period_s = radio.pattern().period_s
        self.rlc_am, self.rlc_status_s = radio.rlc == "am", radio.rlc_status_s
        self.rlc_max_retx = radio.rlc_max_retx
        self.in_order = radio.in_order
        self.set_access(grid.access, grid.sr_windows, grid.grant_delay_s, grid.first_grant_bytes)
        self.set_occasions(grid.occasions, grid.period_s, grid.lead_s)
        self.set_harq(radio.bler, radio.max_retx, radio.harq_s)

    def _radio_off(self) -> None:
        """A radio switched off (the link test's neutral moment, a `set` without `radio`):
        what waited for a slot and what RLC was sending again are decoded now, so PDCP
        delivers them, and what it held back behind them, in their order. Let go any other
        way, their places in that order would stay open, and every packet of the next radio
        would wait in `_reorder` for them, for good."""
        waiting = [(t, p) for t, p, _ in self._queue] + self._recovering
        self._queue.clear()
        self._recovering.clear()
        for t, packet in waiting:
            self._decoded(t, packet, id(packet))
        self.occasions = []
        self._queued_packets = 0
        self._rlc_sent.clear()
        self.set_access("ideal")

    def set_harq(self, bler: float, max_retx: int, harq_s: float) -> None:
        self.bler, self.max_retx, self.harq_s = bler, max_retx, harq_s
        self.retransmissions += [0] * max(0, max_retx + 2 - len(self.retransmissions))

    def radio_counters(self) -> dict[str, Any]:
        """What the air interface did: blocks, their HARQ tries, SRs and RLC resends."""
        return {
            "blocks": self.blocks,
            # blocks by the retransmissions they needed; the last entry: given up on
            "retransmissions": list(self.retransmissions),
            "scheduling_requests": self.scheduling_requests,
            "rlc_recovered": self.recovered,
            "rlc_given_up": self.counters.dropped_packets.get("rlc", 0),
        }

    def _lead(self) -> float:
        return 0.0 if self.access == "sr" else self.lead_s

    def _occasion(self, cursor: tuple[int, int]) -> tuple[float, float, int]:
        n, k = cursor
        o = self.occasions[k]
        base = self.epoch_s + n * self.period_s
        return base + o.start_s, base + o.end_s, o.capacity_bytes

    def _step(self, cursor: tuple[int, int]) -> tuple[int, int]:
        n, k = cursor
        return (n, k + 1) if k + 1 < len(self.occasions) else (n + 1, 0)

    def _first_at_or_after(self, t: float) -> tuple[int, int]:
        """The first occasion that starts at or after `t` (never one already used)."""
        t = max(t, self.epoch_s)
        n = math.floor((t - self.epoch_s) / self.period_s)
        cursor = (n, 0)
        while self._occasion(cursor)[0] < t - 1e-12:
            cursor = self._step(cursor)
        return max(cursor, self._cursor)

    def _sr_window(self, t: float) -> tuple[float, float]:
        """The first SR window that starts at or after `t`."""
        n = math.floor((t - self.epoch_s) / self.period_s)
        while True:
            base = self.epoch_s + n * self.period_s
            for start, end in self.sr_windows:
                if base + start >= t - 1e-12:
                    return base + start, base + end
            n += 1

    def _unannounced_since(self) -> float | None:
        """When the oldest byte no BSR has announced arrived (None: all announced)."""
        if self._arrived <= self._announced:
            return None
        since = None
        for arrival, _, upto in reversed(self._queue):  # the unannounced are the newest
            if upto <= self._announced:
                break
            since = arrival
        return since  # (None: what was not announced has left with a first grant)

    def _grant(self, start: float) -> int:
        """Bytes the gNB grants this UE in the occasion that starts at `start` ("sr")."""
        if self._reports:
            ready = [r for r in self._reports if r[0] <= start + 1e-12]
            if ready:
                self._granted = max(self._granted, *(upto for _, upto in ready))
                self._reports = [r for r in self._reports if r[0] > start + 1e-12]
        grant = max(0, self._granted - self._sent)
        if self._first_grant is not None and self._first_grant <= start + 1e-12:
            grant = max(grant, self.first_grant_bytes)
            self._first_grant = None
        return grant

    def _request(self, before: float) -> None:
        """Send the scheduling request that falls before the occasion starting at `before`."""
        if self.access != "sr" or self._first_grant is not None:
            return
        since = self._unannounced_since()
        if since is None:
            return
        sr_start, sr_end = self._sr_window(max(since, self._sr_floor))
        if sr_start < before - 1e-12:
            self.scheduling_requests += 1
            self._first_grant = self._occasion(
                self._first_at_or_after(sr_end + self.grant_delay_s)
            )[0]

    def _advance(self, now: float) -> None:
        if self._recovering:
            self._readmit(now)
        if self.cell is not None:
            self.cell.advance(now)  # every UE of the cell, occasion by occasion
            return
        q = self._queue
        while q and self.occasions:
            start, end, capacity = self._occasion(self._cursor)
            self._request(start)
            if end > now:
                return
            if self.access != "sr" and q[0][0] + self.lead_s > start + 1e-12:
                # The head was not there in time for this occasion: on to its first one.
                self._cursor = self._first_at_or_after(q[0][0] + self.lead_s)
                continue
            self._cursor = self._step(self._cursor)
            room = capacity - self._reserved.pop(_ns(start), 0)  # what retransmissions took
            self._serve(start, end, min(room, self._demand(start)))

    def _demand(self, start: float) -> int:
        """Bytes this UE would send in the occasion starting at `start`, room permitting.

        Call once per occasion, in order (it takes the grants the gNB made for it).
        """
        q = self._queue
        if not q:
            return 0
        if self.access != "sr":
            return self._arrived_by(start - self.lead_s) - self._sent
        grant = self._grant(start)
        return 0 if grant <= 0 else min(grant, self._arrived_by(start) - self._sent)

    def _arrived_by(self, t: float) -> int:
        """Bytes that had entered the buffer by `t` (those already sent included)."""
        for arrival, _, cumulative in reversed(self._queue):  # the newest arrived last
            if arrival <= t + 1e-12:
                return cumulative
        return self._sent

    def _serve(self, start: float, end: float, budget: int) -> None:
        """Send `budget` bytes of the buffer (in order) in the occasion `start`..`end`."""
        self._used_until = start + 1e-9
        q = self._queue
        if budget <= 0 or not q:
            return
        free = budget
        completing: list[tuple[bytes, float, bool]] = []
        partial = False
        while q and budget > 0:
            if self._head_left <= budget:
                budget -= self._head_left
                packet = q.popleft()[1]
                self._queued_packets -= wire_packets(packet)
                completing.append((packet, self._head_floor, self._head_lost))
                self._head_floor, self._head_lost = 0.0, None
                self._head_left = len(q[0][1]) if q else 0
            else:
                self._head_left -= budget
                budget = 0
                partial = True
        sent = free - budget
        ok_at = self._deliver_block(end, sent)
        self._sent += sent
        if self.access == "sr":
            self._report(start, end, ok_at)
        for packet, floor, lost_at in completing:
            if lost_at is not None or ok_at is None:
                given_up = self._failed_at if lost_at is None else lost_at
                if self.rlc_am and self._rlc_sent.get(id(packet), 0) < self.rlc_max_retx:
                    self._recover(packet, given_up + self.rlc_status_s)
                else:
                    reason = "rlc" if self.rlc_am else "harq"
                    self.counters.drop(reason, len(packet), wire_packets(packet))
                    self._rlc_sent.pop(id(packet), None)
                    self._decoded(0.0, None, id(packet))
                continue
            self._rlc_sent.pop(id(packet), None)
            self._decoded(max(ok_at, floor), packet, id(packet))
        if partial:
            if ok_at is None:
                if self._head_lost is None:
                    self._head_lost = self._failed_at
            else:
                self._head_floor = max(self._head_floor, ok_at)

    def _decoded(self, at: float, packet: bytes | None, key: int) -> None:
        """`packet` is whole at the receiver at `at` (None: it was lost): PDCP delivers it,
        in order of arrival or, without `in_order`, at once."""
        place = self._order.pop(key, None)
        if not self.in_order or place is None:
            if packet is not None:
                bisect.insort(self._left, (at, packet), key=lambda e: e[0])
            return
        self._reorder[place] = None if packet is None else (at, packet)
        while self._next in self._reorder:
            ready = self._reorder.pop(self._next)
            self._next += 1
            if ready is not None:
                t = max(ready[0], self._last_exit)
                self._last_exit = t
                self._left.append((t, ready[1]))

    def _recover(self, packet: bytes, at: float) -> None:
        """RLC-AM: `packet` was lost in a block; it is back in the buffer at `at`."""
        self.recovered += 1
        self._rlc_sent[id(packet)] = self._rlc_sent.get(id(packet), 0) + 1
        bisect.insort(self._recovering, (at, packet), key=lambda e: e[0])

    def _readmit(self, now: float) -> None:
        """Put what RLC sends again back into the buffer once its status report came: next
        after the packet on the air, ahead of new data, as RLC-AM's retransmissions go first
        (TS 38.322 §5.2.3.1.1; MAC serves them before new data). At the back of a long
        buffer it would hold up every packet behind it in PDCP's order until the buffer had
        drained (a saturated UE at BLER 30% stopped delivering for good)."""
        while self._recovering and self._recovering[0][0] <= now:
            at, packet = self._recovering.pop(0)
            size = len(packet)
            self._queued_packets += wire_packets(packet)
            self._arrived += size
            q = self._queue
            if not q:
                self._head_left = size
                self._cursor = self._first_at_or_after(at + self._lead())
                q.append((at, packet, self._arrived))
                continue
            # Behind the head, as if it had been there as early as the head: its bytes count
            # as buffered for every occasion from now on (the earlier ones are past), and
            # every later entry has entered the buffer `size` bytes later than it had.
            head = q.popleft()
            rest = [(t, p, cumulative + size) for t, p, cumulative in q]
            q.clear()
            q.append(head)
            q.append((head[0], packet, head[2] + size))
            q.extend(rest)

    def _report(self, start: float, end: float, ok_at: float | None) -> None:
        """The BSR of the PUSCH at `start`: what had arrived by then, decoded at `ok_at`."""
        upto = max(self._sent, self._arrived_by(start))
        if ok_at is None:
            # Lost with its block: what it announced stays unannounced, and the UE asks
            # again once it could have noticed.
            self._sr_floor = end
            return
        if upto > self._announced:
            self._announced = upto
        self._reports.append((ok_at + self.grant_delay_s, upto))

    def _free(self, cursor: tuple[int, int]) -> int:
        """Bytes of this UE's block in the occasion at `cursor` that no retransmission has
        reserved: in a shared cell, what the cell's PRBs left free by every UE's reservations
        give this UE (`Cell.free_share`), so two UEs' retransmissions never overbook it."""
        start, _, capacity = self._occasion(cursor)
        if self.cell is not None:
            return int(self.cell.free_share(start) * capacity + 1e-9)
        return capacity - self._reserved.get(_ns(start), 0)

    def _deliver_block(self, end: float, size: int) -> float | None:
        """When the block of `size` bytes sent in the occasion ending at `end` is decoded
        (None: never). A retransmission takes `size` bytes of a later occasion that has them
        free; the rest of that occasion still carries new data."""
        self.blocks += 1
        if self.bler <= 0.0:
            self.retransmissions[0] += 1
            return end
        t = end
        for attempt in range(self.max_retx + 1):
            if attempt:
                cursor = self._first_at_or_after(t + self.harq_s)
                while self._free(cursor) < size:
                    cursor = self._step(cursor)
                key = _ns(self._occasion(cursor)[0])
                self._reserved[key] = self._reserved.get(key, 0) + size
                t = self._occasion(cursor)[1]
            if self._rng.random() >= self.bler:
                self.retransmissions[attempt] += 1
                return t
        self.retransmissions[self.max_retx + 1] += 1
        self._failed_at = t
        return None

    def push(self, packet: bytes, now: float) -> None:
        c = self.counters
        c.packets_in += wire_packets(packet)
        c.bytes_in += len(packet)
        if not self.occasions:
            self._left.append((now, packet))
            return
        self._advance(now)
        n = wire_packets(packet)
        if self.queue_packets is not None and self._queued_packets + n > self.queue_packets:
            c.drop("queue_full", len(packet), n)
            return
        if (
            self.buffer_bytes is not None
            and self._arrived - self._sent + len(packet) > self.buffer_bytes
        ):
            c.drop("queue_full", len(packet), n)
            return
        self._queued_packets += n
        if not self._queue:
            self._head_left = len(packet)
            self._cursor = self._first_at_or_after(now + self._lead())
        self._arrived += len(packet)
        self._queue.append((now, packet, self._arrived))
        self._order[id(packet)] = self._came
        self._came += 1

    def pop_ready(self, now: float) -> list[bytes]:
        self._advance(now)
        return _pop_timed(self._left, now, self.counters)

    def next_due(self) -> float | None:
        if self._left:
            return self._left[0][0]
        if self._queue:
            if self.cell is not None:
                return self.cell.next_end()
            return self._occasion(self._cursor)[1]
        if self._recovering:
            return self._recovering[0][0]
        return None

    def queued(self) -> int:
        return len(self._queue) + len(self._left) + len(self._recovering) + len(self._reorder)


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
            return _pop_timed(self._fifo, now, self.counters)
        out: list[bytes] = []
        heap = self._heap
        while heap and heap[0][0] <= now:
            packet = heapq.heappop(heap)[2]
            out.append(packet)
            self.counters.bytes_out += len(packet)
            self.counters.packets_out += wire_packets(packet)
        # Packets still in the FIFO from before a switch to `reorder` leave too.
        return out + _pop_timed(self._fifo, now, self.counters) if self._fifo else out

    def next_due(self) -> float | None:
        if self._heap:
            return self._heap[0][0]
        return self._fifo[0][0] if self._fifo else None

    def queued(self) -> int:
        return len(self._fifo) + len(self._heap)


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
        return _pop_timed(self._passed, now, self.counters)

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


class Pipeline(Stage):
    """One direction of a link: stages chained in order, itself usable as a stage.

    A packet that leaves stage i at time t enters stage i+1 at time t (not at the caller's
    `now`), so the chain is exact however late `pop_ready` is called.
    """

    name = "pipeline"

    def __init__(self, stages: Sequence[Stage], profile: LinkProfile | None = None) -> None:
        super().__init__()
        if not stages:
            raise ValueError("a pipeline needs at least one stage")
        self.stages: list[Stage] = list(stages)
        self.profile = profile if profile is not None else LinkProfile()
        self._handoffs: list[tuple[Stage, float]] = []
        self._plan_handoffs()
        self._deadlines: tuple[float | None, float | None] | None = None

    @classmethod
    def from_profile(
        cls, profile: LinkProfile, seed: int | str = 0, direction: Direction = "uplink"
    ) -> Pipeline:
        """The standard chain for a `LinkProfile`; `seed` makes loss and jitter reproducible.

        `direction` says which windows of a radio (`profile.radio`) this pipeline sends in.
        Its RRC stage has a state machine of its own until `share_rrc` pairs it with the
        other direction's.
        """
        check_profile(profile)
        rate = Rate()
        trace = TraceLink()
        segment = Segment()
        slots = Slots(direction=direction, seed=seed)
        pipeline = cls(
            [
                RrcStage(direction=direction),
                Outage(),
                segment,
                RandomLoss(seed=seed),
                GilbertElliottLoss(seed=seed),
                rate,
                trace,
                slots,
                Delay(seed=seed),
                HandoverGap(),
            ],
            profile,
        )
        for stage in pipeline.stages:
            stage.configure(profile)
        pipeline._plan_handoffs()

        # When a trace ends on its own, the profile's rate applies again.
        def trace_ended() -> None:
            rate.set_rate(rate.profile_rate_bps, suspended=False)
            segment.tracing = False

        trace.on_end = trace_ended
        return pipeline

    def stage(self, name: str) -> Stage:
        for s in self.stages:
            if s.name == name:
                return s
        raise KeyError(f"no stage named {name!r} (stages: {[s.name for s in self.stages]})")

    def apply(self, profile: LinkProfile) -> None:
        """Switch to `profile` in place: queued packets stay, nothing is flushed or paused."""
        check_profile(profile)
        for s in self.stages:
            s.configure(profile)
        self.profile = profile
        self._plan_handoffs()
        self._deadlines = None

    def outage(self, now: float, seconds: float) -> None:
        """Drop every packet entering this direction for `seconds` from `now`."""
        gate = self.stage("outage")
        assert isinstance(gate, Outage)
        gate.start(now, seconds)

    def interrupt(self, now: float, seconds: float, mode: str = "hold") -> None:
        """A handover's interruption from `now` for `seconds`: packets that would leave this
        direction meanwhile are held until its end ("hold") or dropped ("drop"); see
        `HandoverGap`. Raises `ProfileError` for a bad mode or duration."""
        gap = self.stage("handover")
        assert isinstance(gap, HandoverGap)
        gap.start(now, seconds, mode)
        # The gap moves the exit of whatever it holds: the cached deadlines are stale.
        self._deadlines = None

    def play_trace(self, trace: Trace | None, now: float, loop: bool = False) -> None:
        """Let `trace` set the rate from `now` (None: stop it; the profile's rate returns)."""
        rate, link, segment = self.stage("rate"), self.stage("trace"), self.stage("segment")
        assert isinstance(rate, Rate) and isinstance(link, TraceLink)
        assert isinstance(segment, Segment)
        segment.tracing = trace is not None
        self._deadlines = None
        # Packets already in the rate queue keep their place: with the rate suspended they move
        # on to the trace queue at once.
        if trace is None:
            link.stop(now)
            rate.set_rate(rate.profile_rate_bps, suspended=False)
        else:
            rate.set_rate(rate.profile_rate_bps, suspended=True)
            link.play(trace, now, loop)

    def push(self, packet: bytes, now: float) -> None:
        self.counters.packets_in += wire_packets(packet)
        self.counters.bytes_in += len(packet)
        self.stages[0].push(packet, now)
        self._deadlines = None

    def pop_ready(self, now: float) -> list[bytes]:
        self._deadlines = None
        stages = self.stages
        for i in range(len(stages) - 1):
            stage, following = stages[i], stages[i + 1]
            due = stage.next_due()
            while due is not None and due <= now:
                for packet in stage.pop_ready(due):
                    following.push(packet, due)
                due = stage.next_due()
        out = stages[-1].pop_ready(now)
        c = self.counters
        for packet in out:
            c.packets_out += wire_packets(packet)
            c.bytes_out += len(packet)
        return out

    def next_due(self) -> float | None:
        best: float | None = None
        for s in self.stages:
            due = s.next_due()
            if due is not None and (best is None or due < best):
                best = due
        return best

    def next_handoff(self) -> float | None:
        """The latest time `pop_ready` may run without making any packet leave late.

        A hand-off between stages is exact whenever it is handled (the packet enters the next
        stage at its due time), so it may wait as long as the stages after it hold every
        packet anyway: on a link with a 5 ms delay a rate stage's hand-offs can be batched
        over 5 ms instead of waking the relay once per packet.
        """
        best: float | None = None
        for stage, hold in self._handoffs:
            due = stage.next_due()
            if due is not None:
                due += hold
                if best is None or due < best:
                    best = due
        return best

    def _plan_handoffs(self) -> None:
        """Each stage but the last, with the least time the stages after it hold a packet."""
        after, hold = [], 0.0
        for stage in reversed(self.stages[1:]):
            hold += stage.min_hold_s()
            after.append(hold)
        self._handoffs = list(zip(self.stages[:-1], reversed(after), strict=True))

    def deadlines(self) -> tuple[float | None, float | None]:
        """(`next_handoff()`, `next_exit()`), kept until the pipeline changes.

        A relay asks for both on every wake-up, for both directions, and most wake-ups
        concern one direction only; the other's answer has not changed.
        """
        if self._deadlines is None:
            self._deadlines = (self.next_handoff(), self.next_exit())
        return self._deadlines

    def next_exit(self) -> float | None:
        """The earliest time a packet may leave the pipeline, as far as known now.

        `next_due` also counts hand-offs between stages; those are exact even if handled
        late, so a caller may wake for them lazily and precisely only for `next_exit`. But a
        hand-off due at `t` whose later stages hold a packet `hold` at least can make that
        packet leave at `t + hold` (a fixed delay holds it exactly that long): that is a
        departure too, and waking late for it would send late.
        """
        best = self.stages[-1].next_due()
        for stage, hold in self._handoffs:
            due = stage.next_due()
            if due is not None:
                due += hold
                if best is None or due < best:
                    best = due
        return best

    def queued(self) -> int:
        return sum(s.queued() for s in self.stages)

    def snapshot(self) -> dict[str, Any]:
        """Counters of the whole direction and of each stage, plus what is queued now."""
        total = self.counters.to_dict()
        for s in self.stages:
            for key in ("dropped_packets", "dropped_bytes"):
                for reason, n in getattr(s.counters, key).items():
                    total[key][reason] = total[key].get(reason, 0) + n
        out = {
            "total": total,
            "queued": self.queued(),
            "stages": {s.name: s.counters.to_dict() for s in self.stages},
            "profile": self.profile.to_dict(),
        }
        for s in self.stages:
            if isinstance(s, Slots) and s.occasions:
                out["radio"] = s.radio_counters()
            elif isinstance(s, RrcStage) and (s.link.settings is not None or s.waited_packets):
                out["rrc"] = s.rrc_counters()
            elif isinstance(s, HandoverGap) and s.gaps:
                out["handover"] = s.handover_counters()
        return out
