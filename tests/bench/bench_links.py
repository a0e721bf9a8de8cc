"""Fidelity of the emulated links of a run, on the backend `auto` picks (userspace where the
kernel has no sch_netem), measured through a real topology and the link controller.

    sudo .venv/bin/python tests/bench/bench_links.py [--quick]

Builds the one-vehicle topology (run namespaces `el-<id>-*`, removed at the end, also on
failure) and measures the air link's uplink (av1 -> gnb1) with the link self-test's probes
(`testbed.linktest`): median one-way delay error at 5/20/50 ms (net of the no-delay
baseline), jitter sd against the configured one, TCP goodput at 1/10/50/100 Mbit/s against
configured x payload fraction, loss at 1%/5% over 10,000 datagrams, the per-second TCP goodput
while a timeline steps the rate 10 -> 50 -> 5 -> 100 Mbit/s once a second, and the timeline's
lateness. One row per figure with its target; the host's load average is printed, since 2
shared cores move throughput and timing figures.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from typing import Any

from netem.profile import LinkProfile
from netem.stages import jitter_sd
from testbed.errors import TestbedError
from testbed.links import LinkController, neutral
from testbed.linktest import (
    CTX,
    IP_PACKET,
    PORT,
    TCP_PAYLOAD,
    goodput_bps,
    in_namespace,
    tcp_goodput,
    tcp_receive,
    tcp_send,
    udp_stream,
)
from testbed.scenario.model import SetEvent
from testbed.timeline import TimelinePlayer
from testbed.topology import Net, build, example_scenario

LINK = "av1-gnb1"
STEPS_MBIT = (10, 50, 5, 100)


class Bench:
    """The air link of a fresh run, and one table row per figure."""

    def __init__(self, net: Net, quick: bool) -> None:
        assert net.control is not None
        self.net = net
        self.control: LinkController = net.control
        self.quick = quick
        self.src, self.dst = net["av1"], net["gnb1"]
        self.addr = str(self.dst.address_towards("av1"))
        self.misses = 0

    def row(self, what: str, measured: str, target: str, ok: bool | None) -> None:
        mark = "" if ok is None else ("ok" if ok else "MISS")
        self.misses += ok is False
        print(f"  {what:<34} {measured:<44} {target:<20} {mark}", flush=True)

    def profile(self, **fields: Any) -> None:
        """Make the uplink exactly `LinkProfile(**fields)`."""
        self.control.set(LINK, "uplink", LinkProfile(**fields).to_dict())

    def owd_ms(self, count: int, pps: float, tail_s: float = 0.5) -> list[float]:
        got = udp_stream(self.src.netns, self.dst.netns, self.addr, count, 64, pps * 512, tail_s)
        return [(r - s) * 1000 for r, s, _, _ in got]

    def delay(self) -> None:
        print("one-way delay (UDP, 64 B, 200 packets/s; error net of the no-delay path)")
        self.profile()
        with neutral(self.control, LINK, "uplink"):
            base = statistics.median(self.owd_ms(300, 500))
        self.row("no-delay path", f"{base:.3f} ms", "", None)
        for ms in (5, 20, 50):
            self.profile(delay_s=ms / 1000)
            err = statistics.median(self.owd_ms(200 if self.quick else 400, 200)) - base - ms
            self.row(
                f"median error at {ms} ms", f"{err:+.3f} ms", "|err| <= 0.5 ms", abs(err) <= 0.5
            )

    def jitter(self) -> None:
        print("jitter (delay 20 ms, jitter 5 ms normal, reorder on)")
        profile = LinkProfile(delay_s=0.020, jitter_s=0.005, reorder=True)
        self.profile(**profile.to_dict())
        owd = self.owd_ms(600 if self.quick else 1500, 500)
        sd, want = statistics.stdev(owd), jitter_sd(profile) * 1000
        self.row("sd", f"{sd:.3f} ms", f"{want:.3f} ms ±10%", abs(sd - want) <= 0.1 * want)

    def goodput(self) -> None:
        seconds = 2.0 if self.quick else 4.0
        frac = TCP_PAYLOAD / (IP_PACKET + self.control.frame_overhead)
        print(f"TCP goodput ({seconds:g} s each; expected = rate x {frac:.4f})")
        for mbit in (1, 10, 50, 100):
            self.profile(rate_bps=mbit * 1e6, delay_s=0.002)
            warm = 1.0 if mbit == 1 else 0.5
            got = tcp_goodput(self.src.netns, self.dst.netns, self.addr, seconds + warm, warm)
            want = mbit * 1e6 * frac
            self.row(
                f"{mbit} Mbit/s",
                f"{got / 1e6:.3f} Mbit/s ({(got / want - 1) * 100:+.2f}%)",
                f"{want / 1e6:.3f} ±5%",
                abs(got / want - 1) <= 0.05,
            )

    def loss(self) -> None:
        print("loss (10,000 UDP datagrams at 5,000/s)")
        for loss in (0.01, 0.05):
            self.profile(loss=loss)
            got = udp_stream(self.src.netns, self.dst.netns, self.addr, 10_000, 64, 5000 * 512, 0.3)
            measured = 1 - len({seq for _, _, seq, _ in got}) / 10_000
            self.row(
                f"loss {loss:.0%}",
                f"{measured:.2%}",
                "±0.5 pp",
                abs(measured - loss) <= 0.005,
            )

    def steps(self) -> None:
        frac = TCP_PAYLOAD / (IP_PACKET + self.control.frame_overhead)
        print("timeline: rate 10 -> 50 -> 5 -> 100 Mbit/s, one step a second, TCP goodput")
        self.profile(rate_bps=STEPS_MBIT[0] * 1e6, delay_s=0.002)
        ready = CTX.Event()
        seconds = len(STEPS_MBIT) + 1.0  # one warm-up second at the first rate
        receiver = in_namespace(self.dst.netns, tcp_receive, ready, self.addr, PORT, seconds + 0.5)
        if not ready.wait(5):
            raise TestbedError("the TCP receiver did not start")
        sender = in_namespace(self.src.netns, tcp_send, self.addr, PORT, seconds)
        time.sleep(1.0)
        events = [
            SetEvent(float(i), LINK, "uplink", {"rate_bps": mbit * 1e6})
            for i, mbit in enumerate(STEPS_MBIT)
        ]
        player = TimelinePlayer(events, self.control)
        player.start()
        t0 = time.monotonic() - player.elapsed()
        marks = receiver.result(seconds + 30)
        sender.result(30)
        player.stop()
        first = marks[0][0]
        for i, mbit in enumerate(STEPS_MBIT):
            # the second after each step, less 0.2 s for TCP to find the new rate
            start, end = t0 + i + 0.2 - first, t0 + i + 1.0 - first
            got = goodput_bps(marks, start, end)
            want = mbit * 1e6 * frac
            self.row(
                f"step {i + 1}: {mbit} Mbit/s",
                f"{got / 1e6:.3f} Mbit/s ({(got / want - 1) * 100:+.2f}%)",
                f"{want / 1e6:.3f} ±10%",
                abs(got / want - 1) <= 0.10,
            )
        stats = player.lateness()
        self.row(
            "timeline lateness",
            f"median {stats['median_ms']:.3f} ms, max {stats['max_ms']:.3f} ms",
            "< 5 ms",
            stats["max_ms"] < 5,
        )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples, shorter runs")
    parser.add_argument(
        "--only", choices=["delay", "jitter", "goodput", "loss", "steps"], action="append"
    )
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("bench_links needs root (network namespaces)", file=sys.stderr)
        return 2
    load = os.getloadavg()
    started = time.monotonic()
    with build(example_scenario(1, 1), mode="run") as net:
        print(
            f"link fidelity on backend {net.backend_text()}; "
            f"load average {load[0]:.2f} on {os.cpu_count()} cores"
        )
        bench = Bench(net, args.quick)
        for part in args.only or ["delay", "jitter", "goodput", "loss", "steps"]:
            getattr(bench, part)()
    print(f"done in {time.monotonic() - started:.0f} s; {bench.misses} figure(s) off target")
    return 0 if not bench.misses else 1


if __name__ == "__main__":
    sys.exit(main())
