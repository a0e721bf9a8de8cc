"""How a run's namespaces are named and tagged, so `clean` can tell ours from anyone else's."""

from __future__ import annotations

import re
from collections.abc import Callable

from testbed.scenario.patterns import NODE_NAME_PATTERN

NODE_NAME_RE = re.compile(NODE_NAME_PATTERN)  # the schema's: one pattern for names
NETNS_PREFIX = "el-"
RUN_NETNS_RE = re.compile(r"^el-([0-9a-f]{6})-")
OWNER_TAG = "edgeloc-testbed state="  # lo's alias in each namespace: which state file owns it
STOP_GRACE_S = 0.5  # SIGTERM, then SIGKILL after this long

Echo = Callable[[str], None]


def netns_name(run_id: str, node: str) -> str:
    return f"{NETNS_PREFIX}{run_id}-{node}"


def transit_netns_name(run_id: str, link: str) -> str:
    """The transit namespace of a link across hosts (`testbed.topology.vxlan`): `vx-` and the
    link's name, which no node name can be (node names have no dash)."""
    return f"{NETNS_PREFIX}{run_id}-vx-{link}"
