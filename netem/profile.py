"""What one direction of an emulated link does to packets.

A `LinkProfile` is pure data: rate, delay, jitter and its distribution, loss (random or
Gilbert-Elliott), queue limit and whether reordering is allowed. Backends (`tc`, `userspace`)
turn a profile into qdiscs or relay stages; the timeline changes a live link by handing the
backend a new profile, which it applies in place.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

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

    def replace(self, **changes: Any) -> LinkProfile:
        """A copy with `changes` applied (the timeline's `set` action)."""
        return dataclasses.replace(self, **changes)

    @property
    def expected_loss(self) -> float:
        """The loss rate a measurement over many packets should find."""
        if self.gilbert_elliott is not None:
            return self.gilbert_elliott.stationary_loss()
        return self.loss

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LinkProfile:
        data = dict(data)
        ge = data.get("gilbert_elliott")
        if isinstance(ge, dict):
            data["gilbert_elliott"] = GilbertElliott(**ge)
        return cls(**data)


#: Fields of `LinkProfile` that a timeline `set` event may change.
PROFILE_FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(LinkProfile))
