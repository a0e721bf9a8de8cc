"""The `record` and `report` sections of schema v1: what the run keeps in run.mcap (and its
packet captures), and what it reports at the end.
"""

from __future__ import annotations

from testbed.scenario import model
from testbed.scenario.kinds import Bool, Either, Enum, Field, ListOf, Obj, Str, Tagged
from testbed.scenario.schema_v1.shared import LINK_NAME, TOPIC_NAME, node_name

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
