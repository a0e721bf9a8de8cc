"""Which cell serves this vehicle now, as its own kernel says: the interface of its default
route (an air link's interface is named after its gNB). With `channel.handover`, a handover
moves that route (`testbed.topology.Net.hand_over`), so a vehicle's nodes learn their serving
cell the way a UE knows it, locally, without a message from the network; with `edge: follow`
the inference node then asks that cell's edge server.

Pure parsing plus one read of `/proc/net/route`, which is per network namespace (the reading
process's): no ROS import.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

ROUTE_TABLE = Path("/proc/net/route")


def default_interface(table: str) -> str | None:
    """The interface of the first default route (destination and mask 0) in the text of
    `/proc/net/route`; None without one."""
    for line in table.splitlines()[1:]:
        fields = line.split()
        if len(fields) >= 8 and fields[1] == "00000000" and fields[7] == "00000000":
            return fields[0]
    return None


def parse_edges(text: str) -> dict[str, str]:
    """`gnb1=edge1,gnb2=edge2` (the supervisor's `--edges`) as {gnb: edge server}."""
    out: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        gnb, sep, edge = item.partition("=")
        if not sep or not gnb or not edge:
            raise ValueError(f"--edges wants gnb=edge pairs separated by commas, got {item!r}")
        out[gnb] = edge
    return out


class ServingEdge:
    """The edge server a vehicle should ask now: its serving cell's in `edges`, else
    `default` (no handovers, or a route it does not know)."""

    def __init__(self, default: str, edges: Mapping[str, str], table: Path = ROUTE_TABLE) -> None:
        self.default = default
        self.edges = dict(edges)
        self.table = table

    def now(self) -> str:
        if not self.edges:
            return self.default
        try:
            gnb = default_interface(self.table.read_text())
        except OSError:
            return self.default
        return self.edges.get(gnb or "", self.default)
