"""Cross-traffic on a replayed path: what the scenario's `traffic:` flows take of its hops.

A flow offers its rate on the wire (`wire_bps`); the other UEs of the vehicle's cell take
their share of its radio's PRBs (`cell_share`), and flows that cross a wired hop of the path
take rate off it (`_wired_load`), down to `MIN_LEFT` of it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from testbed.scenario.model import LinkSpec, Traffic

#: The least part of its rate a hop keeps under cross-traffic (a saturated link still moves).
MIN_LEFT = 0.02

#: IPv4 + UDP headers of a traffic datagram; IPv4 + TCP with timestamps of a segment.
UDP_HEADERS, TCP_HEADERS = 28, 52
#: The payload of a full TCP segment on a 1500-byte link (what `wire_bps` scales by).
TCP_SEGMENT = 1448


def wire_bps(flow: Traffic) -> float:
    """What a `traffic:` flow offers a link on average, headers included (inf: bulk TCP)."""
    if flow.rate_bps is None:
        return math.inf
    if flow.kind == "tcp":
        rate = flow.rate_bps * (TCP_SEGMENT + TCP_HEADERS) / TCP_SEGMENT
    else:
        rate = flow.rate_bps * (flow.size + UDP_HEADERS) / flow.size
    if flow.kind == "onoff":
        rate *= flow.on_s / (flow.on_s + flow.off_s)
    return rate


def cell_share(capacity_bps: float, others_bps: Sequence[float]) -> float:
    """The part of a cell's capacity a UE with a burst to send gets beside other UEs offering
    `others_bps`, as the `rr` scheduler shares it (water filling: a UE that wants less than an
    equal share keeps what it wants, the rest is split equally). `pf` shares a saturated
    cell the same way in the long run."""
    users, left = len(others_bps) + 1, capacity_bps
    for want in sorted(others_bps):
        if want >= left / users:
            break
        left -= want
        users -= 1
    return left / users / capacity_bps


def _wired_load(
    wired: list[LinkSpec], ues: set[str], active: list[Traffic], index: int, direction: str
) -> float:
    """Cross-traffic on wired hop `index` of the path `wired` in `direction`: flows between
    one of the cell's UEs `ues` and a node at or beyond that hop's far end."""
    beyond = {link.upper for link in wired[index:]}  # links run gNB side first
    load = 0.0
    for f in active:
        ue, far = (f.src, f.dst) if direction == "uplink" else (f.dst, f.src)
        if ue in ues and far in beyond:
            load += wire_bps(f)
    return load
