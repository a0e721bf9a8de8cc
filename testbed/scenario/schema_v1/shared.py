"""The names, limits and small kinds that more than one section of schema v1 uses: node,
link and topic names (the topology and the sweep check names against their patterns too), the
ceilings of durations and delays, a CPU quota and the workload's kind.
"""

from __future__ import annotations

from testbed.scenario.kinds import Enum, Float, Nullable, Str
from testbed.scenario.patterns import LINK_NAME_PATTERN, NODE_NAME_PATTERN

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

CPU = Nullable(Float(0.0, 1024.0, lo_open=True, noun="a number of CPU cores"))
WORKLOAD_KIND = Enum(("edgeloc", "none"))
TOPIC_NAME = Str("a ROS 2 topic name like /chatter", r"^/[A-Za-z0-9_/~{}]*[A-Za-z0-9_}]$")
