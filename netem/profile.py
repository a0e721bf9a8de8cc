"""What one direction of an emulated link does to packets.

A `LinkProfile` is pure data: rate, delay, jitter and its distribution, loss (random or
Gilbert-Elliott), queue limit, whether reordering is allowed, an optional NR air interface
(`netem.nr.radio.Radio`) and optional RRC timers (`netem.nr.rrc.RrcSettings`), both userspace
backend only. Backends (`tc`, `userspace`) turn a profile into qdiscs or relay stages; the
timeline changes a live link by handing the backend a new profile, which it applies in place.

RRC states are the UE's, not a direction's: one state machine serves both directions of a
link, so the two profiles of a link carry the same `rrc` (`check_link`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

from netem.errors import ProfileError
from netem.nr.phy import NrError
from netem.nr.radio import Radio
from netem.nr.rrc import RrcError, RrcSettings

JitterDistribution = Literal["normal", "uniform", "pareto"]
JITTER_DISTRIBUTIONS: tuple[str, ...] = ("normal", "uniform", "pareto")

#: netem's own default queue limit, used by both backends so they drop alike.
DEFAULT_QUEUE_PACKETS = 1000


@dataclass(frozen=True)
class GilbertElliott:
    """Two-state Markov loss (netem's `loss gemodel p r 1-h 1-k`).

    `p` is the per-packet chance to go good→bad, `r` bad→good; `good_loss` and `bad_loss`
    are the loss probabilities inside each state. All are fractions in [0, 1].
    """

    p: float
    r: float
    good_loss: float = 0.0
    bad_loss: float = 1.0

    def stationary_loss(self) -> float:
        """Long-run loss rate, from the chain's stationary distribution."""
        if self.p + self.r == 0:
            return self.good_loss
        bad = self.p / (self.p + self.r)
        return bad * self.bad_loss + (1 - bad) * self.good_loss


@dataclass(frozen=True)
class LinkProfile:
    """One direction of a link. Units are SI: bit/s, seconds, fractions."""

    rate_bps: float | None = None
    delay_s: float = 0.0
    jitter_s: float = 0.0
    jitter_distribution: JitterDistribution = "normal"
    loss: float = 0.0
    gilbert_elliott: GilbertElliott | None = None
    queue_packets: int | None = DEFAULT_QUEUE_PACKETS
    queue_time_s: float | None = None
    reorder: bool = False
    #: The NR air interface (TDD slots, transport blocks, grant lead); userspace backend only.
    radio: Radio | None = None
    #: RRC states (CONNECTED/INACTIVE/IDLE) and what a packet after a quiet spell pays to
    #: reconnect; None: always connected. Userspace backend only; the same in both directions.
    rrc: RrcSettings | None = None

    def replace(self, **changes: Any) -> LinkProfile:
        """A copy with `changes` applied (the timeline's `set` action)."""
        return dataclasses.replace(self, **changes)

    @property
    def fixed_delay_s(self) -> float:
        """The delay every packet of this direction pays besides slots and jitter: `delay_s`
        and, on a radio, its gNB-to-core distance."""
        return self.delay_s + (self.radio.core_delay_s if self.radio is not None else 0.0)

    @property
    def expected_loss(self) -> float:
        """The loss rate a measurement over many packets should find."""
        if self.gilbert_elliott is not None:
            return self.gilbert_elliott.stationary_loss()
        return self.loss

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        if self.radio is not None:
            out["radio"] = self.radio.to_dict()
        if self.rrc is not None:
            out["rrc"] = self.rrc.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LinkProfile:
        data = dict(data)
        ge = data.get("gilbert_elliott")
        if isinstance(ge, dict):
            data["gilbert_elliott"] = GilbertElliott(**ge)
        radio = data.get("radio")
        if isinstance(radio, dict):
            data["radio"] = Radio.from_dict(radio)
        rrc = data.get("rrc")
        if isinstance(rrc, dict):
            data["rrc"] = RrcSettings.from_dict(rrc)
        return cls(**data)


#: Fields of `LinkProfile` that a timeline `set` event may change.
PROFILE_FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(LinkProfile))


#: HTB's smallest useful rate: it cannot send at 0 bit/s, and a lower rate lets no packet through.
HTB_MIN_RATE_BPS = 8.0
#: The smallest rate each backend can keep: HTB's; the relay's rate stage takes any rate >= 0
#: (0 stalls the direction).
MIN_RATE_BPS = {"tc": HTB_MIN_RATE_BPS, "userspace": 0.0}


def check_profile(profile: LinkProfile, backend: Literal["tc", "userspace"] = "userspace") -> None:
    """Raise `ProfileError` (a ValueError) naming the field if `profile` holds a value the
    backend cannot apply: the one check that both backends, the relay's control protocol and
    the tc planner run before touching a link."""

    def bad(field: str, value: object, allowed: str) -> ProfileError:
        return ProfileError(f"link profile field `{field}` = {value!r}: must be {allowed}")

    def number(value: object) -> bool:
        return isinstance(value, int | float) and not isinstance(value, bool)

    def fraction(field: str, value: object) -> None:
        if not number(value) or not 0.0 <= value <= 1.0:  # type: ignore[operator]
            raise bad(field, value, "a fraction in [0, 1]")

    def seconds(field: str, value: object) -> None:
        if not number(value) or not math.isfinite(value) or value < 0:  # type: ignore[arg-type,operator]
            raise bad(field, value, "a finite number of seconds >= 0")

    floor = MIN_RATE_BPS[backend]
    rate = profile.rate_bps
    if rate is not None and (not number(rate) or not math.isfinite(rate) or not rate >= floor):
        raise bad("rate_bps", rate, f"a rate of at least {floor:g} bit/s, or null for unlimited")
    seconds("delay_s", profile.delay_s)
    seconds("jitter_s", profile.jitter_s)
    if profile.jitter_distribution not in JITTER_DISTRIBUTIONS:
        raise bad(
            "jitter_distribution", profile.jitter_distribution, " or ".join(JITTER_DISTRIBUTIONS)
        )
    fraction("loss", profile.loss)
    ge = profile.gilbert_elliott
    if ge is not None:
        for name in ("p", "r", "good_loss", "bad_loss"):
            fraction(f"gilbert_elliott.{name}", getattr(ge, name))
    queue = profile.queue_packets
    if queue is not None and (not isinstance(queue, int) or isinstance(queue, bool) or queue < 1):
        raise bad("queue_packets", queue, "a whole number of packets >= 1, or null")
    qt = profile.queue_time_s
    if qt is not None and (not number(qt) or not qt > 0):  # type: ignore[operator]
        raise bad("queue_time_s", qt, "a number of seconds > 0, or null")
    if not isinstance(profile.reorder, bool):
        raise bad("reorder", profile.reorder, "true or false")
    if profile.radio is not None:
        if backend == "tc":
            raise ProfileError(
                "link profile field `radio`: the NR slot model runs in the userspace relay only"
                " (tc's qdiscs have no slot clock); use backend userspace or auto"
            )
        try:
            profile.radio.check()
        except (NrError, TypeError) as exc:
            raise ProfileError(f"link profile field `radio`: {exc}") from None
    if profile.rrc is not None:
        if backend == "tc":
            raise ProfileError(
                "link profile field `rrc`: RRC states run in the userspace relay only (tc's "
                "qdiscs cannot hold a quiet link's first packet back); use backend userspace"
            )
        if not isinstance(profile.rrc, RrcSettings):
            raise bad("rrc", profile.rrc, "RRC settings (inactivity_s, idle_after_s, ...) or null")
        try:
            profile.rrc.check()
        except RrcError as exc:
            raise ProfileError(f"link profile field `rrc`: {exc}") from None


def check_link(uplink: LinkProfile, downlink: LinkProfile) -> None:
    """Raise `ProfileError` unless the two directions of one link agree on what is the UE's
    rather than a direction's: its RRC state machine, which both directions' packets drive
    (TS 38.331 §4.2.1: the RRC state is the UE's)."""
    if uplink.rrc != downlink.rrc:
        raise ProfileError(
            f"link profile field `rrc` differs between uplink ({uplink.rrc}) and downlink "
            f"({downlink.rrc}): one RRC state machine serves both directions of a link; give "
            "both the same settings (a relay `set` that names rrc changes both)"
        )
