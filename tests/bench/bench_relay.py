"""Benchmark of the userspace link (TUN relay) against a plain veth pair and the relay before
offloads, in one run: throughput, CPU, delay error, rate and loss accuracy.

    sudo .venv/bin/python tests/bench/bench_relay.py [--quick] [--only NAME ...]

Three data planes join the same two namespaces (`elq-<hex>-a`, `elq-<hex>-b`) in turn:
- `veth`: a plain veth pair, no emulation: the host's limit;
- `before`: the relay as it was before offloads (`--no-offload`: one read, one pipeline pass
  and one write per MTU-sized packet);
- `now`: the relay with TUN offloads (TSO/USO super-packets, `netem.gso`).
Traffic comes from Python senders and receivers in the namespaces (the link self-test's, from
`testbed.linktest`, plus a UDP-GSO sender here). One-way delays use the sender's
CLOCK_MONOTONIC stamp in each datagram (both ends share the host clock). Each figure of `now`
is printed beside `before` and `veth` as a ratio, with the issue's goal and ok/MISS. Only
`now` is judged. The host has 2 cores that other work may share, so throughput and CPU
figures move with that load (the load average is printed). Everything is removed at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import secrets
import socket
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from pyroute2 import IPRoute, netns

from netem.netns import in_netns
from netem.profile import LinkProfile
from netem.relay.client import UserspaceLink
from netem.stages import jitter_sd
from testbed.linktest import (
    CTX,
    PORT,
    STAMP,
    Worker,
    in_namespace,
    tcp_receive,
    tcp_send,
    udp_receive,
    udp_send,
)

ADDR_A, ADDR_B = "10.214.0.1", "10.214.0.2"
PLANES = ("veth", "before", "now")
UDP_SEGMENT, UDP_GRO, SOL_UDP = 103, 104, 17  # linux/udp.h: UDP GSO and GRO socket options


def udp_gso_send(
    addr: str, port: int, count: int, size: int, rate_bps: float, per_send: int = 16
) -> int:
    """Like `udp_send`, but `per_send` datagrams per sendto through UDP GSO (as QUIC sends)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 8 << 20)
    sock.setsockopt(SOL_UDP, UDP_SEGMENT, size)
    buf = bytearray(size * per_send)
    t0 = time.monotonic()
    for first in range(0, count, per_send):
        due = t0 + first * size * 8 / rate_bps
        wait = due - time.monotonic()
        if wait > 0.0005:
            time.sleep(wait)
        n = min(per_send, count - first)
        now = time.monotonic()
        for i in range(n):
            STAMP.pack_into(buf, i * size, now, first + i)
        # A full local queue loses them, as on a real host.
        with contextlib.suppress(OSError):
            sock.sendto(memoryview(buf)[: n * size], (addr, port))
    sock.close()
    return count


def udp_gro_receive(
    ready: Any, addr: str, port: int, duration_s: float, idle_s: float = 0.0
) -> list[tuple[float, float, int, int]]:
    """Like `udp_receive`, but the kernel hands over runs of datagrams at once (UDP GRO), so a
    Python receiver keeps up with 1 Gbit/s; each datagram of a run gets the run's time."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
    sock.setsockopt(SOL_UDP, UDP_GRO, 1)
    sock.bind((addr, port))
    sock.settimeout(0.05)
    ready.set()
    out: list[tuple[float, float, int, int]] = []
    end = time.monotonic() + duration_s
    last = 0.0
    space = socket.CMSG_SPACE(4)
    while (now := time.monotonic()) < end:
        if idle_s and out and now - last > idle_s:
            break
        try:
            data, ancillary, _, _ = sock.recvmsg(65535, space)
        except TimeoutError:
            continue
        last = time.monotonic()
        size = len(data)
        for level, kind, value in ancillary:
            if level == SOL_UDP and kind == UDP_GRO:
                size = int.from_bytes(value[:4], sys.byteorder)
        for offset in range(0, len(data), size):
            sent, seq = STAMP.unpack_from(data, offset)
            out.append((last, sent, seq, min(size, len(data) - offset)))
    sock.close()
    return out


@dataclass
class Row:
    section: str
    what: str
    figures: dict[str, float | None]  # plane -> value
    unit: str
    goal: str = ""
    ok: bool | None = None
    note: str = ""


class Bench:
    """Two namespaces, the three data planes between them, and one method per figure."""

    def __init__(self, quick: bool) -> None:
        self.quick = quick
        tag = secrets.token_hex(4)
        self.ns_a, self.ns_b = f"elq-{tag}-a", f"elq-{tag}-b"
        self.rows: list[Row] = []

    @contextmanager
    def namespaces(self) -> Iterator[None]:
        try:
            for name in (self.ns_a, self.ns_b):
                netns.create(name)
                # TCP buffers of these namespaces only: at 5+ Gbit/s and 10 ms RTT the window
                # must exceed the default 6 MiB maximum, or the window, not the link, limits.
                with in_netns(name):
                    for key in ("tcp_rmem", "tcp_wmem"):
                        with open(f"/proc/sys/net/ipv4/{key}", "w") as f:
                            f.write("4096 131072 67108864")
            yield
        finally:
            for name in (self.ns_a, self.ns_b):
                if name in netns.listnetns():
                    netns.remove(name)

    @contextmanager
    def plane(
        self,
        plane: str,
        uplink: LinkProfile | None = None,
        downlink: LinkProfile | None = None,
        mtu: int = 1500,
    ) -> Iterator[UserspaceLink | None]:
        """A fresh data plane between the namespaces (None for veth, which has no counters)."""
        if plane == "veth":
            with self._veth(mtu):
                yield None
            return
        link = UserspaceLink(
            self.ns_a,
            self.ns_b,
            dev_a="bl0",
            dev_b="bl0",
            addr_a=f"{ADDR_A}/30",
            addr_b=f"{ADDR_B}/30",
            mtu=mtu,
            uplink=uplink or LinkProfile(),
            downlink=downlink or LinkProfile(),
            seed=1,
            offload=plane == "now",
        )
        with link:
            yield link

    @contextmanager
    def _veth(self, mtu: int) -> Iterator[None]:
        with IPRoute() as ipr:
            ipr.link("add", ifname="bv0a", kind="veth", peer={"ifname": "bv0b"})
            try:
                for dev, ns in (("bv0a", self.ns_a), ("bv0b", self.ns_b)):
                    ipr.link("set", index=ipr.link_lookup(ifname=dev)[0], net_ns_fd=ns)
                for dev, ns, addr in (("bv0a", self.ns_a, ADDR_A), ("bv0b", self.ns_b, ADDR_B)):
                    with in_netns(ns), IPRoute() as inner:
                        index = inner.link_lookup(ifname=dev)[0]
                        inner.link("set", index=index, mtu=mtu, state="up")
                        inner.addr("add", index=index, address=addr, prefixlen=30)
                yield
            finally:
                with in_netns(self.ns_a), IPRoute() as inner:
                    index = inner.link_lookup(ifname="bv0a")
                    if index:
                        inner.link("del", index=index[0])

    def add(self, row: Row) -> None:
        self.rows.append(row)
        values = "  ".join(
            f"{p} {_fmt(v, row.unit)}" for p, v in row.figures.items() if v is not None
        )
        mark = "" if row.ok is None else ("ok" if row.ok else "MISS")
        print(f"  {row.what:<34} {values:<58} {row.goal:<16} {mark} {row.note}", flush=True)

    # -- traffic ----------------------------------------------------------------------------

    def udp(
        self,
        plane: str,
        profile: LinkProfile,
        count: int,
        size: int,
        rate_bps: float,
        listen_s: float,
        sender: Callable[..., int] = udp_send,
    ) -> tuple[list[tuple[float, float, int, int]], dict[str, Any] | None]:
        receive = udp_gro_receive if sender is udp_gso_send else udp_receive
        with self.plane(plane, profile) as link:
            ready = CTX.Event()
            receiver = in_namespace(self.ns_b, receive, ready, ADDR_B, PORT, listen_s)
            ready.wait(5)
            in_namespace(self.ns_a, sender, ADDR_B, PORT, count, size, rate_bps).result(60)
            got = receiver.result(60)
            return got, None if link is None else link.counters()

    def tcp(
        self,
        plane: str,
        profile: LinkProfile,
        seconds: float,
        mtu: int = 1500,
        back: LinkProfile | None = None,
    ) -> tuple[float, float | None]:
        """Steady-state TCP goodput (bit/s) A->B, and the relay's CPU (cores) meanwhile."""
        warm = min(1.0, seconds / 3)
        with self.plane(plane, profile, back, mtu=mtu) as link:
            ready = CTX.Event()
            receiver: Worker = in_namespace(
                self.ns_b, tcp_receive, ready, ADDR_B, PORT, seconds + 0.5
            )
            ready.wait(5)
            sender = in_namespace(self.ns_a, tcp_send, ADDR_B, PORT, seconds)
            time.sleep(warm)
            cpu0, t0 = _relay_cpu(link), time.monotonic()
            time.sleep(seconds - warm - 0.2)
            cpu1, t1 = _relay_cpu(link), time.monotonic()
            marks = receiver.result(60)
            sender.result(60)
        first = marks[0][0] if marks else 0.0
        window = [m for m in marks if first + warm <= m[0] <= first + seconds - 0.1]
        if len(window) < 2:
            return 0.0, None
        goodput = (window[-1][1] - window[0][1]) * 8 / (window[-1][0] - window[0][0])
        cpu = None if cpu0 is None or cpu1 is None else (cpu1 - cpu0) / (t1 - t0)
        return goodput, cpu

    # -- figures ----------------------------------------------------------------------------

    def throughput(self) -> None:
        seconds = 3.0 if self.quick else 4.0
        print("TCP throughput, no rate limit (relays: 5 ms delay each way; veth: none)")
        delay = LinkProfile(delay_s=0.005, queue_packets=None)
        for mtu, goal in ((1500, 2e9), (65000, 5e9)):
            figures: dict[str, float | None] = {}
            cpus: dict[str, float | None] = {}
            for plane in PLANES:
                figures[plane], cpus[plane] = self.tcp(plane, delay, seconds, mtu, back=delay)
            now = figures["now"] or 0.0
            self.add(
                Row(
                    "throughput",
                    f"TCP, MTU {mtu}",
                    figures,
                    "bps",
                    f">= {goal / 1e9:.0f} Gbit/s",
                    now >= goal,
                    _ratios(figures) + f"; relay CPU now {_pct(cpus['now'])}",
                )
            )

    def cpu(self) -> None:
        seconds = 3.0 if self.quick else 5.0
        print("relay CPU for shaped TCP (100 Mbit/s, 5 ms delay each way)")
        delay = LinkProfile(delay_s=0.005)
        shaped = LinkProfile(rate_bps=100e6, delay_s=0.005)
        per: dict[str, float | None] = {}
        for plane in ("before", "now"):
            got, cpu = self.tcp(plane, shaped, seconds, back=delay)
            per[plane] = None if cpu is None or not got else cpu / (got / 100e6)
        self.add(
            Row(
                "cpu",
                "CPU per 100 Mbit/s of shaped TCP",
                per,
                "share",
                "<= 20% of a core",
                per["now"] is not None and per["now"] <= 0.20,
                _ratio(per, "now", "before", "before"),
            )
        )

    def delay(self) -> None:
        pps, count = 1000, 1500 if self.quick else 3000
        print(f"one-way delay error (UDP, 64 B, {pps} packets/s; net of the 0 ms path)")
        base: dict[str, float] = {}
        for delay_ms in (0, 5, 20, 50):
            errors: dict[str, float | None] = {}
            for plane in ("before", "now"):
                got, _ = self.udp(
                    plane,
                    LinkProfile(delay_s=delay_ms / 1000),
                    count,
                    64,
                    pps * 64 * 8,
                    count / pps + 1.0,
                )
                owd = statistics.median(r - s for r, s, _, _ in got)
                if delay_ms == 0:
                    base[plane] = owd
                    errors[plane] = owd
                else:
                    errors[plane] = owd - delay_ms / 1000 - base[plane]
            if delay_ms == 0:
                self.add(Row("delay", "path without delay (median)", errors, "s"))
                continue
            now = errors["now"] or 0.0
            self.add(
                Row(
                    "delay",
                    f"median error at {delay_ms} ms",
                    errors,
                    "s",
                    "|err| <= 0.1 ms",
                    abs(now) <= 0.0001,
                )
            )

    def jitter(self) -> None:
        print("jitter (delay 20 ms, jitter 5 ms, reorder on: no order clamping)")
        for dist in ("normal", "uniform"):
            profile = LinkProfile(
                delay_s=0.020, jitter_s=0.005, jitter_distribution=dist, reorder=True
            )
            got, _ = self.udp("now", profile, 1000, 64, 500 * 64 * 8, 2.6)
            sd, want = statistics.stdev(r - s for r, s, _, _ in got), jitter_sd(profile)
            self.add(
                Row(
                    "jitter",
                    f"sd, {dist}",
                    {"now": sd},
                    "s",
                    f"{want * 1e3:.3f} ms ±5%",
                    abs(sd - want) <= 0.05 * want,
                )
            )

    def rate(self) -> None:
        seconds = 3.0 if self.quick else 5.0
        print(f"rate accuracy ({seconds:.0f} s each; expected = rate x payload fraction)")
        for mbit in (1, 10, 100, 1000):
            rate = mbit * 1e6
            want = rate * 1448 / 1500
            got = {
                p: self.tcp(p, LinkProfile(rate_bps=rate, delay_s=0.002), seconds)[0]
                for p in ("before", "now")
            }
            self.add(
                Row(
                    "rate",
                    f"TCP at {mbit} Mbit/s",
                    got,
                    "bps",
                    "±2%",
                    abs((got["now"] or 0) / want - 1) <= 0.02,
                    _off(got, want),
                )
            )
        for mbit, gso in ((1, False), (10, False), (100, False), (1000, True)):
            rate = mbit * 1e6
            size = 1472
            want = rate * size / 1500
            count = int(1.3 * want * seconds / (size * 8))
            sender = udp_gso_send if gso else udp_send
            got: dict[str, float | None] = {}
            for plane in ("before", "now"):
                profile = LinkProfile(rate_bps=rate, queue_packets=200)
                arrived, _ = self.udp(
                    plane, profile, count, size, 1.3 * want, seconds + 0.5, sender
                )
                t0 = arrived[0][0] if arrived else 0.0
                window = [n for r, _, _, n in arrived if t0 + 0.5 <= r <= t0 + seconds - 0.5]
                got[plane] = sum(window) * 8 / (seconds - 1.0)
            self.add(
                Row(
                    "rate",
                    f"UDP{'-GSO' if gso else ''} at {mbit} Mbit/s (offered 1.3x)",
                    got,
                    "bps",
                    "±2%",
                    abs((got["now"] or 0) / want - 1) <= 0.02,
                    _off(got, want),
                )
            )

    def loss(self) -> None:
        print("loss (UDP datagrams; 20 Mbit/s plain, 1 Gbit/s through UDP GSO)")
        for loss in (0.01, 0.05):
            for mbit, size, count, sender in (
                (20, 128, 20_000, udp_send),
                (1000, 1200, 200_000, udp_gso_send),
            ):
                got: dict[str, float | None] = {}
                counted = ""
                for plane in ("before", "now"):
                    arrived, counters = self.udp(
                        plane, LinkProfile(loss=loss), count, size, mbit * 1e6, 3.0, sender
                    )
                    got[plane] = 1 - len({seq for _, _, seq, _ in arrived}) / count
                    if plane == "now" and counters is not None:
                        dropped = counters["uplink"]["total"]["dropped_packets"].get("loss", 0)
                        counted = f"relay counted {dropped / count:.2%}"
                self.add(
                    Row(
                        "loss",
                        f"loss {loss:.0%} at {mbit} Mbit/s",
                        got,
                        "fraction",
                        "±0.5 pp",
                        abs((got["now"] or 0) - loss) <= 0.005,
                        counted,
                    )
                )

    def datagrams(self) -> None:
        print("per-packet limit: plain 1472-byte UDP datagrams offered at 1.5 Gbit/s")
        got: dict[str, float | None] = {}
        for plane in PLANES:
            count = 150_000 if not self.quick else 80_000
            arrived, _ = self.udp(plane, LinkProfile(), count, 1472, 1.5e9, 3.0)
            if len(arrived) > 2:
                span = arrived[-1][0] - arrived[0][0]
                got[plane] = len(arrived) / span if span > 0 else None
        self.add(
            Row("datagrams", "datagrams per second delivered", got, "pps", "", None, _ratios(got))
        )


def _relay_cpu(link: UserspaceLink | None) -> float | None:
    return None if link is None else link.counters()["relay"]["cpu_s"]


def _fmt(value: float, unit: str) -> str:
    if unit == "bps":
        return f"{value / 1e6:.0f} Mbit/s" if value >= 1e7 else f"{value / 1e6:.3f} Mbit/s"
    if unit == "s":
        return f"{value * 1e3:+.3f} ms"
    if unit == "share":
        return f"{value:.0%}"
    if unit == "fraction":
        return f"{value:.2%}"
    if unit == "pps":
        return f"{value:,.0f}/s"
    return f"{value:g}"


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.0%}"


def _ratio(figures: dict[str, float | None], a: str, b: str, label: str) -> str:
    x, y = figures.get(a), figures.get(b)
    if not x or not y:
        return ""
    return f"{x / y:.2f}x {label}"


def _ratios(figures: dict[str, float | None]) -> str:
    parts = [_ratio(figures, "now", "veth", "veth"), _ratio(figures, "now", "before", "before")]
    return "now = " + ", ".join(p for p in parts if p)


def _off(got: dict[str, float | None], want: float) -> str:
    return ", ".join(f"{p} {((v or 0) / want - 1) * 100:+.2f}%" for p, v in got.items())


def main() -> int:
    parts = ["throughput", "cpu", "delay", "jitter", "rate", "loss", "datagrams"]
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="shorter runs")
    parser.add_argument("--only", choices=parts, action="append")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_relay needs root (network namespaces, TUN devices)", file=sys.stderr)
        return 2
    bench = Bench(args.quick)
    load = os.getloadavg()
    print(f"userspace link benchmark; load average {load[0]:.2f} on {os.cpu_count()} cores")
    print("planes: veth = plain veth pair; before = relay without offloads; now = relay")
    started = time.monotonic()
    with bench.namespaces():
        for part in args.only or parts:
            getattr(bench, part)()
    misses = [r for r in bench.rows if r.ok is False]
    print(f"done in {time.monotonic() - started:.0f} s; {len(misses)} figure(s) off target")
    for r in misses:
        print(f"  MISS: {r.what}")
    return 0 if not misses else 1


if __name__ == "__main__":
    sys.exit(main())
