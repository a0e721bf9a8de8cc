"""A pcapng file of what one link of the relay delivers (`Capture`), per direction."""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

from netem.directions import DIRECTIONS
from netem.pcap import PcapngWriter
from netem.stages import Pipeline


def _dropped(pipeline: Pipeline) -> int:
    """Packets the direction's stages dropped so far, every reason together."""
    return sum(pipeline.snapshot()["total"]["dropped_packets"].values())


class Capture:
    """A pcapng file of what one link delivers, per direction (one interface each), written as
    packets leave the link: after every impairment, so dropped packets are not in it; their
    number goes into the file's interface statistics when it is closed. With TUN offloads a
    super-packet is written as the wire packets it stands for (the relay's `_deliver`)."""

    def __init__(self, path: str, name: str, pipelines: Mapping[str, Pipeline]) -> None:
        self.path = path
        self.writer = PcapngWriter(path)
        self.pipelines = pipelines  # the link's, whose drops go into the statistics
        self.interfaces = {d: self.writer.interface(f"{name} {d}") for d in DIRECTIONS}
        self._dropped0 = {d: _dropped(pipelines[d]) for d in DIRECTIONS}
        self.packets = {d: 0 for d in DIRECTIONS}

    def write(self, direction: str, packet: bytes) -> None:
        self.writer.packet(
            self.interfaces[direction], packet, time.time_ns(),
            direction="outbound" if direction == "uplink" else "inbound",
        )  # fmt: skip
        self.packets[direction] += 1

    def close(self) -> dict[str, Any]:
        """Finish the file: interface statistics, final name; returns what it holds."""
        now = time.time_ns()
        dropped = {}
        for d in DIRECTIONS:
            dropped[d] = _dropped(self.pipelines[d]) - self._dropped0[d]
            self.writer.statistics(self.interfaces[d], now, self.packets[d], dropped[d])
        self.writer.close()
        return {"path": self.path, "packets": dict(self.packets), "dropped": dropped}
