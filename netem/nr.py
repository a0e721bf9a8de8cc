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
    """Closed-form one-way delay of an idle NR direction, a mixture of uniform pieces.

    A packet arrives at `t`, uniform over the period (an idle UE's traffic is not locked to
    the slot grid). Which cut `c_k` of the period it falls before decides when it leaves: the
    arrivals in `(c_{k-1}, c_k]` all leave at the same time `T` (or, with HARQ, at one of
    a few times with known probabilities), so their delay is uniform on
    `[T - c_k, T - c_{k-1})`. `fixed_s` is the wired part of the link. `cdf` and `quantile`
    are exact; they describe the delivered packets (a residual HARQ loss is not a delay).

    - The scheduled model (`DelayOracle(...)`, the downlink, a configured grant, or an uplink
      whose buffer the gNB sees at once): cut `k` is occasion `k`'s start minus `lead_s`, and
      a packet that fits one window leaves at that occasion's end.
    - Scheduling request (`DelayOracle.scheduling_request`): cut `k` is the start of SR
      window `k`; the SR's small first grant comes `grant_delay_s` after the SR window ends,
      and, when the packet is larger, the buffer status report in it brings grants for the
      rest after the same delay from its decoding (TS 38.321 §5.4.4, §5.4.5).
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
        grid = _Windows([(s, e, 1) for s, e in starts_ends], period_s)
        harq = _Harq(bler, max_retx, harq_s, grid)
        cuts = [start - lead_s for start, _, _ in grid.windows]
        # An idle link's small packet fits any window, so a retransmission takes the first.
        outcomes = [harq.decodes(end) for _, end, _ in grid.windows]
        self._build(cuts, outcomes, period_s, fixed_s)

    @classmethod
    def scheduling_request(
        cls,
        occasions: Sequence[Occasion],
        sr_windows: Sequence[tuple[float, float]],
        period_s: float,
        grant_delay_s: float,
        first_grant_bytes: int,
        size_bytes: int,
        fixed_s: float = 0.0,
        bler: float = 0.0,
        max_retx: int = 0,
        harq_s: float = 0.0,
    ) -> DelayOracle:
        """An idle UE's `size_bytes` packet that must ask for its grant with an SR.

        Exact while the packet's blocks and their retransmissions do not compete for one
        occasion (an idle UE, a packet of a few blocks).
        """
        if not occasions or not sr_windows:
            raise NrError("no uplink occasion or no SR window in the period")
        grid = _Windows([(o.start_s, o.end_s, o.capacity_bytes) for o in occasions], period_s)
        harq = _Harq(bler, max_retx, harq_s, grid)
        srs = sorted(sr_windows)
        outcomes = []
        for _, sr_end in srs:
            _, end, capacity = grid.first(sr_end + grant_delay_s)
            first = min(size_bytes, first_grant_bytes, capacity)
            mixture: dict[float, float] = {}
            for t1, p1 in harq.decodes(end):
                # The rest goes in the occasions its buffer status report is granted.
                rest = [
                    harq.decodes(e) for e in grid.carrying(t1 + grant_delay_s, size_bytes - first)
                ]
                for t, p in _max_of([[(t1, p1)], *rest]):
                    mixture[t] = mixture.get(t, 0.0) + p
            outcomes.append(sorted(mixture.items()))
        inst = cls.__new__(cls)
        inst._build([start for start, _ in srs], outcomes, period_s, fixed_s)
        return inst

    def _build(
        self,
        cuts: Sequence[float],
        outcomes: Sequence[Sequence[tuple[float, float]]],
        period_s: float,
        fixed_s: float,
    ) -> None:
        self.period_s = period_s
        self.fixed_s = fixed_s
        self.pieces: list[tuple[float, float, float]] = []  # (low, high, weight)
        delivered = 0.0
        for k, cut in enumerate(cuts):
            previous = cuts[k - 1] - (period_s if k == 0 else 0.0)
            for leave, p in outcomes[k]:
                self.pieces.append((leave - cut + fixed_s, leave - previous + fixed_s, p))
                delivered += (cut - previous) * p
        #: The share of packets delivered (the rest is lost after the last retransmission).
        self.delivered = delivered / period_s

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
        return total / (self.period_s * self.delivered)

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
        total = sum((h - lo) * (h + lo) / 2 * w for lo, h, w in self.pieces)
        return total / (self.period_s * self.delivered)

    @property
    def minimum(self) -> float:
        return min(p[0] for p in self.pieces if p[2] > 0)

    @property
    def maximum(self) -> float:
        return max(p[1] for p in self.pieces if p[2] > 0)


class _Windows:
    """Windows `(start, end, capacity)` of one period, repeating every `period_s`."""

    def __init__(self, windows: Sequence[tuple[float, float, int]], period_s: float) -> None:
        self.windows = sorted(windows)
        self.period_s = period_s

    def first(self, t: float) -> tuple[float, float, int]:
        """The first window that starts at or after `t`."""
        n = math.floor(t / self.period_s)
        while True:
            for start, end, capacity in self.windows:
                if n * self.period_s + start >= t - 1e-12:
                    base = n * self.period_s
                    return base + start, base + end, capacity
            n += 1

    def carrying(self, t: float, size: int) -> list[float]:
        """The ends of the windows from `t` on that carry `size` bytes, each filled whole."""
        ends: list[float] = []
        while size > 0:
            start, end, capacity = self.first(t)
            ends.append(end)
            size -= capacity
            t = start + 1e-9
        return ends


class _Harq:
    """When a block sent in a window ending at `end` is decoded, with its probabilities."""

    def __init__(self, bler: float, max_retx: int, harq_s: float, grid: _Windows) -> None:
        self.bler, self.max_retx, self.harq_s, self.grid = bler, max_retx, harq_s, grid

    def decodes(self, end: float) -> list[tuple[float, float]]:
        """(decoded at, probability) per attempt; they add up to less than 1 by the loss."""
        if self.bler <= 0.0:
            return [(end, 1.0)]
        out, t = [], end
        for attempt in range(self.max_retx + 1):
            if attempt:
                t = self.grid.first(t + self.harq_s)[1]
            out.append((t, self.bler**attempt * (1.0 - self.bler)))
        return out


def _max_of(blocks: Sequence[Sequence[tuple[float, float]]]) -> list[tuple[float, float]]:
    """The distribution of the latest decoding of independent blocks (all of them decoded)."""
    times = sorted({t for block in blocks for t, _ in block})
    out, before = [], 0.0
    for t in times:
        upto = 1.0
        for block in blocks:
            upto *= sum(p for u, p in block if u <= t)
        out.append((t, upto - before))
        before = upto
    return [(t, p) for t, p in out if p > 0]


#: How an uplink gets its grants: `sr` asks with a scheduling request, then its buffer
#: status reports bring the grants (TS 38.321 §5.4.4, §5.4.5); `configured` sends in a
#: configured grant's periodic occasions without asking (type 1, TS 38.321 §5.8.2); `ideal`
#: is a gNB that sees the UE's buffer as data arrives (no request: a bound, not a real cell).
UL_ACCESS = ("sr", "configured", "ideal")
#: Slot periods TS 38.331 allows for an SR resource (periodicityAndOffset, sl1..sl640).
SR_PERIODS = (1, 2, 4, 5, 8, 10, 16, 20, 40, 80, 160, 320, 640)
#: Configured grant periods in whole slots (TS 38.331 ConfiguredGrantConfig periodicity,
#: n x 14 symbols; the 2- and 7-symbol ones are left out).
CG_PERIODS = (1, 2, 4, 5, 8, 10, 16, 20, 32, 40, 64, 80, 128, 160, 256, 320, 512, 640)


@dataclass(frozen=True)
class Grid:
    """What a `netem.stages.Slots` stage needs to send one direction of a radio.

    `occasions` of one `period_s` (the TDD period, or a multiple of it when an SR or a
    configured grant repeats more slowly) and how packets get them: `access` "sr" waits for
    a grant (`sr_windows`, `grant_delay_s`, `first_grant_bytes`); otherwise a packet may use
    any occasion that starts `lead_s` after it arrived.
    """

    occasions: tuple[Occasion, ...]
    period_s: float
    lead_s: float
    access: str = "ideal"
    sr_windows: tuple[tuple[float, float], ...] = ()
    #: From a decoded SR or buffer status report to the first occasion it may grant.
    grant_delay_s: float = 0.0
    first_grant_bytes: int = 0


@dataclass(frozen=True)
class Radio:
    """The NR air interface of a link: TDD pattern, carrier, uplink access and HARQ.

    Plain data (it travels in a `LinkProfile` to the relay as JSON); the direction is the
    pipeline's (uplink data uses the uplink windows). `k2_slots` is the grant's K2: from the
    DCI to the PUSCH (or, for the downlink and an `ideal` uplink, how long before its slot a
    packet must be there). Every relay's slot grid starts at 0 on CLOCK_MONOTONIC, so all
    the links of a host, and so of a cell, share one grid.
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
    #: How the uplink gets grants (`UL_ACCESS`); the downlink is always scheduled by the gNB.
    ul_access: str = "sr"
    #: SR resource: every `sr_period_slots` slots, in slot `sr_offset` of that period, in the
    #: slot's uplink symbols. OpenAirInterface puts it in the first slot after the downlink
    #: slots (slot 7, the special slot) with period sl10 (nr_rrc_config.c set_SR_periodandoffset).
    sr_period_slots: int = 10
    sr_offset: int = 7
    #: The first grant after an SR, in bytes: small, room for a buffer status report and a
    #: little data (576 bits in srsRAN's log of its issue #603).
    sr_grant_bytes: int = 72
    #: gNB processing from a decoded SR or buffer status report to the DCI of its grant
    #: (an assumption; K2 follows).
    grant_slots: int = 2
    #: Configured grant: every `cg_period_slots` slots, in slot `cg_offset` of that period.
    cg_period_slots: int = 10
    cg_offset: int = 8
    #: RLC mode (TS 38.322): "am" sends a block's packets again after a residual HARQ loss,
    #: once the receiver's status report says so (`rlc_status_s` later); "um" loses them.
    #: OAI and srsRAN run their default bearers in AM.
    rlc: str = "am"
    #: From a residual loss to the packets being back in the sender's buffer: t-Reassembly
    #: and the status report, "tens of ms" (an assumption: 20 ms).
    rlc_status_s: float = 0.02
    #: RLC-AM's maxRetxThreshold (TS 38.322 §5.3.2, TS 38.331 UL-AM-RLC: t1..t32): a packet
    #: sent again this many times and lost once more is given up on (the UE would declare a
    #: radio link failure). OpenAirInterface configures its DRBs with t32.
    rlc_max_retx: int = 32
    #: PDCP in-order delivery (TS 38.323): a packet waits for those before it.
    in_order: bool = True
    #: The buffer for this UE and direction, in bytes (drop-tail beyond it; None: only the
    #: link's packet limit). The gNB's RLC buffer per bearer, e.g. srsRAN's 5QI queue size.
    buffer_bytes: int | None = None
    #: One-way delay from the gNB to the core (the N3 transport and the UPF), carried in this
    #: direction's delay, so a named radio alone gives a cell's round trip to the core
    #: (0: the scenario's backhaul link holds it).
    core_delay_s: float = 0.0

    def __str__(self) -> str:
        """A line a log can carry: the grid, the carrier and how the uplink is granted."""
        return (
            f"NR {self.slots} mu{self.numerology} {self.n_prb} PRB MCS {self.mcs}"
            f"{f' x{self.layers}' if self.layers > 1 else ''}, uplink {self.ul_access}, "
            f"BLER {self.bler:g}, RLC {self.rlc}"
        )

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

    def access(self, direction: Direction) -> str:
        return self.ul_access if direction == "uplink" else "ideal"

    def grid(self, direction: Direction) -> Grid:
        """The occasions of `direction` and how its packets get them."""
        pattern, slot = self.pattern(), slot_s(self.numerology)
        base = occasions(pattern, direction, self.carrier())
        access = self.access(direction)
        if access == "ideal":
            return Grid(tuple(base), pattern.period_s, self.lead_s)
        n = len(self.slots)
        if access == "configured":
            repeat = math.lcm(n, self.cg_period_slots)
            chosen = [
                o
                for o in _repeated(base, pattern.period_s, repeat // n)
                if (_slot_of(o.start_s, slot) - self.cg_offset) % self.cg_period_slots == 0
            ]
            return Grid(tuple(chosen), repeat * slot, 0.0, "configured")
        repeat = math.lcm(n, self.sr_period_slots)
        ul_windows = {_slot_of(s, slot): (s, e) for s, e, _ in pattern.windows("uplink")}
        srs = []
        for i in range(self.sr_offset, repeat, self.sr_period_slots):
            s, e = ul_windows[i % n]
            offset = (i // n) * pattern.period_s
            srs.append((offset + s, offset + e))
        return Grid(
            tuple(_repeated(base, pattern.period_s, repeat // n)),
            repeat * slot,
            self.lead_s,
            "sr",
            tuple(srs),
            (self.grant_slots + self.k2_slots) * slot,
            self.sr_grant_bytes,
        )

    def occasions(self, direction: Direction) -> list[Occasion]:
        """The occasions of one grid period (see `grid`) that carry `direction`'s data."""
        return list(self.grid(direction).occasions)

    def oracle(
        self, direction: Direction, fixed_s: float = 0.0, size_bytes: int = 100
    ) -> DelayOracle:
        """The idle one-way delay of `direction` for a `size_bytes` packet.

        Without a scheduling request the packet must fit one window (the size is then
        not needed).
        """
        grid = self.grid(direction)
        harq = (self.bler, self.max_retx, self.harq_s)
        fixed_s += self.core_delay_s
        if grid.access == "sr":
            return DelayOracle.scheduling_request(
                grid.occasions,
                grid.sr_windows,
                grid.period_s,
                grid.grant_delay_s,
                grid.first_grant_bytes,
                size_bytes,
                fixed_s,
                *harq,
            )
        windows = [(o.start_s, o.end_s) for o in grid.occasions]
        return DelayOracle(windows, grid.period_s, grid.lead_s, fixed_s, *harq)

    def rate_bps(self, direction: Direction) -> float:
        """Transport blocks per second of `direction`, in bit/s (retransmissions included)."""
        grid = self.grid(direction)
        return sum(o.capacity_bytes for o in grid.occasions) * 8 / grid.period_s

    def goodput_bps(self, direction: Direction) -> float:
        """What a saturated `direction` delivers: a share `bler` of the blocks are resends."""
        return self.rate_bps(direction) * (1.0 - self.bler)

    def check(self) -> None:
        """Raise `NrError` naming the field when a value is out of range."""
        pattern = self.pattern()
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
        if self.buffer_bytes is not None and not 1500 <= self.buffer_bytes <= 1 << 30:
            raise NrError(f"buffer_bytes must be 1500 to 2^30 bytes, got {self.buffer_bytes}")
        if self.rlc not in ("am", "um"):
            raise NrError(f"rlc must be am or um, got {self.rlc!r}")
        if not 0.0 <= self.rlc_status_s <= 1.0:
            raise NrError(f"rlc_status must be 0 to 1 s, got {self.rlc_status_s}")
        if not 1 <= self.rlc_max_retx <= 32:
            raise NrError(f"rlc_max_retx must be 1..32 (TS 38.331), got {self.rlc_max_retx}")
        if not 0.0 <= self.core_delay_s <= 1.0:
            raise NrError(f"core_delay must be 0 to 1 s, got {self.core_delay_s}")
        if self.ul_access not in UL_ACCESS:
            allowed = ", ".join(UL_ACCESS)
            raise NrError(f"ul_access must be one of {allowed}, got {self.ul_access!r}")
        for direction in ("uplink", "downlink"):
            if not occasions(pattern, direction, self.carrier()):  # type: ignore[arg-type]
                raise NrError(
                    f"{direction} has no window that carries data in {self.slots} "
                    f"{self.special} (windows too short for the DMRS)"
                )
        if self.ul_access == "sr":
            self._check_sr(pattern)
        elif self.ul_access == "configured":
            self._check_cg(pattern)

    def _check_sr(self, pattern: TddPattern) -> None:
        if self.sr_period_slots not in SR_PERIODS:
            raise NrError(
                f"sr_period must be one of TS 38.331's {', '.join(map(str, SR_PERIODS))} "
                f"slots, got {self.sr_period_slots}"
            )
        if not 0 <= self.sr_offset < self.sr_period_slots:
            raise NrError(
                f"sr_offset must be a slot of the SR period 0..{self.sr_period_slots - 1}, "
                f"got {self.sr_offset}"
            )
        if not 1 <= self.sr_grant_bytes <= 100_000:
            raise NrError(f"sr_grant must be 1..100000 bytes, got {self.sr_grant_bytes}")
        if not 0 <= self.grant_slots <= 32:
            raise NrError(f"grant_slots must be 0..32, got {self.grant_slots}")
        n = len(self.slots)
        uplink = {_slot_of(s, pattern.slot_s) for s, _, _ in pattern.windows("uplink")}
        for i in range(self.sr_offset, math.lcm(n, self.sr_period_slots), self.sr_period_slots):
            if i % n not in uplink:
                raise NrError(
                    f"an SR every {self.sr_period_slots} slots from slot {self.sr_offset} falls "
                    f"in slot {i % n} ({self.slots[i % n]}) of {self.slots}, which has no "
                    f"uplink symbols"
                )

    def _check_cg(self, pattern: TddPattern) -> None:
        if self.cg_period_slots not in CG_PERIODS:
            raise NrError(
                f"cg_period must be one of {', '.join(map(str, CG_PERIODS))} slots "
                f"(TS 38.331 ConfiguredGrantConfig), got {self.cg_period_slots}"
            )
        if not 0 <= self.cg_offset < self.cg_period_slots:
            raise NrError(
                f"cg_offset must be a slot of the grant period 0..{self.cg_period_slots - 1}, "
                f"got {self.cg_offset}"
            )
        n = len(self.slots)
        carrying = {
            _slot_of(o.start_s, pattern.slot_s)
            for o in occasions(pattern, "uplink", self.carrier())
        }
        for i in range(self.cg_offset, math.lcm(n, self.cg_period_slots), self.cg_period_slots):
            if i % n not in carrying:
                raise NrError(
                    f"a configured grant every {self.cg_period_slots} slots from slot "
                    f"{self.cg_offset} falls in slot {i % n} ({self.slots[i % n]}) of "
                    f"{self.slots}, which carries no uplink data"
                )

    def to_dict(self) -> dict[str, object]:
        return {**dataclasses.asdict(self), "special": list(self.special)}

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> Radio:
        data = dict(data)
        if "special" in data:
            data["special"] = tuple(data["special"])  # type: ignore[arg-type]
        return cls(**data)  # type: ignore[arg-type]


def _slot_of(t: float, slot: float) -> int:
    return math.floor(t / slot + 1e-9)


def _repeated(base: Sequence[Occasion], period_s: float, times: int) -> list[Occasion]:
    """`base`'s occasions over `times` consecutive periods."""
    return [
        Occasion(k * period_s + o.start_s, k * period_s + o.end_s, o.capacity_bytes)
        for k in range(times)
        for o in base
    ]


# OpenAirInterface's default band-78 gNB, gnb.sa.band78.fr1.106PRB.usrpb210.conf:
# subcarrierSpacing 1 (30 kHz), dl_UL_TransmissionPeriodicity 6 (5 ms) with
# nrofDownlinkSlots 7, nrofDownlinkSymbols 6, nrofUplinkSymbols 4, nrofUplinkSlots 2;
# 106 PRBs; min_rxtxtime 2 (K2 = 2 slots). MCS 20 is a mid-cell link adaptation choice
# (an assumption, not from the file).
_OAI_TDD_30K = Radio(
    slots="DDDDDDDSUU",
    special=(6, 4, 4),
    numerology=1,
    n_prb=106,
    mcs=20,
    k2_slots=2,
    bler=0.1,  # OAI's link adaptation targets 10% first-transmission BLER
    max_retx=4,  # OAI's and srsRAN's default HARQ retransmissions
    harq_slots=2,  # min_rxtxtime 2
    ul_access="sr",
    sr_period_slots=10,  # nr_rrc_config.c: sl10 for an SR slot offset below 10
    sr_offset=7,  # "SR in the first uplink slot": nrofDownlinkSlots, the special slot
    sr_grant_bytes=72,  # an assumption: srsRAN's 576-bit first grant (issue #603)
    grant_slots=2,  # an assumption; any of 0..7 puts the PUSCH one period after the SR
    cg_period_slots=10,  # for ul_access: configured, once per TDD period...
    cg_offset=8,  # ...in its first full uplink slot
)

#: Named radios, each value with its source: TDD windows, transport blocks, uplink access (SR
#: and grants, or a configured grant), HARQ, RLC and, for a commercial cell, the core's distance.
RADIO_PROFILES: dict[str, Radio] = {
    "oai-tdd-30k": _OAI_TDD_30K,
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
        ul_access="sr",
        sr_period_slots=4,  # SR every 2 ms (low_latency.yml)
        sr_offset=3,  # in the uplink slot
        sr_grant_bytes=72,  # the 576-bit first grant of srsRAN's issue #603 log
        # PUSCH 8 slots after the SR slot: of what this pattern allows (its uplink slots are
        # 4 apart), the nearest to the SR -> grant -> PUSCH of 9 slots measured in #603.
        grant_slots=2,
        cg_period_slots=4,
        cg_offset=3,
    ),
    # A commercial mid-band (n78/n77) cell as measurements see one, not any operator's
    # configuration. 30 kHz and a 5 ms DDDDDDDSUU frame: the LTE-compatible 3.5 GHz frame of
    # the GSMA's "5G TDD Synchronisation" guidelines (2020). 273 PRBs: a 100 MHz carrier at
    # 30 kHz (TS 38.101-1 Table 5.3.2-1). An SR every 10 ms, the short end of the 10-20 ms
    # that commercial cells configure (issue #16); RLC-AM status after 20 ms; the core ~3 ms
    # from the gNB each way. By the oracle an idle UE's 92-byte packet then takes ~19 ms up
    # and ~5 ms down (median), a ~24 ms round trip: Rohde & Schwarz measured one-way delays
    # of under 7 ms down and up to ~18 ms up on Deutsche Telekom's public 5G in Munich
    # (M. Kottkamp, "5G NR and LTE latency analysis in a public network", 2022), and issue
    # #16 puts commercial median RTTs at 20-30 ms. MCS 16 (a mid-cell link) is an assumption.
    # Of OAI's profile, the frame, K2, HARQ and RLC; the rest as above.
    "commercial-midband": dataclasses.replace(
        _OAI_TDD_30K,
        n_prb=273,
        mcs=16,
        sr_period_slots=20,  # 10 ms at 30 kHz
        sr_offset=8,  # the first full uplink slot of the first 5 ms
        grant_slots=3,  # an assumption: a commercial scheduler a little slower than OAI's
        core_delay_s=0.003,
    ),
}
