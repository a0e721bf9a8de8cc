"""A link's NR air interface as plain data (`Radio`), the grid of occasions a direction sends
in (`Grid`), and the named radios of real gNBs (`RADIO_PROFILES`).

srsRAN's low-latency log, cited below: a gNB log of srsRAN Project's `configs/low_latency.yml`
posted to its GitHub tracker (https://github.com/srsran/srsRAN_Project/issues/603), where an
SR, its grant and the PUSCH span 9 slots and the first grant carries 576 bits.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

from netem.directions import DIRECTIONS, Direction
from netem.nr.oracle import DelayOracle
from netem.nr.phy import (
    MCS_TABLE_1,
    Carrier,
    NrError,
    Occasion,
    TddPattern,
    slot_s,
)

#: How an uplink gets its grants: `sr` asks with a scheduling request, then its buffer
#: status reports bring the grants (TS 38.321 §5.4.4, §5.4.5); `sr_free` is granted in every
#: uplink slot without asking (srsRAN's SR-free access, Gong et al., OpenRIT6G'25); `configured`
#: sends in a configured grant's periodic occasions without asking (type 1, TS 38.321 §5.8.2);
#: `ideal` is a gNB that sees the UE's buffer as data arrives (no request: a bound, not a cell).
UL_ACCESS = ("sr", "sr_free", "configured", "ideal")
#: Slot periods TS 38.331 allows for an SR resource (periodicityAndOffset, sl1..sl640).
SR_PERIODS = (1, 2, 4, 5, 8, 10, 16, 20, 40, 80, 160, 320, 640)
#: Configured grant periods in whole slots (TS 38.331 ConfiguredGrantConfig periodicity,
#: n x 14 symbols; the 2- and 7-symbol ones are left out).
CG_PERIODS = (1, 2, 4, 5, 8, 10, 16, 20, 32, 40, 64, 80, 128, 160, 256, 320, 512, 640)


@dataclass(frozen=True)
class Grid:
    """What a `netem.nr.ue.Slots` stage needs to send one direction of a radio.

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
    #: little data (576 bits in srsRAN's low-latency log).
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
    #: The gNB's scheduling offset S and radio offset R, in slots: the MAC decides a slot's
    #: content S + R slots before it is on the air (srsRAN: S = 1, R = 3 by default; Gong et
    #: al., "Towards URLLC with Open-Source 5G Software", OpenRIT6G'25). Given (both), they
    #: are the gNB's turnaround: downlink data is scheduled S + R slots ahead, and a grant's
    #: DCI leaves S + R slots after the SR or buffer status report that asked for it
    #: (`grant_slots` is then not used). None: the downlink needs `k2_slots`, grants
    #: `grant_slots`.
    sched_offset_slots: int | None = None
    radio_offset_slots: int | None = None
    #: The UE's own processing each way, which no 3GPP timer bounds: from the application to
    #: its MAC buffer (uplink) and from a decoded block to the application (downlink); a
    #: modem on USB adds a millisecond or two. A case calibrates it on one measurement and
    #: is judged on the others (scenarios/fidelity).
    ue_ul_delay_s: float = 0.0
    ue_dl_delay_s: float = 0.0
    #: What one uplink grant may use: PRBs and PUSCH symbols (None: the cell's PRBs, the
    #: window's symbols). OpenAirInterface's EDAF measurements granted 5 PRBs x 3 symbols, so
    #: a 128-byte packet left in several RLC segments, one per uplink slot.
    ul_prbs: int | None = None
    ul_symbols: int | None = None
    #: What each block carries besides data: MAC subheaders, a buffer status report and the
    #: RLC header (bytes). EDAF's 48-byte OAI grants carried 43-byte RLC PDUs of which 38
    #: were data: 5 bytes of MAC and 3-5 of RLC.
    l2_overhead_bytes: int = 0
    #: (MCS, share) of the blocks: link adaptation on a fading channel picks each block's MCS,
    #: and a block carries that MCS's bytes (EDAF's OAI uplink: MCS 19 in 59% of blocks, 16
    #: in 29%). Empty: every block at `mcs`. The oracle, for packets of one block, needs none.
    mcs_mix: tuple[tuple[int, float], ...] = ()

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
    def offsets_slots(self) -> int | None:
        """S + R (`sched_offset_slots`, `radio_offset_slots`), or None where not given."""
        if self.sched_offset_slots is None or self.radio_offset_slots is None:
            return None
        return self.sched_offset_slots + self.radio_offset_slots

    @property
    def lead_s(self) -> float:
        """How long before its slot a downlink (or `ideal` uplink) packet must be there."""
        offsets = self.offsets_slots
        return (self.k2_slots if offsets is None else offsets) * slot_s(self.numerology)

    @property
    def turnaround_slots(self) -> int:
        """From a decoded SR or buffer status report to the DCI of its grant."""
        offsets = self.offsets_slots
        return self.grant_slots if offsets is None else offsets

    def ue_delay_s(self, direction: Direction) -> float:
        return self.ue_ul_delay_s if direction == "uplink" else self.ue_dl_delay_s

    def access(self, direction: Direction) -> str:
        return self.ul_access if direction == "uplink" else "ideal"

    def _occasions(self, direction: Direction) -> list[Occasion]:
        """One TDD period's occasions of `direction` with the data each block carries: an
        uplink grant's PRBs and symbols capped by `ul_prbs` and `ul_symbols`, every block less
        its `l2_overhead_bytes`."""
        pattern = self.pattern()
        carrier = self.carrier()
        capped = direction == "uplink" and (self.ul_prbs is not None or self.ul_symbols is not None)
        if capped:
            carrier = dataclasses.replace(carrier, n_prb=min(self.n_prb, self.ul_prbs or 275))
        out = []
        for start, end, symbols in pattern.windows(direction):
            used = min(symbols, self.ul_symbols or symbols) if capped else symbols
            capacity = carrier.tbs_bits(used) // 8 - self.l2_overhead_bytes
            if capacity > 0:
                out.append(Occasion(start, end, capacity))
        return out

    def grid(self, direction: Direction) -> Grid:
        """The occasions of `direction` and how its packets get them (each occasion with its
        bytes at every MCS of `mcs_mix`, where there is one)."""
        grid = self._grid(direction)
        if not self.mcs_mix:
            return grid
        mixes = [
            dataclasses.replace(self, mcs=m, mcs_mix=()).grid(direction).occasions
            for m, _ in self.mcs_mix
        ]
        if any(len(m) != len(grid.occasions) for m in mixes):
            raise NrError("an MCS of mcs_mix leaves a window without data: raise it")
        mixed = tuple(
            dataclasses.replace(o, alternatives=tuple(m[i].capacity_bytes for m in mixes))
            for i, o in enumerate(grid.occasions)
        )
        return dataclasses.replace(grid, occasions=mixed)

    def _grid(self, direction: Direction) -> Grid:
        pattern, slot = self.pattern(), slot_s(self.numerology)
        base = self._occasions(direction)
        access = self.access(direction)
        if access == "ideal":
            return Grid(tuple(base), pattern.period_s, self.lead_s)
        if access == "sr_free":
            # A grant before every uplink slot: the UE needs no more than its own processing.
            return Grid(tuple(base), pattern.period_s, 0.0, "configured")
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
            (self.turnaround_slots + self.k2_slots) * slot,
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
        fixed_s += self.core_delay_s + self.ue_delay_s(direction)
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
        for name in ("sched_offset_slots", "radio_offset_slots"):
            value = getattr(self, name)
            if value is not None and not 0 <= value <= 16:
                raise NrError(f"{name.removesuffix('_slots')} must be 0..16 slots, got {value}")
        if (self.sched_offset_slots is None) != (self.radio_offset_slots is None):
            raise NrError("sched_offset and radio_offset go together: give both or neither")
        for name in ("ue_ul_delay_s", "ue_dl_delay_s"):
            if not 0.0 <= getattr(self, name) <= 0.1:
                raise NrError(f"{name[:-2]} must be 0 to 100 ms, got {getattr(self, name)}")
        for m, share in self.mcs_mix:
            if not 0 <= m < len(MCS_TABLE_1) or not 0.0 < share <= 1.0:
                raise NrError(f"mcs_mix needs (MCS 0..28, share in (0, 1]), got {(m, share)}")
        if self.mcs_mix and abs(sum(share for _, share in self.mcs_mix) - 1.0) > 1e-6:
            raise NrError("mcs_mix's shares must add up to 1")
        if not 0 <= self.l2_overhead_bytes <= 64:
            raise NrError(f"l2_overhead must be 0..64 bytes, got {self.l2_overhead_bytes}")
        if not 0 <= self.dmrs_re_per_prb <= 48:
            raise NrError(f"dmrs_re must be 0..48 resource elements, got {self.dmrs_re_per_prb}")
        if self.ul_prbs is not None and not 1 <= self.ul_prbs <= 275:
            raise NrError(f"ul_prbs must be 1..275, got {self.ul_prbs}")
        if self.ul_symbols is not None and not 1 <= self.ul_symbols <= 14:
            raise NrError(f"ul_symbols must be 1..14, got {self.ul_symbols}")
        if self.ul_access not in UL_ACCESS:
            allowed = ", ".join(UL_ACCESS)
            raise NrError(f"ul_access must be one of {allowed}, got {self.ul_access!r}")
        for direction in DIRECTIONS:
            if not self._occasions(direction):  # type: ignore[arg-type]
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
        carrying = {_slot_of(o.start_s, pattern.slot_s) for o in self._occasions("uplink")}
        for i in range(self.cg_offset, math.lcm(n, self.cg_period_slots), self.cg_period_slots):
            if i % n not in carrying:
                raise NrError(
                    f"a configured grant every {self.cg_period_slots} slots from slot "
                    f"{self.cg_offset} falls in slot {i % n} ({self.slots[i % n]}) of "
                    f"{self.slots}, which carries no uplink data"
                )

    def to_dict(self) -> dict[str, object]:
        return {
            **dataclasses.asdict(self),
            "special": list(self.special),
            "mcs_mix": [list(x) for x in self.mcs_mix],
        }

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> Radio:
        data = dict(data)
        if "special" in data:
            data["special"] = tuple(data["special"])  # type: ignore[arg-type]
        if "mcs_mix" in data:
            data["mcs_mix"] = tuple(tuple(x) for x in data["mcs_mix"])  # type: ignore[attr-defined]
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
# No fidelity case measured this cell: EDAF's OAI gNB (`oai-usrp-edaf`) ran another frame
# (an uplink period every 2.5 ms), grants of 5 PRBs x 3 symbols and 7.2% of blocks
# retransmitted. This profile assumes the 5 ms frame of the file, full-width grants, the SR
# and grant timing below, MCS 20 and a 10% BLER with 2-slot HARQ, and no UE processing time.
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
    sr_grant_bytes=72,  # an assumption: the 576-bit first grant of srsRAN's low-latency log
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
    # The measured srsRAN cell is `srsran-urllc`; this one folds the scheduling and radio
    # offsets into grant_slots and K2 and leaves out the UE's own processing (the 1-2 ms per
    # direction that case calibrated), so its delays are a cell's, not a UE's.
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
        sr_grant_bytes=72,  # the 576-bit first grant of srsRAN's low-latency log
        # PUSCH 8 slots after the SR slot: of what this pattern allows (its uplink slots are
        # 4 apart), the nearest to the SR -> grant -> PUSCH of 9 slots measured there.
        grant_slots=2,
        cg_period_slots=4,
        cg_offset=3,
    ),
    # srsRAN Project with the URLLC changes of Gong et al., "Towards URLLC with Open-Source 5G
    # Software", OpenRIT6G'25 (doi 10.1145/3750718.3750743), as its repository configures it
    # (aygong/srsRAN_Project_Low_Latency, configs/gnb_low_latency.yml) in its stock variant;
    # scenarios/fidelity/srsran_urllc.yaml changes S, R and the access as the paper did.
    "srsran-urllc": Radio(
        slots="DDSU",  # tdd_ul_dl_cfg: dl_ul_tx_period 4, nof_dl_slots 2, nof_ul_slots 1
        special=(8, 6, 0),  # nof_dl_symbols 8, nof_ul_symbols 0
        numerology=1,  # common_scs 30
        n_prb=51,  # channel_bandwidth_MHz 20 at 30 kHz (TS 38.101-1 Table 5.3.2-1)
        mcs=20,  # an assumption (pdsch/pusch mcs_table qam64; the index is not stated)
        k2_slots=2,  # pusch min_k2 2
        harq_slots=2,  # pucch min_k1 2
        bler=0.0,  # an assumption: a bench link (the paper gives no BLER)
        max_retx=4,
        ul_access="sr",  # sr_free_access_enable false
        sr_period_slots=4,  # pucch sr_period_ms 2
        sr_offset=3,  # the uplink slot
        sr_grant_bytes=512,  # slicing sched_cfg min_ul_grant_size 512
        sched_offset_slots=1,  # S = 1, srsRAN's default (the paper's slides)
        radio_offset_slots=3,  # R = 3: expert_phy radio_heads_prep_time 3
        # The UE's own processing (a Quectel module on USB), which the paper does not split
        # out: calibrated on the stock variant's means (DL 3.59, UL 7.44 ms) less this
        # model's (2.82, 5.50 ms); the other three variants are judged with it unchanged.
        ue_ul_delay_s=0.00194,
        ue_dl_delay_s=0.00077,
    ),
    # OpenAirInterface's gNB on a USRP as EDAF measured it, packet by packet (Mostafavi et
    # al., arXiv 2401.09856; samiemostafavi/edaf res.parquet at a15e812, Apache-2.0):
    # scenarios/fidelity/oai_usrp_edaf.yaml. The repository has no gNB configuration file,
    # so most fields are read from the data ("data:"), as scenarios/fidelity/data/edaf says.
    "oai-usrp-edaf": Radio(
        slots="DDDSU",  # data: PUSCH in one slot per 2.5 ms (slots 3, 8, 13, 18 of a frame)
        special=(10, 4, 0),  # data: no PUSCH in the special slot
        numerology=1,  # edaf/core/uplink/decompose.py: 0.5 ms slots
        n_prb=106,  # README.md: the 106-PRB (40 MHz) example configuration
        mcs=16,
        # data: the 5-PRB blocks are 48 bytes (66%) or 57 (34%): MCS 16 or 19 with 6 DMRS
        # resource elements per PRB
        mcs_mix=((16, 0.66), (19, 0.34)),
        dmrs_re_per_prb=6,
        ul_prbs=5,  # data: 72% of the grants; the first grant of an idle UE 617 times in 658
        ul_symbols=3,  # data: every grant
        l2_overhead_bytes=10,  # data: 5 bytes of MAC, 3-5 of RLC header per segment
        k2_slots=2,  # OAI's min_rxtxtime 2
        bler=0.072,  # data: 7.22% of the transport blocks were sent again
        max_retx=1,  # data: no block needed a second retransmission
        harq_slots=10,  # data: a retransmission 3 uplink periods (7.46-7.55 ms) later
        ul_access="sr",
        sr_period_slots=5,  # an SR in every uplink slot (not logged): an idle UE's packet
        sr_offset=4,  # left in the 2nd uplink slot after it came in 322 of 658 cases
        sr_grant_bytes=1000,  # the first grant is a whole 5-PRB block
        grant_slots=2,
        # data: 2.9% of packets ~25 ms late with no HARQ retransmission logged: a block lost
        # twice (0.072^2) comes back by RLC-AM's status, ~10 ms later
        rlc_status_s=0.01,
    ),
    # Ericsson's 5G SA trial network at the 5G Industry Campus Europe (3.7 GHz, 100 MHz), as
    # DETERMINISTIC6G's PD-Wireless-5G-2a histograms measured it (scenarios/fidelity/
    # sa_midband_ericsson.yaml). The data set states the band, the carrier and the traffic
    # only; the rest is chosen by the histograms' shapes and said so.
    "sa-midband-ericsson": Radio(
        slots="DDDSU",  # an assumption: a 2.5 ms period, the width of the uplink's spread
        special=(6, 4, 4),  # an assumption
        numerology=1,  # 30 kHz, the n78 numerology for 100 MHz
        n_prb=273,  # 100 MHz at 30 kHz (TS 38.101-1 Table 5.3.2-1)
        mcs=16,  # an assumption (100-byte frames fit any)
        k2_slots=2,
        bler=0.12,  # the share of frames in the downlink's tail one HARQ round later
        harq_slots=4,  # puts that tail 2.5 ms later, where the histogram has it
        max_retx=4,
        # A grant in every uplink slot (the periodic industrial traffic's configured or
        # proactive grants): the uplink spreads over one period, as measured, not over an SR
        # round trip.
        ul_access="sr_free",
        # The UE, the TSN translators and the core, which the data set does not split:
        # calibrated on the two medians (5.33, 6.43 ms) less this model's (1.82, 1.42 ms).
        ue_dl_delay_s=0.00351,
        ue_ul_delay_s=0.00501,
    ),
    # A public n78 network as a vehicle measured it at 20 Hz to a cloud server and back
    # (CICV5G, Zhang et al., Zenodo 10.5281/zenodo.17475688, CC BY 4.0; scenarios/fidelity/
    # public_n78_cicv5g.yaml). The data gives round trips, cells and signal, not the cells'
    # configuration; the frame is the 2.5 ms double period Chinese n78 networks run.
    "public-n78-cicv5g": Radio(
        slots="DDDSUDDSUU",  # an assumption: the 5 ms "2.5 ms double period" frame
        special=(10, 2, 2),  # an assumption
        numerology=1,
        n_prb=273,  # 100 MHz at 30 kHz
        mcs=16,  # an assumption (100-byte messages fit any)
        k2_slots=2,
        # Chosen with core_delay to match the data's median and 95th percentile (a moving
        # vehicle's first transmissions fail more often than link adaptation's 10%).
        bler=0.25,
        harq_slots=2,
        ul_access="sr",
        sr_period_slots=10,  # an assumption: an SR every 5 ms, in the first uplink slot
        sr_offset=4,
        sr_grant_bytes=72,
        grant_slots=2,
        core_delay_s=0.00225,  # the core and the cloud server each way, from the least RTT
    ),
    # A commercial mid-band (n78/n77) cell as measurements see one, not any operator's
    # configuration. 30 kHz and a 5 ms DDDDDDDSUU frame: the LTE-compatible 3.5 GHz frame of
    # the GSMA's "5G TDD Synchronisation" guidelines (2020). 273 PRBs: a 100 MHz carrier at
    # 30 kHz (TS 38.101-1 Table 5.3.2-1). An SR every 10 ms, the short end of the 10-20 ms
    # that commercial cells configure; RLC-AM status after 20 ms; the core ~3 ms
    # from the gNB each way. By the oracle an idle UE's 92-byte packet then takes ~19 ms up
    # and ~5 ms down (median), a ~24 ms round trip: Rohde & Schwarz measured one-way delays
    # of under 7 ms down and up to ~18 ms up on Deutsche Telekom's public 5G in Munich
    # (M. Kottkamp, "5G NR and LTE latency analysis in a public network", 2022), and public
    # measurements put commercial median RTTs at 20-30 ms. MCS 16 (a mid-cell link) is an
    # assumption.
    # Of OAI's profile, the frame, K2, HARQ and RLC; the rest as above. No fidelity case
    # measured this cell: CICV5G's public n78 network had a median round trip of 16 ms to a
    # cloud server, this profile's is ~21 ms (`testbed fidelity --model` beside
    # public-n78-cicv5g), the Ericsson trial's one-way medians 5.3/6.4 ms. It assumes the
    # slower SR (10 ms) and frame (5 ms, two uplink slots) a macro cell tuned for capacity
    # runs.
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
