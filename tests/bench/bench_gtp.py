"""Benchmark of the N3 tunnel (issue #17): GTP-U throughput and added delay on this machine.

    sudo .venv/bin/python tests/bench/bench_gtp.py [--seconds 4]

Four namespaces (`elb-<hex>-ue|gnb|upf|edge`) joined by plain veth pairs (air, N3, N6), so the
only userspace hops are the two GTP-U endpoints (`netem.gtpu.endpoint`, one process and so at most
one core each). The same namespaces are routed two ways in turn:
- `plain`: IP forwarding gNB -> UPF -> edge, no tunnel (the kernel's limit here);
- `gtp`: the gNB's air traffic into its GTP-U endpoint, G-PDUs over N3, the UPF's endpoint.
Figures: TCP goodput UE -> edge at MTU 1500 on N3 (UE MTU 1456), the endpoints' CPU, and the
median round trip of 64-byte UDP pings UE <-> edge, back to back and 2 ms apart; half the
difference to `plain` is the delay the tunnel adds each way (the 2 ms one is judged).
Goals: >= 1 Gbit/s, <= 0.1 ms. A benchmark: a missed goal is printed as MISS and the script
still exits 0. Everything is removed at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import secrets
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make the repo importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from netem.gtpu.endpoint import EndpointConfig, GtpEndpoint, Session
from netem.netns import in_netns
from testbed.linktest import in_namespace, tcp_goodput

UE, GNB_AIR = "10.45.0.2", "10.201.0.1"
GNB_N3, UPF_N3 = "10.100.3.1", "10.100.3.2"
UPF_N6, EDGE = "10.100.6.1", "10.100.6.2"
POOL = "10.45.0.0/16"
PING_PORT = 7401
#: Pings back to back (the endpoints stay busy), and 2 ms apart: each ping then wakes two idle
#: processes per way, which on a VM's idle vCPUs costs tens of microseconds; that one is judged.
GAPS_S = (0.0, 0.002)


def sh(*args: str) -> None:
    subprocess.run(args, check=True, capture_output=True, timeout=10)


@contextlib.contextmanager
def namespaces() -> Iterator[dict[str, str]]:
    tag = secrets.token_hex(3)
    ns = {r: f"elb-{tag}-{r}" for r in ("ue", "gnb", "upf", "edge")}
    try:
        for name in ns.values():
            sh("ip", "netns", "add", name)
        for a, b, dev_a, dev_b, addr_a, addr_b, mtu in (
            ("ue", "gnb", "pdu0", "air0", f"{UE}/32", f"{GNB_AIR}/32", 1456),
            ("gnb", "upf", "n3", "n3", f"{GNB_N3}/30", f"{UPF_N3}/30", 1500),
            ("upf", "edge", "n6", "n6", f"{UPF_N6}/30", f"{EDGE}/30", 1500),
        ):
            tmp_a, tmp_b = f"t{tag}{a[:2]}", f"t{tag}{b[:2]}"
            sh("ip", "link", "add", tmp_a, "netns", ns[a], "mtu", str(mtu), "type", "veth",
               "peer", "name", tmp_b, "netns", ns[b], "mtu", str(mtu))  # fmt: skip
            sh("ip", "-n", ns[a], "link", "set", tmp_a, "name", dev_a)
            sh("ip", "-n", ns[b], "link", "set", tmp_b, "name", dev_b)
            for n, dev, addr in ((ns[a], dev_a, addr_a), (ns[b], dev_b, addr_b)):
                sh("ip", "-n", n, "addr", "add", addr, "dev", dev)
                sh("ip", "-n", n, "link", "set", dev, "up")
        sh("ip", "-n", ns["ue"], "route", "add", "default", "via", GNB_AIR, "dev", "pdu0", "onlink")
        sh("ip", "-n", ns["gnb"], "route", "add", f"{UE}/32", "dev", "air0")
        sh("ip", "-n", ns["edge"], "route", "add", POOL, "via", UPF_N6)
        for role in ("gnb", "upf"):
            for key in ("net.ipv4.ip_forward=1", "net.ipv4.conf.all.rp_filter=0"):
                sh("ip", "netns", "exec", ns[role], "sysctl", "-qw", key)
        yield ns
    finally:
        for name in ns.values():
            subprocess.run(["ip", "netns", "del", name], capture_output=True)


def route_plain(ns: dict[str, str]) -> None:
    sh("ip", "-n", ns["gnb"], "route", "replace", "default", "via", UPF_N3)
    sh("ip", "-n", ns["upf"], "route", "replace", POOL, "via", GNB_N3)


@contextlib.contextmanager
def route_gtp(ns: dict[str, str], offload: bool) -> Iterator[tuple[GtpEndpoint, GtpEndpoint]]:
    session = Session(UE, 0x1001, 0x2001, GNB_N3, UPF_N3)
    gnb_cfg = EndpointConfig("gnb", ns["gnb"], "gtp0", GNB_N3, (session,), offload=offload)
    upf_cfg = EndpointConfig("upf", ns["upf"], "upf0", UPF_N3, (session,), offload=offload)
    with GtpEndpoint(gnb_cfg) as gnb, GtpEndpoint(upf_cfg) as upf:
        sh("ip", "-n", ns["gnb"], "route", "del", "default")
        sh("ip", "-n", ns["gnb"], "rule", "add", "iif", "air0", "lookup", "100")
        sh("ip", "-n", ns["gnb"], "route", "add", "default", "dev", "gtp0", "table", "100")
        sh("ip", "-n", ns["upf"], "route", "replace", POOL, "dev", "upf0")
        for role, dev in (("gnb", "gtp0"), ("upf", "upf0")):
            sh("ip", "netns", "exec", ns[role], "sysctl", "-qw", f"net.ipv4.conf.{dev}.rp_filter=0")
        yield gnb, upf
    sh("ip", "-n", ns["gnb"], "rule", "del", "iif", "air0", "lookup", "100")


def udp_echo(addr: str, port: int, seconds: float) -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((addr, port))
    s.settimeout(0.5)
    n, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            data, peer = s.recvfrom(2048)
        except TimeoutError:
            continue
        s.sendto(data, peer)
        n += 1
    return n


def rtts(ns: dict[str, str], count: int, gap_s: float) -> list[float]:
    """Round trips (s) of `count` 64-byte UDP pings UE -> edge -> UE, one at a time, `gap_s`
    between an answer and the next ping."""
    server = in_namespace(ns["edge"], udp_echo, EDGE, PING_PORT, count * 0.01 + 3)
    time.sleep(0.3)
    with in_netns(ns["ue"]):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.settimeout(1)
    out = []
    with s:
        for _ in range(count):
            t = time.perf_counter()
            s.sendto(bytes(64), (EDGE, PING_PORT))
            with contextlib.suppress(TimeoutError):
                s.recvfrom(2048)
                out.append(time.perf_counter() - t)
            time.sleep(gap_s)
    server.result(30)
    return out


def cpu_s(pid: int | None) -> float:
    if pid is None:
        return 0.0
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class Tunnel:
    """What one way of routing the namespaces measured."""

    bps: float
    rtt_s: dict[float, float]  # gap between pings -> median RTT
    cpu: tuple[float, float] = (0.0, 0.0)  # gNB, UPF endpoint: share of a core during TCP
    stats: dict[str, Any] = field(default_factory=dict)


def measure_gtp(ns: dict[str, str], offload: bool, seconds: float, pings: int) -> Tunnel:
    route_plain(ns)  # the routes the last tunnel's devices took with them
    with route_gtp(ns, offload) as (gnb, upf):
        c0 = (cpu_s(gnb.pid), cpu_s(upf.pid), time.monotonic())
        bps = tcp_goodput(ns["ue"], ns["edge"], EDGE, seconds, 1.0)
        c1 = (cpu_s(gnb.pid), cpu_s(upf.pid), time.monotonic())
        rtt = {g: statistics.median(rtts(ns, pings, g)) for g in GAPS_S}
        wall = c1[2] - c0[2]
        cpu = ((c1[0] - c0[0]) / wall, (c1[1] - c0[1]) / wall)
        return Tunnel(bps, rtt, cpu, upf.stats())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=4.0, help="per TCP measurement")
    p.add_argument("--pings", type=int, default=500)
    a = p.parse_args()
    if os.geteuid() != 0:
        print("bench_gtp: needs root (network namespaces); skipped")
        return 0
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    with namespaces() as ns:
        route_plain(ns)
        plain = Tunnel(
            tcp_goodput(ns["ue"], ns["edge"], EDGE, a.seconds, 1.0),
            {g: statistics.median(rtts(ns, a.pings, g)) for g in GAPS_S},
        )
        before = measure_gtp(ns, False, a.seconds, a.pings)
        now = measure_gtp(ns, True, a.seconds, a.pings)
    print("\nN3 tunnel, UE -> edge (veth air/N3/N6; GTP-U endpoints in user space)")
    print("  before: one packet per TUN read and write; now: GRO into the TUN (netem.gso)")
    print(f"  {'figure':34s} {'plain':>9s} {'before':>9s} {'now':>9s}  goal         verdict")
    ok = now.bps >= 1e9
    print(
        f"  {'TCP goodput, Gbit/s, N3 MTU 1500':34s} {plain.bps / 1e9:9.2f} "
        f"{before.bps / 1e9:9.2f} {now.bps / 1e9:9.2f}  >= 1          {'ok' if ok else 'MISS'}"
    )
    print(f"  {'  now as a ratio':34s} {now.bps / plain.bps:9.3f} {now.bps / before.bps:9.2f}")
    for gap in GAPS_S:
        label = "back to back" if gap == 0 else f"{gap * 1e3:g} ms apart"
        row = f"median RTT, ms, 64 B UDP, {label}"
        print(
            f"  {row:34s} {plain.rtt_s[gap] * 1e3:9.3f} {before.rtt_s[gap] * 1e3:9.3f} "
            f"{now.rtt_s[gap] * 1e3:9.3f}"
        )
        added = [(t.rtt_s[gap] - plain.rtt_s[gap]) / 2 * 1e3 for t in (before, now)]
        judged = gap == GAPS_S[-1]
        verdict = ("ok" if added[1] <= 0.1 else "MISS") if judged else "(not judged)"
        print(
            f"  {'  added delay each way, ms':34s} {'':9s} {added[0]:9.3f} {added[1]:9.3f}"
            f"  <= 0.1       {verdict}"
        )
    for name, t in (("before", before), ("now", now)):
        print(
            f"  endpoint CPU during TCP ({name}): gNB {t.cpu[0]:.0%}, UPF {t.cpu[1]:.0%} of a core"
        )
    share = now.stats.get("overhead_share") or 0
    writes = now.stats.get("received", {}).get("tun_writes", 0)
    packets = now.stats.get("received", {}).get("packets", 0)
    print(
        f"  UPF (now): GTP-U overhead {share:.1%} of its N3 bytes; {packets} packets in "
        f"{writes} TUN writes; drops {now.stats.get('drops') or 'none'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
