"""RRC states of one UE and the delay the first packet after a quiet spell pays.

Pure: packet times go in, extra delays come out; the link stage that holds packets back by
them is elsewhere.

Nouns:
- `RrcState`: RRC_CONNECTED, RRC_INACTIVE, RRC_IDLE (TS 38.331 §4.2.1).
- `Rrc`: one UE's state machine. After `inactivity_s` without a packet the network suspends
  the connection (RRCRelease with suspendConfig, TS 38.331 §5.3.8): CONNECTED -> INACTIVE.
  After a further `idle_after_s` it releases it: INACTIVE -> IDLE. The first packet in
  INACTIVE pays an RRC resume (TS 38.331 §5.3.13, TS 38.300 §9.2.2.4), in IDLE a random
  access and RRC setup (TS 38.331 §5.3.3); packets sent while that promotion runs wait for
  its end, and later ones pay nothing until the next quiet spell.
- `Promotion`: one such promotion, for logs and reports.
- `RrcSettings`: the four timers as plain data, what a `netem.profile.LinkProfile` carries
  (`rrc`) to the relay, whose `netem.nr.rrc_stage.RrcStage` holds packets back by them.

Only the packets given to `on_packet` count as traffic (both directions of the UE's link
should be fed to one `Rrc`), and paging (a downlink packet to an idle UE) costs the same as
the UE's own setup here.

In a scenario: `links.air.rrc: {inactivity: 10s, idle_after: 60s, resume: 30ms, setup: 150ms}`,
or per link in `overrides` (userspace backend); the stage is first in each direction's
pipeline. On a real relay link the first datagram after 12 s of quiet with the default 10 s
timer arrived 30.2 ms later than a plain one, after 8 s no later (`python -m pytest -s
tests/test_rrc_root.py`). The replay leaves RRC out: EdgeLoc asks ~10 times a second and never
goes quiet.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from netem.errors import NetemError


class RrcError(NetemError, ValueError):
    """An RRC setting out of range, or packets given out of time order."""


class RrcState(StrEnum):
    CONNECTED = "connected"
    INACTIVE = "inactive"
    IDLE = "idle"


@dataclass(frozen=True)
class Promotion:
    """A packet at `start_s` found the UE in `from_state`; connected again at `end_s`."""

    start_s: float
    end_s: float
    from_state: RrcState


class Rrc:
    """One UE's RRC state machine, driven by its packets' times.

    Defaults, all assumptions:
    - `inactivity_s` 10 s: a common operator setting of the RRC inactivity timer (the timer
      is the gNB's, 3GPP does not fix it).
    - `idle_after_s` 60 s: how long the network keeps a UE suspended before releasing it to
      IDLE is its own policy too (the periodic RNA update, T380, is 5 min or more); 0 models a
      network without INACTIVE, which releases straight to IDLE; math.inf one that never does.
    - `resume_s` 30 ms: resume request, resume and resume complete take one or two round
      trips over the air, ~20-40 ms (the project's spec); ITU-R M.2410 asks 20 ms of the
      control plane from idle to active.
    - `setup_s` 150 ms: random access and RRC setup from IDLE, ~100-300 ms measured (the
      project's spec).

    The UE starts in `initial` at `t0_s` (CONNECTED: as if its last packet was then).
    """

    def __init__(
        self,
        inactivity_s: float = 10.0,
        idle_after_s: float = 60.0,
        resume_s: float = 0.030,
        setup_s: float = 0.150,
        initial: RrcState | str = RrcState.CONNECTED,
        t0_s: float = 0.0,
    ) -> None:
        if not (math.isfinite(inactivity_s) and 0.0 < inactivity_s <= 3600.0):
            raise RrcError(f"inactivity_s must be > 0 and <= 3600 s, got {inactivity_s!r}")
        if math.isnan(idle_after_s) or idle_after_s < 0.0:
            raise RrcError(f"idle_after_s must be >= 0 s (inf: never idle), got {idle_after_s!r}")
        for name, value in (("resume_s", resume_s), ("setup_s", setup_s)):
            if not (math.isfinite(value) and 0.0 <= value <= 10.0):
                raise RrcError(f"{name} must be 0..10 s, got {value!r}")
        if not math.isfinite(t0_s):
            raise RrcError(f"t0_s must be a finite time, got {t0_s!r}")
        try:
            start = RrcState(initial)
        except ValueError:
            known = ", ".join(s.value for s in RrcState)
            raise RrcError(f"unknown RRC state {initial!r} (known: {known})") from None
        self.inactivity_s = inactivity_s
        self.idle_after_s = idle_after_s
        self.resume_s = resume_s
        self.setup_s = setup_s
        # The state follows from when the UE last had traffic; a UE that starts INACTIVE or
        # IDLE is given a last activity that far back.
        self._last_activity = {
            RrcState.CONNECTED: t0_s,
            RrcState.INACTIVE: t0_s - inactivity_s,
            RrcState.IDLE: -math.inf,
        }[start]
        self._last_packet = t0_s
        self._promotion: Promotion | None = None
        self.promotions: list[Promotion] = []

    def _quiet_state(self, t: float) -> RrcState:
        """The state at `t` from the timers alone (no promotion under way)."""
        quiet = t - self._last_activity
        if quiet < self.inactivity_s:
            return RrcState.CONNECTED
        # Written as a comparison of the quiet time with each timer, so inf timers work.
        if quiet - self.inactivity_s < self.idle_after_s:
            return RrcState.INACTIVE
        return RrcState.IDLE

    def state_at(self, t: float) -> RrcState:
        """The state at `t` (not before the last packet): during a promotion the UE is still in
        the state it is leaving, connected from the promotion's end."""
        if t < self._last_packet:
            raise RrcError(
                f"state_at({t:g}) is before the last packet ({self._last_packet:g} s): the "
                f"state machine keeps no history"
            )
        if self._promotion is not None and t < self._promotion.end_s:
            return self._promotion.from_state
        return self._quiet_state(t)

    def on_packet(self, t: float) -> float:
        """A packet sent at `t` (in time order); the extra delay it waits for the connection."""
        if not math.isfinite(t) or t < self._last_packet:
            raise RrcError(
                f"packet at {t!r} s is before the previous one ({self._last_packet:g} s)"
            )
        self._last_packet = t
        if self._promotion is not None and t < self._promotion.end_s:
            # A promotion already under way: wait for its end, not a second one.
            return self._promotion.end_s - t
        state = self._quiet_state(t)
        if state is RrcState.CONNECTED:
            self._last_activity = t
            return 0.0
        cost = self.resume_s if state is RrcState.INACTIVE else self.setup_s
        self._promotion = Promotion(t, t + cost, state)
        self.promotions.append(self._promotion)
        # The inactivity timer starts again when the packet goes, at the end of the promotion.
        self._last_activity = t + cost
        return cost


@dataclass(frozen=True)
class RrcSettings:
    """The RRC timers of a link's UE, as plain data: it travels in a `LinkProfile` (`rrc`) to
    the relay as JSON, and `machine()` makes the `Rrc` that applies them (defaults and
    meaning: `Rrc`). `idle_after_s` may be math.inf (never released to IDLE), written as
    null in JSON, which has no infinity.
    """

    inactivity_s: float = 10.0
    idle_after_s: float = 60.0
    resume_s: float = 0.030
    setup_s: float = 0.150

    def check(self) -> None:
        """Raise `RrcError` naming the field when a value is not a number or out of range."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, int | float) or isinstance(value, bool):
                raise RrcError(f"{f.name} must be a number of seconds, got {value!r}")
        self.machine(0.0)  # `Rrc` holds the ranges: one place for them

    def machine(self, t0_s: float) -> Rrc:
        """A state machine with these timers whose UE is connected at `t0_s`."""
        return Rrc(self.inactivity_s, self.idle_after_s, self.resume_s, self.setup_s, t0_s=t0_s)

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        if out["idle_after_s"] == math.inf:
            out["idle_after_s"] = None
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RrcSettings:
        data = dict(data)
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise RrcError(f"unknown RRC setting(s) {unknown}; allowed: {', '.join(known)}")
        if "idle_after_s" in data and data["idle_after_s"] is None:
            data["idle_after_s"] = math.inf
        return cls(**data)
