"""The RRC states as stages: `RrcStage` holds the first packets after a quiet spell while the
UE's connection resumes or is set up (the state machine of `netem.nr.rrc`).

Every stage belongs to one direction, except what `RrcStage` consults: the RRC state is the
UE's, so the two directions of a link share one `RrcLink` (`share_rrc`, which the relay calls
for each link it carries). Transparent without a profile's `rrc`.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

from netem.directions import Direction
from netem.errors import ProfileError
from netem.nr.rrc import Promotion, Rrc, RrcSettings, RrcState
from netem.profile import LinkProfile, check_link
from netem.stages.base import Stage, pop_timed, wire_packets
from netem.stages.pipeline import Pipeline


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
        return pop_timed(self._held, now, self.counters)

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

    def report(self) -> tuple[str, dict[str, Any]] | None:
        if self.link.settings is None and not self.waited_packets:
            return None
        return "rrc", self.rrc_counters()


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
