"""The `topology` section of schema v1: cells (a gNB with a core, or with a UPF and an edge
server, and its site), vehicles, the address pools, the QoS flows on N3 and the hosts a
topology spans.
"""

from __future__ import annotations

from netem.nr.channel import CARRIER_RANGE_GHZ
from netem.nr.policy import SCHEDULERS
from netem.nr.radio import RADIO_PROFILES
from testbed.scenario import model
from testbed.scenario.kinds import (
    Either,
    Enum,
    Field,
    Float,
    Int,
    ListOf,
    MapOf,
    Nullable,
    Obj,
    PrivateNetwork,
    Str,
)
from testbed.scenario.patterns import HOST_NAME_PATTERN, IPV4_ADDRESS_PATTERN
from testbed.scenario.schema_v1.radio import CELL_RADIO
from testbed.scenario.schema_v1.shared import CPU, WORKLOAD_KIND, node_name

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
