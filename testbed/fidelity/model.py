"""A case's probes: when they are sent, and what the link's own stages do to them on a fake
clock (`model_delays`), packet by packet, without namespaces or a relay.

`testbed fidelity` measures real packets through the relay (`testbed.fidelity.measure`); the
fake-clock run is the same pipelines (`netem.relay.direction.build_pipeline`) driven by the
probe schedule, so the test suite can judge many probes in a second and show that changing a
field of a case's radio misses a published figure.

A probe's phase against the slot grid: every probe is sent at `k * interval` plus a uniform
draw over one TDD period. A real UE's application clock drifts against the gNB's slot grid;
on one host the prober and the grid share a clock, and probes every 10 ms over a 5 ms
pattern would lock onto one phase (three runs gave uplink medians of 12.6, 14.0 and 16.4 ms).
"""

from __future__ import annotations

import math
import random
import struct
from dataclasses import dataclass, field
from typing import Any

from netem.directions import Direction
from netem.nr.radio import Radio
from netem.profile import LinkProfile
from netem.relay.direction import build_pipeline
from testbed.fidelity.case import Probe

_SEQ = struct.Struct("!I")
#: IPv4 and UDP headers: a probe of `size` bytes of payload is this much more on the air.
HEADERS = 28


def schedule(probe: Probe, period_s: float, seed: int) -> list[float]:
    """Send times (s from a start on a TDD period's boundary) of `probe.count` probes: at
    the source's phase in the period (`probe.phase_s`), or uniform over it."""
    rng = random.Random(f"fidelity:{seed}")
    lo, hi = probe.phase_s or (0.0, min(period_s, probe.interval_s * 0.9))
    return [k * probe.interval_s + rng.uniform(lo, hi) for k in range(probe.count)]


def aligned(t: float, period_s: float) -> float:
    """The first boundary of the slot grid's period at or after `t` (the grid starts at 0)."""
    return math.ceil(t / period_s - 1e-9) * period_s


def profile_of(radio: Radio, wired_ms: float) -> LinkProfile:
    """A direction of the case's link: its radio and the wired path beyond it."""
    return LinkProfile(radio=radio, delay_s=wired_ms / 1000.0, queue_packets=10_000)


@dataclass
class Delays:
    """What one measure's probes took (ms, in send order; None: lost) and the radio's
    counters of the direction(s) they crossed."""

    ms: list[float | None]
    counters: dict[str, Any] = field(default_factory=dict)
    #: What the host's relay adds with no radio (ms), subtracted from `ms` (0: a fake clock).
    baseline_ms: float = 0.0

    @property
    def delivered(self) -> list[float]:
        return [d for d in self.ms if d is not None]


def _through(
    profile: LinkProfile, direction: Direction, sends: list[float], size: int, seed: int
) -> tuple[list[float | None], dict[str, Any]]:
    """Exit times of packets pushed at `sends` through one direction's pipeline."""
    pipeline = build_pipeline(profile, seed, direction)
    exits: list[float | None] = [None] * len(sends)
    order = sorted(range(len(sends)), key=lambda i: sends[i])
    pad = bytes(max(0, size + HEADERS - _SEQ.size))

    def drain(until: float) -> None:
        while (due := pipeline.next_due()) is not None and due <= until:
            for packet in pipeline.pop_ready(due):
                exits[_SEQ.unpack_from(packet)[0]] = due

    for i in order:
        drain(sends[i])
        pipeline.push(_SEQ.pack(i) + pad, sends[i])
    drain(float("inf"))
    slots = pipeline.stage("slots")
    counters = slots.radio_counters() if hasattr(slots, "radio_counters") else {}
    return exits, counters


def model_delays(
    radio: Radio, probe: Probe, measure: str, wired_ms: float = 0.0, seed: int = 0
) -> Delays:
    """The delays (ms) of `probe` in `measure` (a direction, or "rtt": uplink then downlink
    to an echo at the far end) through the stages of `radio`, on a fake clock."""
    profile = profile_of(radio, wired_ms)
    period = radio.pattern().period_s
    start = aligned(1.0, period)
    sends = [start + t for t in schedule(probe, period, seed)]
    if measure != "rtt":
        exits, counters = _through(profile, measure, sends, probe.size, seed)  # type: ignore[arg-type]
        return Delays([_ms(e, s) for e, s in zip(exits, sends, strict=True)], counters)
    up, up_counters = _through(profile, "uplink", sends, probe.size, seed)
    back = [s for s in up if s is not None]
    down, down_counters = _through(profile, "downlink", back, probe.size, seed + 1)
    it = iter(down)
    out: list[float | None] = []
    for e, s in zip(up, sends, strict=True):
        out.append(None if e is None else _ms(next(it), s))
    return Delays(out, {"uplink": up_counters, "downlink": down_counters})


def _ms(exit_s: float | None, sent_s: float) -> float | None:
    return None if exit_s is None else (exit_s - sent_s) * 1000.0
