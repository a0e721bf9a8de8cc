"""5G NR air-interface timing and capacity: numerology, TDD patterns, transport block sizes.

Pure functions and frozen data, no clock and no packets; `netem.nr.ue.Slots` is the stage that
gates packets with them, `netem.nr.radio.Radio` a link's whole air interface as plain data, and
`netem.nr.oracle.DelayOracle` the closed-form one-way delay a test or a link self-test compares
measurements with.

Nouns:
- `TddPattern`: one TDD-UL-DL period as people write it (`DDDDDDDSUU`, `DDDSU`), the special
  slot's DL / guard / UL symbols, and the numerology µ (slot = 1 ms / 2^µ, TS 38.211 §4.2).
  `windows(direction)` are the stretches of one period in which that direction may send.
- `Carrier`: PRBs, MCS (TS 38.214 Table 5.1.3.1-1), layers and DMRS overhead per direction;
  `tbs_bits(symbols)` is the transport block one window of that many symbols carries
  (TS 38.214 §5.1.3.2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from netem.directions import Direction

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
    #: The block's bytes at each MCS of a radio's `mcs_mix`, in its order (empty: none).
    alternatives: tuple[int, ...] = ()


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
