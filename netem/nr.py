"""5G NR air-interface timing and capacity: numerology, TDD patterns, transport block sizes.

Pure functions and frozen data, no clock and no packets; `netem.stages.Slots` is the stage that
gates packets with them, and `DelayOracle` the closed-form one-way delay a test or a link
self-test compares measurements with.

Nouns:
- `TddPattern`: one TDD-UL-DL period as people write it (`DDDDDDDSUU`, `DDDSU`), the special
  slot's DL / guard / UL symbols, and the numerology µ (slot = 1 ms / 2^µ, TS 38.211 §4.2).
  `windows(direction)` are the stretches of one period in which that direction may send.
- `Carrier`: PRBs, MCS (TS 38.214 Table 5.1.3.1-1), layers and DMRS overhead per direction;
  `tbs_bits(symbols)` is the transport block one window of that many symbols carries
  (TS 38.214 §5.1.3.2).
- `DelayOracle`: for an idle link whose packets fit one window, the distribution of the delay
  from a packet's arrival (uniform over the period) to the end of the first window that starts
  at least `lead_s` after it (a grant decided before the slot: K2, or a configured grant).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

Direction = Literal["uplink", "downlink"]

#: OFDM symbols per slot with the normal cyclic prefix (TS 38.211 §4.3.2).
SYMBOLS_PER_SLOT = 14
#: Subcarriers per resource block (TS 38.211 §4.4.4.1).
SUBCARRIERS_PER_PRB = 12
#: Numerologies of data channels: µ = 0..4, 15..240 kHz (TS 38.211 Table 4.2-1).
NUMEROLOGIES = range(5)

#: TS 38.214 Table 5.1.3.1-1 (MCS index table 1, up to 64QAM): (modulation order Qm, target
#: code rate R x 1024) for MCS 0..28. The PUSCH without transform precoding uses it as well.
MCS_TABLE_1: tuple[tuple[int, int], ...] = (
    (2, 120), (2, 157), (2, 193), (2, 251), (2, 308), (2, 379), (2, 449), (2, 526), (2, 602),
    (2, 679), (4, 340), (4, 378), (4, 434), (4, 490), (4, 553), (4, 616), (4, 658), (6, 438),
    (6, 466), (6, 517), (6, 567), (6, 616), (6, 666), (6, 719), (6, 772), (6, 822), (6, 873),
    (6, 910), (6, 948),
)  # fmt: skip

#: TS 38.214 Table 5.1.3.2-1: the transport block sizes (bits) for N_info <= 3824.
TBS_TABLE: tuple[int, ...] = (
    24, 32, 40, 48, 56, 64, 72, 80, 88, 96, 104, 112, 120, 128, 136, 144, 152, 160, 168, 176,
    184, 192, 208, 224, 240, 256, 272, 288, 304, 320, 336, 352, 368, 384, 408, 432, 456, 480,
    504, 528, 552, 576, 608, 640, 672, 704, 736, 768, 808, 848, 888, 928, 984, 1032, 1064,
    1128, 1160, 1192, 1224, 1256, 1288, 1320, 1352, 1416, 1480, 1544, 1608, 1672, 1736, 1800,
    1864, 1928, 2024, 2088, 2152, 2216, 2280, 2408, 2472, 2536, 2600, 2664, 2728, 2792, 2856,
    2976, 3104, 3240, 3368, 3496, 3624, 3752, 3824,
)  # fmt: skip


class NrError(ValueError):
    """A radio parameter out of its 3GPP range; the message names the field and the range."""


def slot_s(numerology: int) -> float:
    """Slot length in seconds: 1 ms / 2^µ (TS 38.211 §4.2)."""
    if numerology not in NUMEROLOGIES:
        raise NrError(f"numerology must be 0..4 (15..240 kHz), got {numerology!r}")
    return 1e-3 / (1 << numerology)


def tbs_bits(
    n_prb: int,
    mcs: int | None = None,
    symbols: int = SYMBOLS_PER_SLOT,
    dmrs_re_per_prb: int = 12,
    overhead_re_per_prb: int = 0,
    layers: int = 1,
    *,
    qm: int | None = None,
    code_rate: float | None = None,
    scaling: float = 1.0,
) -> int:
    """Transport block size in bits of one allocation (TS 38.214 §5.1.3.2, steps 1-4).

    Give `mcs` (Table 5.1.3.1-1) or `qm` and `code_rate` directly. `dmrs_re_per_prb`: 12 is
    one front-loaded DMRS symbol of type 1 with both CDM groups left without data, as
    OpenAirInterface and srsRAN configure by default. `scaling` is the TB scaling factor S.
    """
    if mcs is not None:
        if not 0 <= mcs < len(MCS_TABLE_1):
            raise NrError(f"mcs must be 0..{len(MCS_TABLE_1) - 1} (TS 38.214 Table 5.1.3.1-1)")
        qm, rate_x1024 = MCS_TABLE_1[mcs]
        code_rate = rate_x1024 / 1024.0
    if qm is None or code_rate is None:
        raise NrError("tbs_bits needs an mcs, or both qm and code_rate")
    if not 1 <= n_prb <= 275:
        raise NrError(f"n_prb must be 1..275 (TS 38.101), got {n_prb}")
    if not 1 <= symbols <= SYMBOLS_PER_SLOT:
        raise NrError(f"symbols must be 1..14, got {symbols}")
    # Step 1: resource elements for data.
    re_per_prb = SUBCARRIERS_PER_PRB * symbols - dmrs_re_per_prb - overhead_re_per_prb
    if re_per_prb <= 0:
        return 0
    n_re = min(156, re_per_prb) * n_prb
    # Step 2: intermediate number of information bits.
    n_info = scaling * n_re * code_rate * qm * layers
    if n_info <= 0:
        return 0
    if n_info <= 3824:
        # Step 3: quantise, then the smallest table entry not below it.
        n = max(3, math.floor(math.log2(n_info)) - 6)
        quantised = max(24, (1 << n) * math.floor(n_info / (1 << n)))
        return next(t for t in TBS_TABLE if t >= quantised)
    # Step 4: quantise and fit whole code blocks (with their 24-bit CRCs).
    n = math.floor(math.log2(n_info - 24)) - 5
    # (round half up, as the spec means it; Python's round() goes to even)
    quantised = max(3840, (1 << n) * math.floor((n_info - 24) / (1 << n) + 0.5))
    if code_rate <= 0.25:
        blocks = math.ceil((quantised + 24) / 3816)
    elif quantised > 8424:
        blocks = math.ceil((quantised + 24) / 8424)
    else:
        blocks = 1
    return 8 * blocks * math.ceil((quantised + 24) / (8 * blocks)) - 24


@dataclass(frozen=True)
class TddPattern:
    """One TDD period: slots `D` (downlink), `U` (uplink) and `S` (special), and µ.

    `special` is the special slot's (downlink, guard, uplink) symbols; they add up to 14
    (TS 38.213 §11.1, the symbols of a TDD-UL-DL-ConfigCommon pattern).
    """

    slots: str
    special: tuple[int, int, int] = (10, 2, 2)
    numerology: int = 1

    def __post_init__(self) -> None:
        slot_s(self.numerology)  # range check
        if not self.slots or set(self.slots) - set("DSU"):
            raise NrError(
                f"a TDD pattern is a string of D, S and U slots (like DDDDDDDSUU), "
                f"got {self.slots!r}"
            )
        if len(self.special) != 3 or any(s < 0 for s in self.special):
            raise NrError(f"special slot symbols are (downlink, guard, uplink), got {self.special}")
        if sum(self.special) != SYMBOLS_PER_SLOT:
            raise NrError(
                f"special slot symbols {self.special} add up to {sum(self.special)}, not 14"
            )
        period_ms = self.period_s * 1000
        # TS 38.331 dl-UL-TransmissionPeriodicity: 0.5, 0.625, 1, 1.25, 2, 2.5, 3, 4, 5, 10 ms.
        allowed = (0.5, 0.625, 1.0, 1.25, 2.0, 2.5, 3.0, 4.0, 5.0, 10.0)
        if not any(math.isclose(period_ms, a) for a in allowed):
            raise NrError(
                f"TDD period {period_ms:g} ms ({len(self.slots)} slots of "
                f"{self.slot_s * 1000:g} ms) is not one of TS 38.331's "
                f"{', '.join(f'{a:g}' for a in allowed)} ms"
            )
        if not self.windows("uplink") or not self.windows("downlink"):
            raise NrError(f"TDD pattern {self.slots} {self.special} has no uplink or no downlink")

    @property
    def slot_s(self) -> float:
        return slot_s(self.numerology)

    @property
    def period_s(self) -> float:
        return len(self.slots) * self.slot_s

    def windows(self, direction: Direction) -> list[tuple[float, float, int]]:
        """(start_s, end_s, symbols) of each stretch of one period that `direction` may use.

        Consecutive slots of the direction are separate windows: each slot carries its own
        transport block (one grant per slot).
        """
        symbol = self.slot_s / SYMBOLS_PER_SLOT
        dl, guard, ul = self.special
        own = "D" if direction == "downlink" else "U"
        out: list[tuple[float, float, int]] = []
        for i, kind in enumerate(self.slots):
            start = i * self.slot_s
            if kind == own:
                out.append((start, start + self.slot_s, SYMBOLS_PER_SLOT))
            elif kind == "S":
                if direction == "downlink" and dl:
                    out.append((start, start + dl * symbol, dl))
                elif direction == "uplink" and ul:
                    out.append((start + (dl + guard) * symbol, start + self.slot_s, ul))
        return out

    def share(self, direction: Direction) -> float:
        """The fraction of air time `direction` gets."""
        return sum(e - s for s, e, _ in self.windows(direction)) / self.period_s


@dataclass(frozen=True)
class Carrier:
    """What one direction of a cell carries per window: PRBs, MCS, layers, DMRS overhead."""

    n_prb: int = 106
    mcs: int = 20
    layers: int = 1
    dmrs_re_per_prb: int = 12

    def tbs_bits(self, symbols: int) -> int:
        """Bits in one window of `symbols` OFDM symbols (0 if too short to carry data)."""
        if symbols * SUBCARRIERS_PER_PRB <= self.dmrs_re_per_prb:
            return 0
        return tbs_bits(self.n_prb, self.mcs, symbols, self.dmrs_re_per_prb, layers=self.layers)


@dataclass(frozen=True)
class Occasion:
    """One window of one period that carries data: when it starts and ends, how many bytes."""

    start_s: float
    end_s: float
    capacity_bytes: int


def occasions(pattern: TddPattern, direction: Direction, carrier: Carrier) -> list[Occasion]:
    """The windows of one period that carry data, with their transport block in bytes."""
    out = []
    for start, end, symbols in pattern.windows(direction):
        capacity = carrier.tbs_bits(symbols) // 8
        if capacity > 0:
            out.append(Occasion(start, end, capacity))
    return out


def rate_bps(pattern: TddPattern, direction: Direction, carrier: Carrier) -> float:
    """What a saturated direction carries: its transport blocks per second, in bit/s."""
    return (
        sum(o.capacity_bytes for o in occasions(pattern, direction, carrier))
        * 8
        / (pattern.period_s)
    )


class DelayOracle:
    """Closed-form one-way delay of an idle NR direction for a packet that fits one window.

    A packet arriving at `t` (uniform over the period: an idle UE's traffic is not locked to
    the slot grid) leaves at the end of the first occasion that starts at or after
    `t + lead_s`, plus `fixed_s` (the wired part of the link). `lead_s` is the time between
    the data being there and the slot that carries it (K2 and processing, or 0 for a
    configured grant on every occasion). The delay is then a mixture of uniform pieces, one
    per occasion; `cdf` and `quantile` are exact.
    """

    def __init__(
        self,
        starts_ends: Sequence[tuple[float, float]],
        period_s: float,
        lead_s: float = 0.0,
        fixed_s: float = 0.0,
        bler: float = 0.0,
        max_retx: int = 0,
        harq_s: float = 0.0,
    ) -> None:
        if not starts_ends:
            raise NrError("no occasion in the period: this direction never sends")
        self.period_s = period_s
        self.fixed_s = fixed_s
        # Occasion k serves arrivals in (start_{k-1} - lead, start_k - lead]; a packet there
        # waits from its arrival t to end_k: a delay uniform on [end_k - (start_k - lead),
        # end_k - (start_{k-1} - lead)). With HARQ, a share bler^j (1 - bler) of them waits
        # for j retransmissions more: the same piece shifted by where the j-th one ends.
        windows = sorted(starts_ends)
        self.delivered = 1.0 - (bler ** (max_retx + 1) if bler > 0 else 0.0)
        self.pieces: list[tuple[float, float, float]] = []  # (low, high, weight)
        for k, (start, end) in enumerate(windows):
            previous = windows[k - 1][0] - (period_s if k == 0 else 0.0)
            low = end - start + lead_s + fixed_s
            high = end - previous + lead_s + fixed_s
            t = end
            for j in range(max_retx + 1 if bler > 0 else 1):
                if j:
                    # An idle link's small packet fits any window: the first one will do.
                    t = _next_end(windows, period_s, t + harq_s)
                weight = (bler**j) * (1.0 - bler) / self.delivered
                self.pieces.append((low + t - end, high + t - end, weight))

    @classmethod
    def for_direction(
        cls,
        pattern: TddPattern,
        direction: Direction,
        carrier: Carrier,
        lead_s: float = 0.0,
        fixed_s: float = 0.0,
        bler: float = 0.0,
        max_retx: int = 0,
        harq_s: float = 0.0,
    ) -> DelayOracle:
        windows = [(o.start_s, o.end_s) for o in occasions(pattern, direction, carrier)]
        return cls(windows, pattern.period_s, lead_s, fixed_s, bler, max_retx, harq_s)

    def cdf(self, x: float) -> float:
        """P(delay <= x) of a delivered packet."""
        total = 0.0
        for low, high, weight in self.pieces:
            if x >= high:
                total += (high - low) * weight
            elif x > low:
                total += (x - low) * weight
        return total / self.period_s

    def quantile(self, q: float) -> float:
        """The delay below which a fraction `q` of packets fall (bisection on the exact cdf)."""
        lo = min(p[0] for p in self.pieces)
        hi = max(p[1] for p in self.pieces)
        for _ in range(60):
            mid = (lo + hi) / 2
            if self.cdf(mid) < q:
                lo = mid
            else:
                hi = mid
        return hi

    def mean(self) -> float:
        return sum((h - lo) * (h + lo) / 2 * w for lo, h, w in self.pieces) / self.period_s

    @property
    def minimum(self) -> float:
        return min(p[0] for p in self.pieces)

    @property
    def maximum(self) -> float:
        return max(p[1] for p in self.pieces)


def _next_end(windows: Sequence[tuple[float, float]], period_s: float, t: float) -> float:
    """The end of the first window (repeating every period) that starts at or after `t`."""
    n = math.floor(t / period_s)
    while True:
        for start, end in windows:
            if n * period_s + start >= t - 1e-12:
                return n * period_s + end
        n += 1


@dataclass(frozen=True)
class Radio:
    """The NR air interface of a link: TDD pattern, carrier and grant lead.

    Plain data (it travels in a `LinkProfile` to the relay as JSON); the direction is the
    pipeline's (uplink data uses the uplink windows). `k2_slots` is how long
    before its slot a packet must be there to be scheduled in it (the grant's K2 plus gNB
    processing; 0 models a configured grant on every occasion). Every relay's slot grid starts
    at 0 on CLOCK_MONOTONIC, so all the links of a host, and so of a cell, share one grid.
    """

    slots: str = "DDDDDDDSUU"
    special: tuple[int, int, int] = (6, 4, 4)
    numerology: int = 1
    n_prb: int = 106
    mcs: int = 20
    layers: int = 1
    dmrs_re_per_prb: int = 12
    k2_slots: int = 2
    #: First-transmission block error rate; link adaptation aims at 10% (TS 38.214 §5.2.2.1).
    bler: float = 0.0
    #: HARQ retransmissions before a block is lost (srsRAN's default max_nof_harq_retxs: 4).
    max_retx: int = 4
    #: Slots from a failed block's end to the earliest slot of its retransmission (K1/K2 and
    #: processing, OpenAirInterface's min_rxtxtime 2).
    harq_slots: int = 2

    @property
    def harq_s(self) -> float:
        return self.harq_slots * slot_s(self.numerology)

    def pattern(self) -> TddPattern:
        return TddPattern(self.slots, tuple(self.special), self.numerology)  # type: ignore[arg-type]

    def carrier(self) -> Carrier:
        return Carrier(self.n_prb, self.mcs, self.layers, self.dmrs_re_per_prb)

    @property
    def lead_s(self) -> float:
        return self.k2_slots * slot_s(self.numerology)

    def occasions(self, direction: Direction) -> list[Occasion]:
        return occasions(self.pattern(), direction, self.carrier())

    def oracle(self, direction: Direction, fixed_s: float = 0.0) -> DelayOracle:
        """The idle one-way delay of `direction` for a packet that fits one window."""
        return DelayOracle.for_direction(
            self.pattern(),
            direction,
            self.carrier(),
            self.lead_s,
            fixed_s,
            self.bler,
            self.max_retx,
            self.harq_s,
        )

    def rate_bps(self, direction: Direction) -> float:
        """Transport blocks per second of `direction`, in bit/s (retransmissions included)."""
        return rate_bps(self.pattern(), direction, self.carrier())

    def goodput_bps(self, direction: Direction) -> float:
        """What a saturated `direction` delivers: a share `bler` of the blocks are resends."""
        return self.rate_bps(direction) * (1.0 - self.bler)

    def check(self) -> None:
        """Raise `NrError` naming the field when a value is out of range."""
        self.pattern()
        if not 0 <= self.mcs < len(MCS_TABLE_1):
            raise NrError(f"mcs must be 0..{len(MCS_TABLE_1) - 1} (TS 38.214 Table 5.1.3.1-1)")
        if not 1 <= self.n_prb <= 275:
            raise NrError(f"n_prb must be 1..275 (TS 38.101), got {self.n_prb}")
        if not 1 <= self.layers <= 4:
            raise NrError(f"layers must be 1..4, got {self.layers}")
        if not 0 <= self.k2_slots <= 32:
            raise NrError(f"k2_slots must be 0..32 (TS 38.214 §6.1.2.1), got {self.k2_slots}")
        if not 0.0 <= self.bler < 1.0:
            raise NrError(f"bler must be a fraction in [0, 1), got {self.bler}")
        if not 0 <= self.max_retx <= 16:
            raise NrError(f"max_retx must be 0..16, got {self.max_retx}")
        if not 0 <= self.harq_slots <= 32:
            raise NrError(f"harq_slots must be 0..32, got {self.harq_slots}")
        for direction in ("uplink", "downlink"):
            if not self.occasions(direction):  # type: ignore[arg-type]
                raise NrError(
                    f"{direction} has no window that carries data in {self.slots} "
                    f"{self.special} (windows too short for the DMRS)"
                )

    def to_dict(self) -> dict[str, object]:
        return {**dataclasses.asdict(self), "special": list(self.special)}

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> Radio:
        data = dict(data)
        if "special" in data:
            data["special"] = tuple(data["special"])  # type: ignore[arg-type]
        return cls(**data)  # type: ignore[arg-type]


#: Named radios, each value with its source. Only what the model has today: TDD windows,
#: transport blocks, the grant lead and HARQ (scheduling requests and RLC come later, #16).
RADIO_PROFILES: dict[str, Radio] = {
    # OpenAirInterface's default band-78 gNB, gnb.sa.band78.fr1.106PRB.usrpb210.conf:
    # subcarrierSpacing 1 (30 kHz), dl_UL_TransmissionPeriodicity 6 (5 ms) with
    # nrofDownlinkSlots 7, nrofDownlinkSymbols 6, nrofUplinkSymbols 4, nrofUplinkSlots 2;
    # 106 PRBs; min_rxtxtime 2 (K2 = 2 slots). MCS 20 is a mid-cell link adaptation choice
    # (an assumption, not from the file).
    "oai-tdd-30k": Radio(
        slots="DDDDDDDSUU",
        special=(6, 4, 4),
        numerology=1,
        n_prb=106,
        mcs=20,
        k2_slots=2,
        bler=0.1,  # OAI's link adaptation targets 10% first-transmission BLER
        max_retx=4,  # OAI's and srsRAN's default HARQ retransmissions
        harq_slots=2,  # min_rxtxtime 2
    ),
    # srsRAN Project configs/low_latency.yml: a 2 ms period at 30 kHz of 2 downlink slots, a
    # special slot of 10 downlink symbols, and 1 uplink slot; min K1 = K2 = 2. 106 PRBs (a
    # 40 MHz carrier at 30 kHz, TS 38.101-1 Table 5.3.2-1) and MCS 20 are assumptions.
    "srsran-lowlat": Radio(
        slots="DDSU",
        special=(10, 4, 0),
        numerology=1,
        n_prb=106,
        mcs=20,
        k2_slots=2,
        bler=0.1,  # the CQI definition's 10% target (TS 38.214 §5.2.2.1)
        max_retx=4,  # srsRAN's max_nof_harq_retxs default
        harq_slots=2,  # min K1 = K2 = 2
    ),
}
