"""Handover between cells: the A3 event with time-to-trigger and L3 filtering, and what a
handover costs the data path.

Pure: RSRP measurements go in (from `netem.nr.channel.Channel` or a recorded trace), handover
decisions come out; nothing here knows about links or packets.

Nouns:
- `A3Handover`: one UE's measurement and decision logic. Every `step_s` it L3-filters each
  cell's RSRP (TS 38.331 §5.5.3.2) and checks event A3, "neighbour becomes offset better than
  SpCell" (TS 38.331 §5.5.4.4), for every neighbour; when a neighbour's entering condition has
  held at every measurement for the time-to-trigger, the UE reports it and the network hands
  the UE over to it (a `HandoverDecision`).
- `HandoverDecision`: when, from which cell, to which.
- `Interruption`: how long the user plane stops at a handover and whether the packets of that
  gap are delivered late (forwarded) or lost.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from netem.errors import NetemError

#: TS 38.331 TimeToTrigger: ms0 .. ms5120.
TTT_MS: tuple[int, ...] = (
    0, 40, 64, 80, 100, 128, 160, 256, 320, 480, 512, 640, 1024, 1280, 2560, 5120,
)  # fmt: skip
#: TS 38.331 FilterCoefficient: fc0 .. fc19 (fc4 is the default).
FILTER_COEFFICIENTS: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 13, 15, 17, 19)
#: TS 38.331 Hysteresis: 0..30 in 0.5 dB steps.
HYSTERESIS_RANGE_DB = (0.0, 15.0)
#: TS 38.331 MeasTriggerQuantityOffset (a3-Offset): -30..30 in 0.5 dB steps.
OFFSET_RANGE_DB = (-15.0, 15.0)
#: The sample period the filter coefficient assumes: one intra-frequency L1 measurement period
#: without DRX (TS 38.331 §5.5.3.2), in FR1 max(200 ms, 5 SMTC periods) (TS 38.133 §9.2.5.1),
#: i.e. 200 ms with the usual 20 ms SMTC.
L1_PERIOD_S = 0.2
#: Slack for comparing times that were sums of float steps.
_EPS_S = 1e-9


class HandoverError(NetemError, ValueError):
    """A handover setting out of its 3GPP range, or measurements that cannot be used."""


@dataclass(frozen=True)
class HandoverDecision:
    """The UE leaves `source` for `target`; `t` is when event A3 triggered (the measurement at
    which the time-to-trigger was complete)."""

    t: float
    source: str
    target: str


@dataclass(frozen=True)
class Interruption:
    """What a handover costs the user plane: no packet passes for `interruption_s` from the
    decision, and `lossless` says whether those packets arrive afterwards (the source forwards
    them to the target and PDCP delivers them in order, TS 38.300 §9.2.3.2) or are lost.

    40 ms is an assumption: close to what TS 38.133 §6.1.1 allows a known intra-frequency
    target (20 ms of processing, up to one 20 ms SSB period to find timing, a 2 ms margin);
    the project's spec puts measured NR handovers at 50-150 ms and ITU-R M.2410's requirement
    for the mobility interruption time is 0 ms (make-before-break, DAPS).
    """

    interruption_s: float = 0.040
    lossless: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.interruption_s) and 0.0 <= self.interruption_s <= 10.0):
            raise HandoverError(
                f"interruption_s must be 0..10 s (a longer gap is a radio link failure, an "
                f"outage), got {self.interruption_s!r}"
            )

    def window(self, decision: HandoverDecision) -> tuple[float, float]:
        """[start, end) of the gap a handover opens."""
        return decision.t, decision.t + self.interruption_s


def _half_db(value: float, field: str, bounds: tuple[float, float]) -> None:
    low, high = bounds
    if not (math.isfinite(value) and low <= value <= high and (value * 2).is_integer()):
        raise HandoverError(
            f"{field} must be {low:g}..{high:g} dB in 0.5 dB steps (TS 38.331), got {value!r}"
        )


class A3Handover:
    """Event A3 handover of one UE (TS 38.331 §5.5.4.4), measured every `step_s` seconds.

    The entering condition Mn + Ofn + Ocn - Hys > Mp + Ofp + Ocp + Off is taken with the
    frequency and cell offsets at 0 dB (one carrier, no cell individual offsets):
    Mn - Hys > Ms + Off, on L3-filtered RSRP in dBm. A neighbour triggers when the condition
    has held at every measurement for `ttt_ms` (at least one measurement: TTT 0 triggers at
    once); among neighbours that trigger together the strongest is the target. The handover
    is taken to execute at once: the target serves from the next measurement on.

    L3 filter (TS 38.331 §5.5.3.2): F_n = (1 - a) F_{n-1} + a M_n, F_1 = M_1, with
    a = 1/2^(k/4) per `l1_period_s`. The spec asks the filter to keep its time characteristics
    at other input rates, so at `step_s` != `l1_period_s` each step uses
    a' = 1 - (1 - a)^(step_s / l1_period_s). `filter_k` None (or 0) turns the filter off.

    The defaults (offset 3 dB, hysteresis 1 dB, TTT 320 ms) are an assumption, a moderate
    intra-frequency setting within TS 38.331's ranges; `step_s` 40 ms resolves the shortest
    non-zero TTT. `observe` may be called more often than `step_s` (every simulation tick):
    the calls between measurement instants are ignored.
    """

    def __init__(
        self,
        offset_db: float = 3.0,
        hysteresis_db: float = 1.0,
        ttt_ms: int = 320,
        filter_k: int | None = 4,
        step_s: float = 0.04,
        l1_period_s: float = L1_PERIOD_S,
        serving: str | None = None,
    ) -> None:
        _half_db(offset_db, "offset_db (a3-Offset)", OFFSET_RANGE_DB)
        _half_db(hysteresis_db, "hysteresis_db", HYSTERESIS_RANGE_DB)
        if ttt_ms not in TTT_MS:
            raise HandoverError(
                f"ttt_ms must be one of TS 38.331's TimeToTrigger values "
                f"{', '.join(map(str, TTT_MS))} ms, got {ttt_ms!r}"
            )
        if filter_k is not None and filter_k not in FILTER_COEFFICIENTS:
            raise HandoverError(
                f"filter_k must be one of TS 38.331's FilterCoefficient values "
                f"{', '.join(map(str, FILTER_COEFFICIENTS))} (or None: no L3 filter), "
                f"got {filter_k!r}"
            )
        for name, value in (("step_s", step_s), ("l1_period_s", l1_period_s)):
            if not (math.isfinite(value) and 0.0 < value <= 10.0):
                raise HandoverError(f"{name} must be > 0 and <= 10 s, got {value!r}")
        self.offset_db = offset_db
        self.hysteresis_db = hysteresis_db
        self.ttt_ms = ttt_ms
        self.filter_k = filter_k
        self.step_s = step_s
        self.l1_period_s = l1_period_s
        a = 1.0 if not filter_k else 1.0 / 2.0 ** (filter_k / 4.0)
        #: The filter's weight of a new measurement at `step_s`.
        self.alpha = 1.0 - (1.0 - a) ** (step_s / l1_period_s)
        self._serving = serving
        self._filtered: dict[str, float] = {}
        self._entered: dict[str, float] = {}  # neighbour -> first measurement of its run
        self._t0: float | None = None
        self._next_s = -math.inf
        self._last_t = -math.inf

    @property
    def serving(self) -> str | None:
        """The serving cell (None until the first measurement, unless one was given)."""
        return self._serving

    @property
    def filtered(self) -> Mapping[str, float]:
        """The L3-filtered RSRP of each cell at the last measurement."""
        return MappingProxyType(self._filtered)

    def observe(self, t: float, rsrp_by_cell: Mapping[str, float]) -> HandoverDecision | None:
        """Take the RSRPs (dBm) of `t`, if a measurement is due; the handover it triggers.

        Without a serving cell the first measurement selects the strongest one (cell
        selection) and triggers nothing. A cell missing from `rsrp_by_cell` is not heard: its
        filter and its time-to-trigger start again when it is back. The serving cell must be
        heard.
        """
        if not math.isfinite(t) or t < self._last_t:
            raise HandoverError(f"measurement time {t!r} is before the previous one")
        self._last_t = t
        if t < self._next_s - _EPS_S:
            return None
        if self._t0 is None:
            self._t0 = t
        # Measurement instants on the grid t0 + k step_s, so a caller ticking at another rate
        # does not stretch the measurement period.
        k = math.floor((t - self._t0) / self.step_s + _EPS_S)
        self._next_s = self._t0 + (k + 1) * self.step_s
        if not rsrp_by_cell:
            raise HandoverError(f"no cell measured at {t:g} s")
        for cell, value in rsrp_by_cell.items():
            if not math.isfinite(value):
                raise HandoverError(f"RSRP of cell {cell} at {t:g} s is {value!r}")
        filtered: dict[str, float] = {}
        for cell, m in rsrp_by_cell.items():
            before = self._filtered.get(cell)
            filtered[cell] = m if before is None else before + self.alpha * (m - before)
        self._filtered = filtered
        if self._serving is None:
            self._serving = max(self._filtered, key=lambda c: self._filtered[c])
            return None
        if self._serving not in self._filtered:
            heard = ", ".join(self._filtered)
            raise HandoverError(
                f"serving cell {self._serving} is not among the cells measured at {t:g} s ({heard})"
            )
        ms = self._filtered[self._serving]
        for cell, mn in self._filtered.items():
            if cell == self._serving:
                continue
            if mn - self.hysteresis_db > ms + self.offset_db:
                self._entered.setdefault(cell, t)
            else:
                self._entered.pop(cell, None)
        for cell in [c for c in self._entered if c not in self._filtered]:
            del self._entered[cell]
        ttt_s = self.ttt_ms / 1000.0
        ready = [c for c, since in self._entered.items() if t - since >= ttt_s - _EPS_S]
        if not ready:
            return None
        target = max(ready, key=lambda c: self._filtered[c])
        decision = HandoverDecision(t, self._serving, target)
        self._serving = target
        self._entered.clear()
        return decision
