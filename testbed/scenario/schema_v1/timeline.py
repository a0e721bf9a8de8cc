"""The `timeline` section of schema v1: events told apart by their action key (set, shape,
clear, outage, trace), each `at` a time of the run.
"""

from __future__ import annotations

from netem.directions import DIRECTIONS
from testbed.scenario.kinds import Bool, Duration, Enum, Field, Obj, Rate, Str, Tagged
from testbed.scenario.schema_v1.links import PROFILE_FIELDS
from testbed.scenario.schema_v1.shared import LINK_NAME, MAX_DURATION_S, node_name

AT = Field(
    "at",
    Duration(MAX_DURATION_S, noun="a time"),
    "When the event happens, from the start of the run (0 to the scenario's duration).",
    required=True,
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
    require_any=DIRECTIONS,
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
        Field("direction", Enum(DIRECTIONS), "Which direction.", required=True),
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
