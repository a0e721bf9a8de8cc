"""The 5G NR air interface of schema v1: a named radio with some of its fields changed
(`RADIO`, per link direction), the cell-level part of it (`CELL_RADIO`: slot grid and
scheduler) and the UE's RRC states (`RRC`).
"""

from __future__ import annotations

from netem.nr.policy import SCHEDULERS
from netem.nr.radio import RADIO_PROFILES, UL_ACCESS
from netem.nr.rrc import RrcSettings
from testbed.scenario.kinds import (
    Bool,
    Duration,
    Either,
    Enum,
    Field,
    Int,
    Nullable,
    Obj,
    Percent,
    Str,
)
from testbed.scenario.schema_v1.shared import MAX_DURATION_S

RADIO = Obj(
    "A 5G NR air interface: a named radio with some of its fields changed. A mapping starts"
    " from its `profile` (default oai-tdd-30k), in a `set` event too: name the profile there"
    " to change another one.",
    [
        Field(
            "profile",
            Enum(tuple(RADIO_PROFILES)),
            "The named radio these fields change (default oai-tdd-30k).",
            attr=None,
        ),
        Field(
            "tdd",
            Str("a TDD pattern of D, S and U slots like DDDDDDDSUU", r"^[DSU]{1,160}$"),
            "Slots of one TDD period: D downlink, S special, U uplink (TS 38.331).",
            attr=None,
        ),
        Field(
            "special_dl",
            Int(0, 14, noun="a number of symbols"),
            "Downlink symbols of the special slot.",
            attr=None,
        ),
        Field(
            "special_ul",
            Int(0, 14, noun="a number of symbols"),
            "Uplink symbols of the special slot; the rest of its 14 are the guard.",
            attr=None,
        ),
        Field(
            "numerology",
            Int(0, 4, noun="a numerology µ"),
            "µ: subcarrier spacing 15·2^µ kHz, slot 1 ms / 2^µ (TS 38.211 §4.2).",
            attr=None,
        ),
        Field("prbs", Int(1, 275, noun="a number of PRBs"), "Resource blocks.", attr=None),
        Field(
            "mcs",
            Int(0, 28, noun="an MCS index of TS 38.214 Table 5.1.3.1-1"),
            "Modulation and coding scheme (64QAM table).",
            attr=None,
        ),
        Field("layers", Int(1, 4, noun="a number of MIMO layers"), "MIMO layers.", attr=None),
        Field(
            "bler",
            Percent(noun="a block error rate"),
            "First-transmission block error rate (10% is what link adaptation aims at).",
            attr=None,
        ),
        Field(
            "max_retx",
            Int(0, 16, noun="a number of HARQ retransmissions"),
            "Retransmissions of a failed block before it is lost.",
            attr=None,
        ),
        Field(
            "harq_slots",
            Int(0, 32, noun="a number of slots"),
            "Slots from a failed block's end to the earliest slot of its retransmission.",
            attr=None,
        ),
        Field(
            "k2",
            Int(0, 32, noun="a number of slots"),
            "K2: slots from a grant's DCI to the PUSCH it grants (for the downlink and an"
            " `ideal` uplink: how long before its slot a packet must be there).",
            attr=None,
        ),
        Field(
            "access",
            Enum(UL_ACCESS),
            "How the uplink gets grants: sr (a scheduling request, then grants from buffer"
            " status reports), sr_free (a grant in every uplink slot, srsRAN's SR-free"
            " access), configured (a configured grant, no request) or ideal (a gNB that sees"
            " the UE's buffer at once: a bound).",
            attr=None,
        ),
        Field(
            "sr_period",
            Int(1, 640, noun="a number of slots"),
            "Slots between SR occasions (TS 38.331: 1, 2, 4, 5, 8, 10, 16, 20, 40 ... 640).",
            attr=None,
        ),
        Field(
            "sr_offset",
            Int(0, 639, noun="a slot"),
            "The slot of the SR period that has the SR; it must have uplink symbols.",
            attr=None,
        ),
        Field(
            "sr_grant",
            Int(1, 100_000, noun="a number of bytes"),
            "Bytes of the first grant after an SR (small: a buffer status report and a little"
            " data).",
            attr=None,
        ),
        Field(
            "grant_slots",
            Int(0, 32, noun="a number of slots"),
            "gNB processing from a decoded SR or buffer status report to its grant's DCI.",
            attr=None,
        ),
        Field(
            "cg_period",
            Int(1, 640, noun="a number of slots"),
            "Slots between configured-grant occasions (access: configured).",
            attr=None,
        ),
        Field(
            "cg_offset",
            Int(0, 639, noun="a slot"),
            "The slot of the configured-grant period that carries it.",
            attr=None,
        ),
        Field(
            "rlc",
            Enum(("am", "um")),
            "RLC mode: am sends the packets of a block HARQ gave up on again (after"
            " `rlc_status`), um loses them.",
            attr=None,
        ),
        Field(
            "rlc_status",
            Duration(1.0, noun="a delay"),
            "From a block HARQ gave up on to its packets being sent again (RLC-AM's status"
            " report).",
            attr=None,
        ),
        Field(
            "rlc_max_retx",
            Int(1, 32, noun="a number of RLC retransmissions"),
            "RLC-AM's maxRetxThreshold: times a packet is sent again before it is lost"
            " (OpenAirInterface: 32).",
            attr=None,
        ),
        Field(
            "buffer",
            Int(1500, 1 << 30, noun="a number of bytes"),
            "Bytes this UE's buffer holds in this direction (drop-tail beyond).",
            attr=None,
        ),
        Field(
            "in_order",
            Bool(),
            "PDCP in-order delivery: a packet waits for those before it (false: each leaves"
            " when decoded).",
            attr=None,
        ),
        Field(
            "core_delay",
            Duration(1.0, noun="a delay"),
            "One-way delay from the gNB to the core carried in this direction (0: the"
            " backhaul link holds it).",
            attr=None,
        ),
        Field(
            "sched_offset",
            Int(0, 16, noun="a number of slots"),
            "The gNB's scheduling offset S: slots between the MAC's decision and the PHY's"
            " (srsRAN: 1). With radio_offset it replaces grant_slots and the downlink's k2.",
            attr=None,
        ),
        Field(
            "radio_offset",
            Int(0, 16, noun="a number of slots"),
            "The gNB's radio offset R: slots the PHY and radio head get ahead of the air"
            " (srsRAN: 3).",
            attr=None,
        ),
        Field(
            "ue_delay_ul",
            Duration(0.1, noun="a delay"),
            "The UE's own processing from the application to its MAC buffer.",
            attr=None,
        ),
        Field(
            "ue_delay_dl",
            Duration(0.1, noun="a delay"),
            "The UE's own processing from a decoded block to the application.",
            attr=None,
        ),
        Field(
            "ul_prbs",
            Int(1, 275, noun="a number of PRBs"),
            "PRBs one uplink grant may use (default: the cell's); small grants segment packets.",
            attr=None,
        ),
        Field(
            "ul_symbols",
            Int(1, 14, noun="a number of symbols"),
            "PUSCH symbols one uplink grant may use (default: the window's).",
            attr=None,
        ),
        Field(
            "l2_overhead",
            Int(0, 64, noun="a number of bytes"),
            "Bytes of MAC subheaders, buffer status report and RLC header per block (default 0).",
            attr=None,
        ),
        Field(
            "dmrs_re",
            Int(0, 48, noun="a number of resource elements"),
            "Resource elements per PRB the DMRS takes in a block (default 12: one front-loaded"
            " symbol, both CDM groups).",
            attr=None,
        ),
    ],
    fill_defaults=False,
    ref="radio",
)
RADIO_VALUE = Either(Enum(tuple(RADIO_PROFILES)), RADIO)
#: The fields of a radio that belong to the cell (its slot grid and carrier), not to a UE.
CELL_RADIO_KEYS = ("profile", "tdd", "special_dl", "special_ul", "numerology", "prbs")
CELL_RADIO = Obj(
    "The cell-level part of the radios of a gNB's air links: its TDD pattern, numerology and"
    " PRBs (one gNB, one slot grid), and how it schedules. A `profile` takes those fields from"
    " a named radio and gives that radio to the air links that have none.",
    [
        *(f for f in RADIO.fields if f.key in CELL_RADIO_KEYS),
        Field(
            "scheduler",
            Enum(SCHEDULERS),
            "How the gNB shares its slots among its UEs: rr or pf (as the cell's scheduler).",
            attr=None,
        ),
    ],
    fill_defaults=False,
    ref="cell_radio",
)


RRC = Obj(
    "RRC states of the UE on an air link (userspace backend): after `inactivity` without a"
    " packet the network suspends it (RRC_INACTIVE, TS 38.331 §5.3.8), `idle_after` later"
    " releases it (RRC_IDLE); the first packet after that pays `resume` (§5.3.13) or `setup`"
    " (random access and RRC setup, §5.3.3). Both directions' packets count as activity.",
    [
        Field(
            "inactivity",
            Duration(3600.0, lo_open=True, noun="an inactivity timer"),
            "Quiet time before CONNECTED -> INACTIVE (a common operator setting: 10 s).",
            attr="inactivity_s",
        ),
        Field(
            "idle_after",
            Nullable(Duration(MAX_DURATION_S, noun="a time in INACTIVE")),
            "Further quiet time before INACTIVE -> IDLE (0: no INACTIVE, straight to IDLE;"
            " null: never IDLE). Default 60 s.",
            attr="idle_after_s",
        ),
        Field(
            "resume",
            Duration(10.0, noun="a resume delay"),
            "What the first packet in INACTIVE waits: RRC resume (default 30 ms).",
            attr="resume_s",
        ),
        Field(
            "setup",
            Duration(10.0, noun="a setup delay"),
            "What the first packet in IDLE waits: random access and RRC setup (default 150 ms).",
            attr="setup_s",
        ),
    ],
    model=RrcSettings,
    ref="rrc",
)
