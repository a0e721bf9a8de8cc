"""Real packets across a built topology: a UDP echo from each vehicle to its core server.

Sockets belong to the network namespace they were created in, so the probe opens each socket
inside the right namespace (`Node.socket`) and drives both ends from this thread: no helper
processes, no shelling out. `testbed run` uses it before any workload starts; the tests use it
as the ground truth that routes and forwarding work.
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from testbed.topology import Net, Node

ECHO_PORT = 7  # the classic echo port; inside our own namespaces it is always free


@dataclass(frozen=True)
class EchoResult:
    src: str
    dst: str
    dst_addr: str
    sent: int
    received: int
    rtt_ms_median: float | None
    rtt_ms_max: float | None

    @property
    def ok(self) -> bool:
        return self.received == self.sent

    def to_dict(self) -> dict[str, object]:
        return {**asdict(self), "ok": self.ok}


def echo_rtts(
    src: Node,
    dst: Node,
    dst_addr: str,
    *,
    count: int,
    port: int = ECHO_PORT,
    timeout_s: float = 1.0,
) -> list[float]:
    """RTTs (ms) of `count` datagrams echoed one at a time from `src` to `dst_addr` (on
    `dst`); a datagram lost or late beyond `timeout_s` is left out."""
    server = dst.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client = src.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rtts: list[float] = []
    try:
        server.bind((dst_addr, port))
        server.settimeout(timeout_s)
        client.settimeout(timeout_s)
        for seq in range(count):
            payload = seq.to_bytes(4, "big") + os.urandom(28)
            t0 = time.perf_counter()
            client.sendto(payload, (dst_addr, port))
            try:
                data, peer = server.recvfrom(2048)
                server.sendto(data, peer)
                reply, _ = client.recvfrom(2048)
            except TimeoutError:
                continue
            if reply == payload:
                rtts.append((time.perf_counter() - t0) * 1000)
    finally:
        server.close()
        client.close()
    return rtts


def udp_echo(
    src: Node, dst: Node, dst_addr: str, *, count: int = 5, timeout_s: float = 1.0
) -> EchoResult:
    """Echo `count` datagrams from `src` to `dst_addr` (an address of `dst`) and summarise."""
    rtts = sorted(echo_rtts(src, dst, dst_addr, count=count, timeout_s=timeout_s))
    return EchoResult(
        src=src.name,
        dst=dst.name,
        dst_addr=dst_addr,
        sent=count,
        received=len(rtts),
        rtt_ms_median=rtts[len(rtts) // 2] if rtts else None,
        rtt_ms_max=rtts[-1] if rtts else None,
    )


def vehicles_reach_cores(net: Net, count: int = 5) -> list[EchoResult]:
    """Echo from every vehicle to the edge server of its cell, through its gNB (and, behind a
    UPF, the GTP-U tunnel on N3)."""
    results = []
    for vehicle in net.scenario.topology.vehicles:
        cell = net.scenario.topology.cell_of_gnb(vehicle.gnb)
        server = net[cell.server]
        addr = str(net.server_address(cell))
        results.append(udp_echo(net[vehicle.name], server, addr, count=count))
    return results
