"""One direction of a link: its stages chained in order, the chain itself a stage.

The relay builds the standard chain for a `LinkProfile` (`netem.relay.direction`);
`Pipeline.apply(profile)` reconfigures the same stages in place, so queued packets stay queued.
The pipeline knows its outage, segment, rate and trace stages by class, and the stages above
this wing (a radio's slots, the RRC states, a handover's gap: `netem.nr`) only by name and by
what they report (`Stage.report`), so it never imports them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, cast

from netem.profile import LinkProfile, check_profile
from netem.stages.base import Stage, wire_packets
from netem.stages.gates import Outage, Segment
from netem.stages.rate import Rate
from netem.stages.trace import TraceLink
from netem.traces import Trace


class Gap(Protocol):
    """What `Pipeline.interrupt` needs of its "handover" stage (`HandoverGap`)."""

    def start(self, now: float, seconds: float, mode: str = "hold") -> None: ...


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
        `netem.nr.handover_gap.HandoverGap`. Raises `ProfileError` for a bad mode or duration."""
        gap = cast(Gap, self.stage("handover"))
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
        """Counters of the whole direction and of each stage, plus what is queued now and what
        a stage reports of its own (`Stage.report`)."""
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
            extra = s.report()  # a radio's, the RRC states', a handover's figures
            if extra is not None:
                out[extra[0]] = extra[1]
        return out
