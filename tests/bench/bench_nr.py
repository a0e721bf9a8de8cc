"""Benchmark of the NR radio model on real packets (issue #16, deliverable 6).

    sudo .venv/bin/python tests/bench/bench_nr.py [--quick] [--only NAME ...]

- `departure`: how late the relay lets packets leave after the end of their slot (its exit
  lateness: the clock when the first packet of a batch is written, minus the slot end plus
  delay the model gave it), p50 and p99, for sparse probes alone and with 100 Mbit/s of UDP
  through the same radio direction. Goal: p99 <= 0.2 ms idle, <= 0.5 ms loaded.
- `cpu`: the relay's CPU per 10 Mbit/s of saturating TCP through OpenAirInterface's uplink
  (`oai-tdd-30k`: SR and grants, HARQ at 10% BLER, RLC-AM).
- `cell`: the most one cell carries, with 1 UE and with 8 UEs in one relay (saturating TCP
  from each), on a radio whose blocks carry more than the relay can (273 PRBs, 4 layers,
  MCS 27, nine uplink slots in ten), so the relay, not the model, is the limit. Goal:
  >= 300 Mbit/s per cell on one core.

Namespaces are `elq-<hex>-*`, removed at the end. The host has 2 cores that other work may
share: the load average is printed.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import secrets
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from pyroute2 import netns

from netem.netns import in_netns
from netem.nr.radio import Radio
from netem.profile import LinkProfile
from netem.relay.client import UserspaceLink
from testbed.linktest import CTX, PORT, in_namespace, tcp_receive, tcp_send, udp_receive, udp_send

#: A radio no relay can fill: 273 PRBs, 4 layers, MCS 27, an uplink slot every slot but one.
WIDE = Radio(slots="SUUUUUUUUU", special=(2, 2, 10), n_prb=273, layers=4, mcs=27, ul_access="ideal")
OAI = Radio(bler=0.1)  # oai-tdd-30k's uplink as the scenarios use it


def _subnet(i: int) -> tuple[str, str]:
    return f"10.216.{i}.1", f"10.216.{i}.2"


class Bench:
    def __init__(self, quick: bool) -> None:
        self.quick = quick
        self.tag = secrets.token_hex(3)
        self.made: list[str] = []
        self.misses: list[str] = []

    @contextmanager
    def namespaces(self, names: list[str]) -> Iterator[list[str]]:
        full = [f"elq-{self.tag}-{n}" for n in names]
        try:
            for name in full:
                netns.create(name)
                with in_netns(name):
                    for key in ("tcp_rmem", "tcp_wmem"):
                        with open(f"/proc/sys/net/ipv4/{key}", "w") as f:
                            f.write("4096 131072 67108864")
            yield full
        finally:
            for name in full:
                if name in netns.listnetns():
                    netns.remove(name)

    @contextmanager
    def cell(self, ues: list[str], gnb: str, uplink: LinkProfile) -> Iterator[list[UserspaceLink]]:
        """One relay carrying an air link per UE, all in one cell."""
        links: list[UserspaceLink] = []
        try:
            for i, ue in enumerate(ues):
                a, b = _subnet(i)
                link = UserspaceLink(
                    ue,
                    gnb,
                    dev_a="nr0",
                    dev_b=f"nr{i}",
                    addr_a=f"{a}/30",
                    addr_b=f"{b}/30",
                    uplink=uplink,
                    seed=i,
                    name=f"ue{i}",
                    cell="gnb",
                    host=links[0] if links else None,
                )
                link.start()
                links.append(link)
            yield links
        finally:
            for link in reversed(links):
                link.close()

    def judge(self, what: str, ok: bool) -> str:
        if not ok:
            self.misses.append(what)
        return "ok" if ok else "MISS"

    # -- figures ----------------------------------------------------------------------------

    def departure(self) -> None:
        print("slot-boundary departure error (relay exit lateness), uplink of a wide radio")
        seconds = 4.0 if self.quick else 8.0
        with self.namespaces(["ue", "gnb"]) as (ue, gnb):
            for load_bps, goal in ((0.0, 0.0002), (100e6, 0.0005)):
                with self.cell([ue], gnb, LinkProfile(radio=WIDE)) as (link,):
                    b = _subnet(0)[1]
                    flood = None
                    if load_bps:
                        ready = CTX.Event()
                        sink = in_namespace(gnb, udp_receive, ready, b, PORT + 1, seconds + 2)
                        ready.wait(5)
                        count = int(seconds * load_bps / (1400 * 8))
                        flood = in_namespace(ue, udp_send, b, PORT + 1, count, 1400, load_bps)
                    ready = CTX.Event()
                    probes = in_namespace(gnb, udp_receive, ready, b, PORT, seconds + 2)
                    ready.wait(5)
                    n = int(seconds * 50)
                    in_namespace(ue, udp_send, b, PORT, n, 64, 50 * 64 * 8).result(60)
                    got = probes.result(60)
                    carried = None
                    if flood is not None:
                        flood.result(60)
                        arrived = sink.result(60)
                        if len(arrived) > 1:
                            span = arrived[-1][0] - arrived[0][0]
                            carried = sum(x[3] for x in arrived) * 8 / span if span else None
                    late = link.counters()["relay"]["exit_lateness_s"]
                p50, p99 = late["p50"] or float("nan"), late["p99"] or float("nan")
                mark = self.judge(f"departure p99 at {load_bps / 1e6:g} Mbit/s", p99 <= goal)
                extra = "" if carried is None else f"; {carried / 1e6:.1f} Mbit/s carried"
                print(
                    f"  {'idle' if not load_bps else f'{load_bps / 1e6:g} Mbit/s of UDP':<20}"
                    f" p50 {p50 * 1000:.3f} ms  p99 {p99 * 1000:.3f} ms"
                    f"  (goal p99 <= {goal * 1000:g} ms) {mark}; {len(got)} probes{extra}"
                )

    def cpu(self) -> None:
        print("relay CPU per 10 Mbit/s of saturating TCP through oai-tdd-30k's uplink")
        seconds = 4.0 if self.quick else 8.0
        with (
            self.namespaces(["ue", "gnb"]) as (ue, gnb),
            self.cell([ue], gnb, LinkProfile(radio=OAI)) as (link,),
        ):
            goodput, cpu = self._tcp([link], [ue], gnb, seconds)
        per = cpu / (goodput / 10e6) if goodput else float("nan")
        print(
            f"  {goodput / 1e6:.2f} Mbit/s of TCP (the model's goodput "
            f"{OAI.goodput_bps('uplink') / 1e6:.2f}), relay {cpu * 100:.1f}% of a core: "
            f"{per * 100:.2f}% of a core per 10 Mbit/s"
        )

    def cell_capacity(self) -> None:
        print("what one cell carries before the relay is the limit (saturating TCP per UE)")
        seconds = 4.0 if self.quick else 6.0
        model = WIDE.rate_bps("uplink")
        print(f"  the radio's blocks: {model / 1e6:.0f} Mbit/s of uplink")
        for n in (1, 8):
            names = [f"u{i}" for i in range(n)] + ["gnb"]
            with self.namespaces(names) as full:
                ues, gnb = full[:-1], full[-1]
                with self.cell(ues, gnb, LinkProfile(radio=WIDE)) as links:
                    goodput, cpu = self._tcp(links, ues, gnb, seconds)
            mark = self.judge(f"cell with {n} UE(s)", goodput >= 300e6)
            print(
                f"  {n} UE(s): {goodput / 1e6:.0f} Mbit/s in all, relay {cpu * 100:.0f}% "
                f"of a core (goal >= 300 Mbit/s) {mark}"
            )

    def _tcp(
        self, links: list[UserspaceLink], ues: list[str], gnb: str, seconds: float
    ) -> tuple[float, float]:
        """Summed steady TCP goodput of every UE to the gNB, and the relay's CPU (cores)."""
        receivers: list[Any] = []
        for i in range(len(ues)):
            ready = CTX.Event()
            receivers.append(
                in_namespace(gnb, tcp_receive, ready, _subnet(i)[1], PORT, seconds + 0.5)
            )
            ready.wait(5)
        senders = [
            in_namespace(ue, tcp_send, _subnet(i)[1], PORT, seconds) for i, ue in enumerate(ues)
        ]
        warm = min(1.5, seconds / 3)
        time.sleep(warm)
        cpu0, t0 = links[0].counters()["relay"]["cpu_s"], time.monotonic()
        time.sleep(seconds - warm - 0.3)
        cpu1, t1 = links[0].counters()["relay"]["cpu_s"], time.monotonic()
        total = 0.0
        for receiver in receivers:
            marks = receiver.result(60)
            first = marks[0][0] if marks else 0.0
            window = [m for m in marks if first + warm <= m[0] <= first + seconds - 0.3]
            if len(window) >= 2:
                total += (window[-1][1] - window[0][1]) * 8 / (window[-1][0] - window[0][0])
        for sender in senders:
            with contextlib.suppress(Exception):
                sender.result(60)
        return total, (cpu1 - cpu0) / (t1 - t0)


def main() -> int:
    parts = {"departure": "departure", "cpu": "cpu", "cell": "cell_capacity"}
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="shorter runs")
    parser.add_argument("--only", choices=list(parts), action="append")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_nr needs root (network namespaces, TUN devices)", file=sys.stderr)
        return 2
    bench = Bench(args.quick)
    load = os.getloadavg()
    print(f"NR radio benchmark; load average {load[0]:.2f} on {os.cpu_count()} cores")
    started = time.monotonic()
    for part in args.only or list(parts):
        getattr(bench, parts[part])()
    print(f"done in {time.monotonic() - started:.0f} s; {len(bench.misses)} figure(s) off target")
    for what in bench.misses:
        print(f"  MISS: {what}")
    return 0 if not bench.misses else 1


if __name__ == "__main__":
    sys.exit(main())
