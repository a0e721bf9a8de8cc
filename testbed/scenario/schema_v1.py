"""Schema v1, declared once: every field of a scenario file, its kind, unit, default, allowed
values and doc string.

`SCENARIO` is the whole file: `topology` (cells and vehicles), `links` (backend, air and
backhaul profiles, per-link overrides), `timeline` (set / shape / clear / outage / trace
events), `workload` (learner, fusion, Kalman), `record` and `report`. The loader checks a file
against it (`SCENARIO.check`) and builds the model dataclasses from the sections
(`CELL.build`...); `json_schema()` is what `testbed schema` writes. Defaults come from the
dataclasses of `model.py`; the kinds themselves (how a duration or a mapping is checked) are
in `kinds.py`, the rules that join fields in `loader.py`.
"""

from __future__ import annotations

from typing import Any

from netem.nr.channel import CARRIER_RANGE_GHZ, LOS_MODES, MODELS, UE_HEIGHT_RANGE_M
from netem.nr.policy import SCHEDULERS
from netem.nr.radio import RADIO_PROFILES, UL_ACCESS
from netem.nr.rrc import RrcSettings
from netem.profile import JITTER_DISTRIBUTIONS, GilbertElliott, LinkProfile
from testbed.scenario import model
from testbed.scenario.kinds import (
    Argv,
    Bool,
    Const,
    Duration,
    Either,
    Enum,
    Field,
    Float,
    Int,
    ListOf,
    MapOf,
    Nullable,
    Obj,
    Percent,
    PrivateNetwork,
    Rate,
    Str,
    Tagged,
    Word,
)

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

NODE_NAME_PATTERN = r"^[a-z][a-z0-9]{0,9}$"
HOST_NAME_PATTERN = r"^[a-z][a-z0-9-]{0,31}$"
IPV4_ADDRESS_PATTERN = r"^[0-9]{1,3}(\.[0-9]{1,3}){3}$"
LINK_NAME_PATTERN = r"^[a-z][a-z0-9]{0,9}-[a-z][a-z0-9]{0,9}$"
SCENARIO_NAME_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,31}$"

MAX_DURATION_S = 24 * 3600.0
MAX_DELAY_S = 10.0

NODE_NAME_WHY = (
    "node names become interface, namespace and process names and appear in shell commands, "
    "so they are short lowercase words"
)


def node_name(what: str) -> Str:
    return Str(
        f"{what}: a lowercase letter then up to 9 lowercase letters or digits, like av1",
        NODE_NAME_PATTERN,
        NODE_NAME_WHY,
    )


LINK_NAME = Str(
    "a link name like av1-gnb1 (vehicle-gnb) or gnb1-core1 (gnb-core)",
    LINK_NAME_PATTERN,
)
AT = Field(
    "at",
    Duration(MAX_DURATION_S, noun="a time"),
    "When the event happens, from the start of the run (0 to the scenario's duration).",
    required=True,
)
CPU = Nullable(Float(0.0, 1024.0, lo_open=True, noun="a number of CPU cores"))
WORKLOAD_KIND = Enum(("edgeloc", "none"))

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
            " status reports), configured (a configured grant, no request) or ideal (a gNB"
            " that sees the UE's buffer at once: a bound).",
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

# Each profile key maps to one or more LinkProfile attributes; `loader.profile_changes` says how.
PROFILE_FIELDS: tuple[Field, ...] = (
    Field(
        "rate",
        Rate(unlimited=True),
        "Bandwidth of this direction, tc units (bit, kbit, mbit, gbit; mbps is refused "
        "because tc reads it as megabytes/s), or unlimited.",
        attr="rate_bps",
    ),
    Field(
        "delay",
        Duration(MAX_DELAY_S, noun="a delay"),
        "One-way delay added to every packet.",
        attr="delay_s",
    ),
    Field(
        "jitter",
        Duration(MAX_DELAY_S, noun="a jitter"),
        "Spread of the delay around its mean.",
        attr="jitter_s",
    ),
    Field(
        "jitter_distribution",
        Enum(JITTER_DISTRIBUTIONS),
        "Shape of the delay spread.",
    ),
    Field(
        "loss",
        Either(
            Percent(noun="a loss"),
            Obj(
                "Gilbert-Elliott two-state loss (bursts).",
                [
                    Field(
                        "model",
                        Enum(("gilbert-elliott",)),
                        "The loss model.",
                        required=True,
                        attr=None,
                    ),
                    Field("p", Percent(), "Chance per packet to go good -> bad.", required=True),
                    Field("r", Percent(), "Chance per packet to go bad -> good.", required=True),
                    Field("good_loss", Percent(), "Loss rate in the good state."),
                    Field("bad_loss", Percent(), "Loss rate in the bad state."),
                ],
                model=GilbertElliott,
                ref="gilbert_elliott",
            ),
        ),
        "Random loss as a percentage (0.5%), or a Gilbert-Elliott mapping for bursty loss.",
    ),
    Field(
        "queue",
        Either(
            Int(1, 1_000_000, noun="a queue limit in packets"),
            Duration(MAX_DELAY_S, lo_open=True, noun="a queue time limit"),
        ),
        "Queue limit: a number of packets, or a duration (packets waiting longer are dropped).",
        attr="queue_packets",
    ),
    Field("reorder", Bool(), "Let jitter reorder packets (otherwise order is kept)."),
    Field(
        "radio",
        Nullable(RADIO_VALUE),
        "5G NR air interface of this direction (userspace backend): a named radio "
        f"({', '.join(RADIO_PROFILES)}), or a mapping that changes one; null: a plain link.",
    ),
)

PROFILE = Obj(
    "One direction of a link. Keys left out keep the value they merge over "
    "(the links.air/backhaul default, or no shaping at all).",
    PROFILE_FIELDS,
    model=LinkProfile,
    fill_defaults=False,
    ref="profile",
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


def _direction_pair(doc: str, radio: bool = False) -> Obj:
    fields = [
        Field("uplink", PROFILE, "Towards the core (vehicle -> gNB -> core)."),
        Field("downlink", PROFILE, "Towards the vehicle."),
    ]
    if radio:
        fields.append(
            Field(
                "radio",
                Nullable(RADIO_VALUE),
                "5G NR air interface of both directions of every air link (userspace backend):"
                f" a named radio ({', '.join(RADIO_PROFILES)}) or a mapping that changes one."
                " A direction's own `radio` mapping changes this one.",
            )
        )
        fields.append(
            Field(
                "rrc",
                Nullable(RRC),
                "RRC states of every air link's UE (inactivity timer, resume and setup"
                " delays); null or left out: always connected.",
            )
        )
    return Obj(doc, fields, fill_defaults=False)


OVERRIDE = Obj(
    "Per-link profile fields that merge over the air/backhaul defaults.",
    [
        Field("link", LINK_NAME, "The link to change, e.g. av2-gnb1.", required=True),
        Field("uplink", PROFILE, "Fields of the uplink direction."),
        Field("downlink", PROFILE, "Fields of the downlink direction."),
        Field(
            "rrc",
            Nullable(RRC),
            "RRC states of this air link's UE (both directions); null: always connected.",
        ),
    ],
    require_any=("uplink", "downlink", "rrc"),
)

LINKS = Obj(
    "How links behave: the backend that emulates them and per-direction profiles.",
    [
        Field(
            "backend",
            Enum(("auto", "tc", "userspace")),
            "auto: tc if the kernel has sch_netem, else the userspace relay.",
            default="auto",
        ),
        Field(
            "air",
            _direction_pair("Default of every vehicle-gNB link (named like av1-gnb1).", True),
            "Default of every vehicle-gNB link (named like av1-gnb1).",
        ),
        Field(
            "backhaul",
            _direction_pair("Default of every gNB-core link (named like gnb1-core1)."),
            "Default of every gNB-core link (named like gnb1-core1), and of every N3 link"
            " where `n3` is not written.",
        ),
        Field(
            "n3",
            _direction_pair("Default of every gNB-UPF link, N3 (named like gnb1-upf1)."),
            "Default of every gNB-UPF link, N3 (named like gnb1-upf1): carries GTP-U.",
        ),
        Field(
            "n6",
            _direction_pair("Default of every link to an edge server, N6 (like upf1-edge1)."),
            "Default of every link to an edge server, N6 (named like upf1-edge1, or gnb1-edge1"
            " for an edge at the cell).",
        ),
        Field(
            "overrides",
            ListOf(OVERRIDE),
            "Per-link changes, merged over the defaults.",
        ),
    ],
)

EDGE = Obj(
    "The edge server behind a UPF, and where it sits.",
    [
        Field("name", node_name("an edge server name"), "Name of the edge node.", required=True),
        Field(
            "placement",
            Enum(("core", "cell")),
            "core: behind the UPF, over N3 and N6 (the paper's lab, where the core host served"
            " as edge); cell: at the cell site, reached from the gNB over its own N6 link"
            " without crossing N3 (local breakout, an RSU).",
            default="core",
        ),
    ],
)

SITE = Obj(
    "Where a cell's antenna stands, in the world frame of the workload's poses (metres).",
    [
        Field("x", Float(noun="a position in metres"), "East, metres.", required=True),
        Field("y", Float(noun="a position in metres"), "North, metres.", required=True),
        Field(
            "height",
            Float(0.0, 300.0, lo_open=True, noun="an antenna height in metres"),
            "Antenna height above ground, metres (TR 38.901: UMa 25, UMi 10).",
            attr="height_m",
        ),
        Field(
            "tx_power",
            Float(-10.0, 70.0, noun="a transmit power in dBm"),
            "Total transmit power over the channel, dBm (a macro cell: 46).",
            attr="tx_power_dbm",
        ),
        Field(
            "carrier",
            Float(*CARRIER_RANGE_GHZ, noun="a carrier frequency in GHz"),
            "Carrier frequency, GHz (FR1; band n78: 3.5). Cells on one carrier interfere.",
            attr="carrier_ghz",
        ),
    ],
    model=model.CellSite,
)

CELL = Obj(
    "A cell: a gNB and what is behind it: a core (`core`: one node that routes and hosts the"
    " edge server, plain IP), or the 5G core path (`upf` and `edge`: GTP-U over N3 to the"
    " UPF, N6 to the edge server).",
    [
        Field("gnb", node_name("a gNB name"), "Name of the gNB node.", required=True),
        Field(
            "core",
            node_name("a core name"),
            "Name of the core/edge-server node (the first form; or `upf` and `edge`).",
        ),
        Field(
            "upf",
            node_name("a UPF name"),
            "Name of the UPF node: the gNB's N3 peer. Several cells may share one.",
        ),
        Field(
            "edge",
            Either(node_name("an edge server name"), EDGE),
            "The edge server: its name (behind the UPF), or {name, placement}.",
            attr=None,
        ),
        Field("core_cpu", CPU, "CPU cores for the edge server (null: unlimited)."),
        Field(
            "scheduler",
            Enum(SCHEDULERS),
            "How the gNB shares the NR slots of its air links' radios among its UEs: rr (equal"
            " shares of each slot's PRBs) or pf (proportional fair in time).",
        ),
        Field(
            "radio",
            Either(Enum(tuple(RADIO_PROFILES)), CELL_RADIO),
            "The cell-level part of its air links' radios (TDD pattern, numerology, PRBs,"
            " scheduler): a named radio, or a mapping of those fields.",
            attr=None,
        ),
        Field(
            "site",
            Either(Enum(("auto",)), SITE),
            "Where the cell stands: {x, y, height, tx_power, carrier}, or auto (spread along"
            " the route). With `channel:`, the vehicles' positions against the sites set their"
            " radio.",
            attr=None,
        ),
    ],
    model=model.Cell,
)

VEHICLE = Obj(
    "A vehicle (UE) attached to one gNB.",
    [
        Field("name", node_name("a vehicle name"), "Name of the vehicle node.", required=True),
        Field("gnb", node_name("a gNB name"), "The gNB it attaches to.", required=True),
        Field("cpu", CPU, "CPU cores for this vehicle's processes (null: unlimited)."),
        Field(
            "workload",
            WORKLOAD_KIND,
            "edgeloc: this vehicle runs EdgeLoc's nodes; none: a background UE that only"
            " carries `traffic:` and `apps:` (e.g. to load its cell).",
        ),
    ],
    model=model.Vehicle,
)

QFI = Int(0, 63, "a QoS flow identifier (QFI)")
QOS_RULE = Obj(
    "A packet filter: packets matching every criterion given go in QoS flow `qfi`.",
    [
        Field("qfi", QFI, "The QoS flow; one of `flows`.", required=True),
        Field("dscp", Int(0, 63, "a DSCP value"), "The packet's DSCP."),
        Field(
            "ports",
            ListOf(Int(1, 65535, "a port number"), min_items=1, unique=True),
            "TCP/UDP ports; a packet to or from one of them matches.",
        ),
        Field(
            "dds",
            Enum(("discovery", "data")),
            "DDS traffic of the run's ROS domain by its RTPS ports: discovery (SPDP/SEDP) or"
            " data (topics, such as EdgeLoc's requests and answers).",
        ),
    ],
    require_any=("dscp", "ports", "dds"),
)
QOS = Obj(
    "The QoS flows of every PDU session on N3: each G-PDU's PDU Session Container carries the"
    " QFI of the flow its packet is in. Default: flows 1 and 2, DDS discovery in 2, the rest"
    " (EdgeLoc's requests and answers) in 1.",
    [
        Field(
            "flows",
            ListOf(QFI, min_items=1, unique=True),
            "The QFIs each PDU session has.",
            default=model.Qos.flows,
        ),
        Field(
            "default_qfi",
            QFI,
            "The flow of a packet no rule matches; one of `flows`.",
            default=model.Qos.default_qfi,
        ),
        Field(
            "rules",
            ListOf(QOS_RULE),
            "Packet filters, first match wins (default: DDS discovery in QFI 2, where the"
            " flows have it).",
        ),
    ],
)

HOST = Obj(
    "A machine that holds part of the topology: its underlay address and its nodes.",
    [
        Field(
            "address",
            Str("an IPv4 address like 192.168.1.10", IPV4_ADDRESS_PATTERN),
            "This host's underlay address: where the VXLAN tunnels (UDP 4789) of its links to"
            " nodes on other hosts end. The other hosts must reach it.",
            required=True,
        ),
        Field(
            "nodes",
            ListOf(node_name("a node name"), unique=True),
            "The nodes on this host (nodes no host lists are on the first host).",
        ),
    ],
)

TOPOLOGY = Obj(
    "Nodes: cells (gNB + core, or gNB + UPF + edge) and vehicles. Names are unique across all"
    " of them, but cells may share a UPF and an edge.",
    [
        Field(
            "address_pool",
            Nullable(PrivateNetwork()),
            "Private IPv4 network for link addresses (one /30 per link); null: pick a free /16.",
            default=None,
        ),
        Field(
            "ue_pool",
            PrivateNetwork(),
            "Private IPv4 network the vehicles of cells with a UPF get their addresses from"
            " (default 10.45.0.0/16, Open5GS's). It must not overlap `address_pool`.",
        ),
        Field(
            "ue_mtu",
            Int(
                model.MIN_UE_MTU,
                model.MAX_UE_MTU,
                f"an MTU in bytes that leaves room for GTP-U's {model.N3_OVERHEAD} bytes on a"
                f" {model.N3_MTU}-byte N3",
            ),
            "MTU of the air interface of vehicles behind a UPF: nothing they send is"
            " fragmented on N3.",
            default=model.MAX_UE_MTU,
        ),
        Field("qos", QOS, "QoS flows on N3 (cells with a UPF)."),
        Field("cells", ListOf(CELL, min_items=1), "At least one cell.", required=True),
        Field("vehicles", ListOf(VEHICLE, min_items=1), "At least one vehicle.", required=True),
        Field(
            "hosts",
            MapOf(
                Str(
                    "a host name: a lowercase letter then up to 31 lowercase letters, digits"
                    " or dashes",
                    HOST_NAME_PATTERN,
                ),
                HOST,
            ),
            "The machines the topology spans (default: every node on this one). A link whose"
            " ends are on two hosts is carried by a VXLAN tunnel between their addresses;"
            " `testbed up FILE --host NAME --run-id ID` builds one host's part. Needs"
            " `address_pool`, so that every host gives the links the same addresses.",
        ),
    ],
)

_DIRECTION_BOTH = Field(
    "direction",
    Enum(("uplink", "downlink", "both")),
    "Which direction(s) of the link to change.",
    default="both",
)

SET_EVENT = Obj(
    "Change profile fields of a link direction (or both) in place.",
    [
        AT,
        Field("set", LINK_NAME, "The link to change.", required=True),
        _DIRECTION_BOTH,
        *PROFILE_FIELDS,
    ],
    require_any=tuple(f.key for f in PROFILE_FIELDS),
)
SHAPE_EVENT = Obj(
    "Wondershaper-style cap on a node's uplink (egress) and/or downlink (ingress).",
    [
        AT,
        Field("shape", node_name("a node name"), "The node to cap.", required=True),
        Field("uplink", Rate(unlimited=False), "Cap on what the node sends."),
        Field("downlink", Rate(unlimited=False), "Cap on what the node receives."),
    ],
    require_any=("uplink", "downlink"),
)
CLEAR_EVENT = Obj(
    "Remove what `shape` put on a node, and only that.",
    [AT, Field("clear", node_name("a node name"), "The node to uncap.", required=True)],
)
OUTAGE_EVENT = Obj(
    "Drop everything on a link (both directions) for a while.",
    [
        AT,
        Field("outage", LINK_NAME, "The link to cut.", required=True),
        Field(
            "for",
            Duration(MAX_DURATION_S, lo_open=True, noun="an outage length"),
            "How long the outage lasts.",
            required=True,
        ),
    ],
)
TRACE_EVENT = Obj(
    "Replay a bandwidth trace on one direction of a link.",
    [
        AT,
        Field("trace", LINK_NAME, "The link to drive.", required=True),
        Field("direction", Enum(("uplink", "downlink")), "Which direction.", required=True),
        Field(
            "file",
            Str("a path to a trace file, relative to the scenario file"),
            "Trace file, relative to the scenario file.",
            required=True,
        ),
        Field(
            "format",
            Enum(("mahimahi", "csv")),
            "mahimahi: one ms timestamp per 1500-byte delivery opportunity per line; "
            "csv: time_s,mbit rows. Default: csv for a .csv file, else mahimahi.",
        ),
        Field("loop", Bool(), "Start over at the end of the trace.", default=False),
    ],
)
EVENT = Tagged(
    "a timeline event",
    {
        "set": SET_EVENT,
        "shape": SHAPE_EVENT,
        "clear": CLEAR_EVENT,
        "outage": OUTAGE_EVENT,
        "trace": TRACE_EVENT,
    },
)

LEARNER = Obj(
    "Split-point learner (sliding-window UCB1-normal) and its KL change detector.",
    [
        Field("window", Int(2, noun="a window of plays"), "W: plays kept by the sliding window."),
        Field("cost", Enum(("latency", "error")), "What the learner minimizes."),
        Field(
            "fixed_split",
            Nullable(Str("a split name")),
            "Play only this split (a baseline); null: learn.",
        ),
        Field("detector", Bool(), "Reset the learner when the cost distribution changes."),
        Field(
            "kl_threshold",
            Float(0.0, lo_open=True, noun="a KL divergence"),
            "KL divergence that counts as a change.",
        ),
        Field(
            "consecutive",
            Int(1, noun="a count"),
            "C: consecutive exceedances that trigger a reset.",
        ),
        Field(
            "detector_window",
            Int(2, noun="a number of samples"),
            "Samples per Gaussian fit of the detector.",
        ),
    ],
    model=model.Learner,
)
FUSION = Obj(
    "Latency-aware fusion weight 1 / (1 + exp(-k_s (dt - dt0))).",
    [
        Field("k_s", Float(0.0, lo_open=True, noun="a slope (1/s)"), "Slope k_s, in 1/s."),
        Field(
            "dt0",
            Duration(MAX_DELAY_S, lo=-MAX_DELAY_S, noun="a latency offset", signed=True),
            "Midpoint latency dt0 of the sigmoid; may be negative (the weight u is then below"
            " 1/2 even for an instant answer).",
            attr="dt0_s",
        ),
        Field(
            "robust",
            Nullable(Float(0.0, lo_open=True, noun="a multiple of the median innovation")),
            "BEYOND THE PAPER: scale each answer's weight by 1 / (1 + (r / (c s))^2), r its"
            " distance from the fused pose, s the median of the last 50; null: the paper's"
            " latency-only weight.",
            attr="robust_c",
        ),
        Field(
            "robust_centre",
            Nullable(Duration(60.0, lo_open=True, noun="a window")),
            "BEYOND THE PAPER, with robust and method paper: measure r from the answers' mean"
            " innovation over this window (in the vehicle's frame) instead of from the fused"
            " pose, so the lag a drifting VO builds up is corrected rather than shrunk as an"
            " outlier; null: from the fused pose.",
            attr="robust_centre_s",
        ),
        Field(
            "method",
            Enum(("paper", "ekf")),
            "paper: the latency weight above; ekf (BEYOND THE PAPER): a delayed-measurement EKF"
            " over pose, VO scale and yaw-rate bias that corrects its state at each answer's"
            " capture time and replays the VO since, with the kalman block's r_pos/r_yaw as the"
            " DNN's noise and robust as above (k_s and dt0 unused).",
        ),
        Field(
            "correlation",
            Nullable(Duration(10.0, lo_open=True, noun="a correlation time")),
            "ekf only (BEYOND THE PAPER): the DNN's errors are correlated over this time, so an"
            " answer soon after the previous one counts for less (its R times (1 + rho) /"
            " (1 - rho), rho = exp(-gap / correlation)); null: every answer independent.",
            attr="correlation_s",
        ),
        Field(
            "confidence",
            Bool(),
            "BEYOND THE PAPER, method paper only: scale each answer's weight by the DNN's own"
            " doubt, the entropy H of its place classifier, as min(1, exp(-per_nat (H -"
            " H_ref))), calibrated on held-out drives (confidence.json beside the weights:"
            " `python -m nodes.edgeloc.train --calibrate --out DIR` writes it).",
        ),
    ],
    model=model.Fusion,
)
_VARIANCE = Float(0.0, noun="a variance")
_POSITIVE_VARIANCE = Float(0.0, lo_open=True, noun="a variance")
KALMAN = Obj(
    "Kalman-filter baseline noise (per-axis variances, m^2 and rad^2).",
    [
        Field("q_pos", _VARIANCE, "Process noise of x and y (m^2)."),
        Field("q_yaw", _VARIANCE, "Process noise of the heading (rad^2)."),
        Field("r_pos", _POSITIVE_VARIANCE, "Measurement noise of x and y (m^2)."),
        Field("r_yaw", _POSITIVE_VARIANCE, "Measurement noise of the heading (rad^2)."),
    ],
    model=model.Kalman,
)
WORKLOAD = Obj(
    "The EdgeLoc workload: rates, data, model and algorithm knobs.",
    [
        Field(
            "kind",
            WORKLOAD_KIND,
            "The built-in workload: edgeloc, or none (a scenario of apps and traffic only).",
        ),
        Field(
            "rate_hz",
            Float(0.0, 1000.0, lo_open=True, noun="a rate in Hz"),
            "Real-time thread rate (VO and fused pose).",
        ),
        Field(
            "dataset",
            Str("'synthetic' or a path to a folder of recorded data"),
            "'synthetic', or a folder of recorded data relative to the scenario file.",
        ),
        Field("codec", Enum(("fp16-zlib", "int8-zlib")), "How intermediate features are sent."),
        Field(
            "weights",
            Nullable(Str("a path to a weights file")),
            "Model weights relative to the scenario file; null: the repo's trained model.",
        ),
        Field(
            "splits",
            Nullable(ListOf(Str("a split name"), min_items=1, unique=True)),
            "Split points the learner may play; null: every split point of the model.",
        ),
        Field(
            "corruption",
            Percent(noun="a corruption rate"),
            "Experiment knob: share of corrupted requests (off by default; reports name it).",
        ),
        Field("learner", LEARNER, "Split-point learner."),
        Field("fusion", FUSION, "Latency-aware fusion."),
        Field("kalman", KALMAN, "Kalman-filter baseline."),
    ],
    model=model.Workload,
)
TOPIC_NAME = Str("a ROS 2 topic name like /chatter", r"^/[A-Za-z0-9_/~{}]*[A-Za-z0-9_}]$")
_RECORD_NODE = Field(
    "node", node_name("a node name"), "The namespace the recorder runs in.", required=True
)
TOPIC_RECORD = Tagged(
    "a topic to record",
    {
        "topic": Obj(
            "One topic by name.",
            [Field("topic", TOPIC_NAME, "The topic.", required=True), _RECORD_NODE],
            model=model.TopicRecord,
        ),
        "regex": Obj(
            "Every topic whose name a regular expression matches (re.search).",
            [
                Field("regex", Str("a regular expression"), "The pattern.", required=True),
                _RECORD_NODE,
            ],
            model=model.TopicRecord,
        ),
    },
)

RECORD = Obj(
    "What the run records into run.mcap.",
    [
        Field("enabled", Bool(), "Record the run."),
        Field("compression", Enum(("zstd", "lz4", "none")), "MCAP chunk compression."),
        Field("images", Bool(), "Also record camera frames (large)."),
        Field(
            "pcap",
            Either(Enum(("all",)), ListOf(LINK_NAME, unique=True)),
            "Links whose packets are captured to runs/<id>/pcap/<link>.pcapng (both directions"
            " as they leave the link, after its impairments; what they dropped is counted in"
            " the file's interface statistics), or all; userspace backend only.",
        ),
        Field(
            "topics",
            ListOf(TOPIC_RECORD),
            "ROS 2 topics that apps publish, recorded into run.mcap with their full schemas by"
            " a recorder in the named node's namespace (so no recording traffic crosses an"
            " emulated link).",
        ),
    ],
    model=model.Record,
)
REPORT = Obj(
    "What the run reports at the end.",
    [
        Field("enabled", Bool(), "Write a report."),
        Field(
            "formats",
            ListOf(Enum(("html", "md", "json")), min_items=1, unique=True),
            "Report formats.",
        ),
        Field("plots", Bool(), "Draw plots."),
        Field(
            "link_test",
            Either(Bool(), ListOf(LINK_NAME, min_items=1, unique=True)),
            "Measure each link briefly before the workload (true), no link (false), or only"
            " the links listed, e.g. [av1-gnb1] for the air link alone (each wired link costs"
            " ~8 s, each radio link ~20 s).",
        ),
        Field(
            "compare",
            Bool(),
            "Replay every fixed split and the oracle on the run's drive under its measured"
            " latencies, beside the learned run (false: leave them out of the report, saving"
            " ~10 s of CPU after a 20-s run; `testbed report RUN --compare` adds them later).",
        ),
    ],
    model=model.Report,
)

# ---- apps and traffic ------------------------------------------------------------------------

PROGRAM_NAME = Str(
    "a name: a lowercase letter, then up to 31 lowercase letters, digits, '_' or '-'",
    r"^[a-z][a-z0-9_-]{0,31}$",
    "it names the log file and the report's row",
)
START = Field(
    "start",
    Duration(MAX_DURATION_S, noun="a time"),
    "When it starts, from the start of the timeline.",
    attr="start_s",
)
STOP = Field(
    "stop",
    Nullable(Duration(MAX_DURATION_S, lo_open=True, noun="a time")),
    "When it is stopped (SIGTERM), from the start of the timeline; null: at the end of the run.",
    attr="stop_s",
)
READY_TIMEOUT = Field(
    "timeout",
    Duration(3600.0, lo_open=True, noun="a timeout"),
    "How long to wait for it; then the run fails naming the app.",
    required=True,
    attr="timeout_s",
)
READY = Tagged(
    "a readiness check",
    {
        "log": Obj(
            "A line of the app's log (stdout and stderr) matches a regular expression.",
            [
                Field("log", Str("a regular expression"), "The pattern.", required=True),
                READY_TIMEOUT,
            ],
        ),
        "topic": Obj(
            "A message arrives on a ROS 2 topic (read in the app's namespace).",
            [Field("topic", TOPIC_NAME, "The topic.", required=True), READY_TIMEOUT],
        ),
        "port": Obj(
            "A TCP port listens, or a UDP port is bound, in the app's namespace.",
            [
                Field("port", Int(1, 65535, "a port number"), "The port.", required=True),
                Field("protocol", Enum(("tcp", "udp")), "tcp or udp.", default="tcp"),
                READY_TIMEOUT,
            ],
        ),
    },
)
APP = Obj(
    "A process you bring, run in one namespace of the topology.",
    [
        Field("name", PROGRAM_NAME, "Its name (log file logs/app.<name>.log).", required=True),
        Field("node", node_name("a node name"), "The namespace it runs in.", required=True),
        Field(
            "command",
            Argv(),
            "argv as a list, never a shell string: [python, apps/talker.py, --rate, 10]."
            " `python` is the testbed's own interpreter; an argument naming an existing file"
            " or folder relative to the scenario file is made absolute.",
            required=True,
        ),
        Field(
            "env",
            MapOf(
                Str("an environment variable name", r"^[A-Za-z_][A-Za-z0-9_]*$"),
                Word("a value"),
            ),
            "Extra environment variables (over the run's ROS environment with ros: true).",
        ),
        Field(
            "cwd",
            Str("a folder, relative to the scenario file"),
            "Working folder relative to the scenario file (default: the scenario's folder).",
        ),
        Field(
            "ros",
            Bool(),
            "Give it the run's ROS environment: domain id, the Fast DDS profile with the"
            " namespace's unicast peers, socket buffers.",
            default=False,
        ),
        Field("ready", READY, "When it counts as started (default: once it is running)."),
        START,
        STOP,
        Field("cpu", CPU, "CPU cores it may use (cgroup quota; null: unlimited)."),
        Field(
            "required",
            Bool(),
            "Its non-zero exit fails the run with its last log lines (false: recorded only).",
            default=True,
        ),
    ],
)
TRAFFIC = Obj(
    "A cross-traffic flow between two nodes (our generator, `nodes.traffic`).",
    [
        Field("name", PROGRAM_NAME, "Its name (topic /traffic/<name>).", required=True),
        Field(
            "kind",
            Enum(("tcp", "udp", "onoff")),
            "tcp: bulk TCP; udp: constant bit rate; onoff: UDP at `rate` for `on`, then"
            " silent for `off` (video-like).",
            required=True,
        ),
        Field("from", node_name("a node name"), "The sender's node.", required=True, attr="src"),
        Field("to", node_name("a node name"), "The receiver's node.", required=True, attr="dst"),
        Field(
            "rate",
            Rate(unlimited=True),
            "Sending rate (udp and onoff: required; tcp: a cap, default unlimited).",
            attr="rate_bps",
        ),
        Field(
            "size",
            Int(16, 65000, "a datagram size in bytes"),
            "UDP payload bytes per datagram (tcp: bytes per write).",
        ),
        START,
        STOP,
        Field(
            "on",
            Duration(3600.0, lo_open=True, noun="an on period"),
            "onoff: how long each burst lasts.",
            attr="on_s",
        ),
        Field(
            "off",
            Duration(3600.0, lo_open=True, noun="an off period"),
            "onoff: how long each pause lasts.",
            attr="off_s",
        ),
        Field(
            "port",
            Int(1024, 65535, "a port number"),
            "The receiver's port (default: one per flow from 5300 up).",
        ),
    ],
    model=model.Traffic,
)

HANDOVER = Obj(
    "Handover between cells (TS 38.331 event A3 on L3-filtered RSRP): a vehicle leaves its"
    " serving cell for a neighbour that stays `offset` + `hysteresis` stronger for `ttt`; its"
    " user plane then stops for `interruption`, and its routes, its gNB and its N3 tunnel"
    " switch to the target. Needs two or more cells with sites, behind one UPF.",
    [
        Field(
            "offset",
            Float(-15.0, 15.0, noun="an offset in dB (0.5 dB steps)"),
            "a3-Offset, dB (TS 38.331: -15..15 in 0.5 dB steps).",
            attr="offset_db",
        ),
        Field(
            "hysteresis",
            Float(0.0, 15.0, noun="a hysteresis in dB (0.5 dB steps)"),
            "Hysteresis, dB (0..15 in 0.5 dB steps).",
            attr="hysteresis_db",
        ),
        Field(
            "ttt",
            Duration(5.12, noun="a time-to-trigger"),
            "Time-to-trigger: one of TS 38.331's 0, 40, 64, 80, 100, 128, 160, 256, 320, 480,"
            " 512, 640, 1024, 1280, 2560, 5120 ms.",
            attr="ttt_s",
        ),
        Field(
            "filter",
            Int(0, 19, "a filter coefficient"),
            "L3 filter coefficient k (TS 38.331 FilterCoefficient; 4 is the spec's default,"
            " 0 no filter).",
            attr="filter_k",
        ),
        Field(
            "interruption",
            Duration(10.0, noun="an interruption time"),
            "How long the user plane stops at a handover (default 40 ms).",
            attr="interruption_s",
        ),
        Field(
            "lossless",
            Bool(),
            "true: what is in flight is forwarded to the target and delivered in order after"
            " the interruption (PDCP); false: it is lost.",
        ),
        Field(
            "edge",
            Enum(("stay", "follow")),
            "stay: the vehicle keeps asking the edge server it started with (through the"
            " target's N3 and the UPF); follow: it asks the serving cell's edge server.",
        ),
    ],
    model=model.HandoverSpec,
)

CHANNEL = Obj(
    "The radio channel from each vehicle's route: TR 38.901 path loss, LOS and shadowing from"
    " its distance to the cell sites, then SINR -> CQI -> MCS and BLER (TS 38.214) on its air"
    " link, both directions, every `step`. Needs a `site` on every cell and an NR `radio` on"
    " the air links.",
    [
        Field(
            "model",
            Enum(MODELS),
            "TR 38.901 scenario: uma (urban macro) or umi (urban micro, street canyon).",
        ),
        Field(
            "los",
            Enum(LOS_MODES),
            "Line of sight: auto (drawn from TR 38.901's LOS probability, correlated along the"
            " route), los or nlos everywhere.",
        ),
        Field(
            "step",
            Duration(10.0, 0.001, noun="a sampling step"),
            "How often the channel is sampled and link adaptation may change the MCS.",
            attr="step_s",
        ),
        Field("shadowing", Bool(), "Log-normal shadowing (TR 38.901 Table 7.4.1-1), seeded."),
        Field(
            "ue_height",
            Float(*UE_HEIGHT_RANGE_M, noun="a UE height in metres"),
            "The vehicle's antenna height, metres.",
            attr="ue_height_m",
        ),
        Field(
            "ue_power",
            Float(-40.0, 40.0, noun="a transmit power in dBm"),
            "The UE's uplink power, dBm (power class 3: 23).",
            attr="ue_power_dbm",
        ),
        Field(
            "noise_figure",
            Float(0.0, 30.0, noun="a noise figure in dB"),
            "The UE receiver's noise figure, dB.",
            attr="noise_figure_db",
        ),
        Field(
            "gnb_noise_figure",
            Float(0.0, 30.0, noun="a noise figure in dB"),
            "The gNB receiver's noise figure, dB.",
            attr="gnb_noise_figure_db",
        ),
        Field(
            "trace",
            Str("a path to a radio trace CSV, relative to the scenario file"),
            "A recorded radio instead of the model: CSV rows time_s,ue,rsrp_dbm,sinr_db,mcs"
            " (a drive test's export); each vehicle plays its own rows.",
            attr=None,
        ),
        Field("handover", HANDOVER, "Handovers between the cells along the route (event A3)."),
    ],
    model=model.ChannelSpec,
)

SCENARIO = Obj(
    "An edgeloc-testbed scenario (schema v1): topology, links, timeline, workload.",
    [
        Field(
            "version",
            Const(1, "1 (this testbed reads schema v1)"),
            "Schema version.",
            default=1,
        ),
        Field(
            "name",
            Str(
                "a scenario name: lowercase letters, digits, '_' or '-', up to 32 characters",
                SCENARIO_NAME_PATTERN,
                "the name is used in run folders and reports",
            ),
            "Scenario name (used in run folders and reports).",
            required=True,
        ),
        Field("seed", Int(0, 2**32 - 1, noun="a seed"), "Seed of every random choice.", default=0),
        Field(
            "duration",
            Duration(MAX_DURATION_S, lo_open=True, noun="a run length"),
            "How long the run lasts.",
            required=True,
        ),
        Field("topology", TOPOLOGY, "Nodes of the emulated network.", required=True),
        Field("links", LINKS, "Link behaviour."),
        Field("timeline", ListOf(EVENT), "Link and shaping changes during the run."),
        Field("channel", CHANNEL, "Radio from the vehicles' routes and the cells' sites."),
        Field(
            "workload",
            Either(WORKLOAD_KIND, WORKLOAD),
            "The built-in workload: edgeloc (default), none (apps and traffic only), or a"
            " mapping of EdgeLoc's settings.",
        ),
        Field("apps", ListOf(APP), "Processes you bring, each in a namespace of the topology."),
        Field("traffic", ListOf(TRAFFIC), "Cross-traffic flows between nodes."),
        Field("record", RECORD, "Recording."),
        Field("report", REPORT, "Report."),
    ],
    extensions=True,
)


def json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of scenario files, derived from the declarations above."""
    defs: dict[str, Any] = {}
    body = SCENARIO.schema(defs)
    return {
        "$schema": JSON_SCHEMA_DIALECT,
        "$id": "https://edgeloc-testbed.invalid/scenario.schema.json",
        "title": "edgeloc-testbed scenario, schema v1",
        **body,
        "$defs": dict(sorted(defs.items())),
    }
