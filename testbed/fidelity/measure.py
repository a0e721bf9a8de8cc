"""A case's probes as real packets: two namespaces (a UE and a gNB side), the relay between
them carrying the case's radio in both directions, and stamped UDP datagrams sent on the
probe schedule of `testbed.fidelity.model`.

One-way delays come from the send stamp (both ends share the host's monotonic clock); a round
trip is an echo in the gNB's namespace answering the UE's probe (with the wired path in each
direction of the link, as a cloud server's distance). Namespaces are `elf-<hex>-ue|gnb` and
are removed, with the relay, however the measurement ends.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import socket
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from pyroute2 import netns

from netem.netns import in_netns
from netem.nr.radio import Radio
from netem.profile import LinkProfile
from netem.relay.client import UserspaceLink
from testbed.errors import HostError
from testbed.fidelity.case import Probe
from testbed.fidelity.model import Delays, aligned, profile_of, schedule
from testbed.linktest import CTX, STAMP, in_namespace

UE_ADDR, GNB_ADDR = "10.217.0.1", "10.217.0.2"
PORT = 9300
#: Time for the relay and the receivers to be ready before the first probe.
LEAD_S = 0.5
#: Probes each way of the host's baseline, every BASELINE_INTERVAL_S. The figure depends on how
#: busy the relay is (sparser probes let the CPU reach deeper idle states between packets), and
#: a radio's relay is awake at every slot a packet waits for: a probe every 2 ms is the nearest
#: a plain link comes to that. `testbed fidelity` prints the baseline it took off.
BASELINE_PROBES = 300
BASELINE_INTERVAL_S = 0.002


@contextmanager
def _link(radio: Radio, wired_ms: float, seed: int) -> Iterator[tuple[str, str, UserspaceLink]]:
    tag = secrets.token_hex(3)
    names = [f"elf-{tag}-ue", f"elf-{tag}-gnb"]
    link = None
    try:
        for name in names:
            netns.create(name)
            with in_netns(name):
                # No router solicitations or MLD reports: a stray packet on a new interface
                # asks for a grant that the next probe would find waiting.
                for key in ("all", "default"):
                    with open(f"/proc/sys/net/ipv6/conf/{key}/disable_ipv6", "w") as f:
                        f.write("1")
        profile = profile_of(radio, wired_ms)
        link = UserspaceLink(
            names[0],
            names[1],
            dev_a="nr0",
            dev_b="nr1",
            addr_a=f"{UE_ADDR}/30",
            addr_b=f"{GNB_ADDR}/30",
            uplink=profile,
            downlink=profile,
            seed=seed,
            name="fidelity",
        )
        link.start()
        yield names[0], names[1], link
    finally:
        if link is not None:
            link.close()
        for name in names:
            if name in netns.listnetns():
                netns.remove(name)


#: The last stretch before a send is waited out by spinning: a sleep wakes 0.05-0.1 ms late,
#: and a probe whose phase against the slot grid matters must not drift past a slot's start.
SPIN_S = 0.0005


def _until(t: float) -> None:
    """Return at monotonic `t` (sleep, then spin the last SPIN_S)."""
    wait = t - time.monotonic() - SPIN_S
    if wait > 0:
        time.sleep(wait)
    while time.monotonic() < t:
        pass


def _send(addr: str, port: int, sends: list[float], size: int, start: float) -> int:
    """Send a stamped datagram at each of `sends` (s after monotonic `start`)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        pad = bytes(max(0, size - STAMP.size))
        for seq, at in enumerate(sends):
            _until(start + at)
            with contextlib.suppress(OSError):
                sock.sendto(STAMP.pack(time.monotonic(), seq) + pad, (addr, port))
    return len(sends)


def _bound(addr: str, port: int, ready: Any) -> socket.socket:
    """A UDP socket on addr:port that wakes every 50 ms to check the time; `ready` set."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind((addr, port))
    sock.settimeout(0.05)
    ready.set()
    return sock


def _receive(ready: Any, addr: str, port: int, until: float) -> dict[int, float]:
    """Each datagram's one-way delay (ms) by sequence number, until monotonic `until`."""
    out: dict[int, float] = {}
    with _bound(addr, port, ready) as sock:
        buf = bytearray(2048)
        while time.monotonic() < until:
            try:
                sock.recv_into(buf)
            except TimeoutError:
                continue
            now = time.monotonic()
            sent, seq = STAMP.unpack_from(buf)
            out[seq] = (now - sent) * 1000.0
    return out


def _echo(ready: Any, addr: str, port: int, until: float) -> int:
    """Send every datagram back where it came from, until monotonic `until`."""
    n = 0
    with _bound(addr, port, ready) as sock:
        buf = bytearray(2048)
        while time.monotonic() < until:
            try:
                size, peer = sock.recvfrom_into(buf)
            except TimeoutError:
                continue
            sock.sendto(buf[:size], peer)
            n += 1
    return n


def _ping(addr: str, port: int, sends: list[float], size: int, start: float, until: float) -> dict:
    """Send on the schedule and take the echoes: each probe's round trip (ms) by sequence."""
    out: dict[int, float] = {}
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setblocking(False)
        pad = bytes(max(0, size - STAMP.size))
        buf = bytearray(2048)
        k = 0
        while (now := time.monotonic()) < until:
            while k < len(sends) and now >= start + sends[k]:
                with contextlib.suppress(OSError):
                    sock.sendto(STAMP.pack(time.monotonic(), k) + pad, (addr, port))
                k += 1
            with contextlib.suppress(BlockingIOError):
                while True:
                    sock.recv_into(buf)
                    sent, seq = STAMP.unpack_from(buf)
                    out[seq] = (time.monotonic() - sent) * 1000.0
            due = start + sends[k] if k < len(sends) else until
            time.sleep(max(0.0, min(0.0002, due - time.monotonic())))
    return out


def _one_way(
    ue: str,
    gnb: str,
    measures: list[str],
    sends: list[float],
    size: int,
    period_s: float,
    early_ms: dict[str, float] | None = None,
) -> dict[str, list[float | None]]:
    """Each measure's one-way delays (ms, in send order) of probes sent on `sends` (s after
    a boundary of the slot grid's `period_s`: the relay's grid starts at 0 on this clock),
    each measure's `early_ms` sooner: the host's own delay before a packet reaches the radio,
    so that it reaches the UE's MAC at the probe's phase."""
    span = (sends[-1] if sends else 0.0) + 1.0
    start = aligned(time.monotonic() + LEAD_S, period_s)
    until = start + span
    receivers, senders = {}, []
    ends = {"uplink": (gnb, GNB_ADDR, ue), "downlink": (ue, UE_ADDR, gnb)}
    for i, measure in enumerate(measures):
        at, addr, sender = ends[measure]
        ready = CTX.Event()
        receivers[measure] = in_namespace(at, _receive, ready, addr, PORT + i, until)
        ready.wait(5)
        early = (early_ms or {}).get(measure, 0.0) / 1000.0
        senders.append(in_namespace(sender, _send, addr, PORT + i, sends, size, start - early))
    for sender in senders:
        sender.result(span + 30)
    out = {}
    for measure, receiver in receivers.items():
        got = receiver.result(span + 30)
        out[measure] = [got.get(k) for k in range(len(sends))]
    return out


def _radio_counters(link: UserspaceLink, direction: str) -> dict[str, Any]:
    counters = link.counters().get(direction, {})
    return dict(counters.get("radio", {}))


def host_baseline(ue: str, gnb: str, link: UserspaceLink, count: int = BASELINE_PROBES) -> dict:
    """The median one-way delay (ms) of this host's relay with no radio and no delay, each
    way: what the emulator itself adds (timers, TUN devices, sockets), not the model."""
    plain = LinkProfile(queue_packets=10_000)
    saved = dict(link.profiles)
    for direction in ("uplink", "downlink"):
        link.set(direction, plain)  # type: ignore[arg-type]
    sends = [k * BASELINE_INTERVAL_S for k in range(count)]
    got = _one_way(ue, gnb, ["uplink", "downlink"], sends, 100, BASELINE_INTERVAL_S)
    for direction, profile in saved.items():
        link.set(direction, profile)  # type: ignore[arg-type]
    out = {}
    for direction, ms in got.items():
        delivered = sorted(d for d in ms if d is not None)
        out[direction] = delivered[len(delivered) // 2] if delivered else 0.0
    return out


def measure_delays(
    radio: Radio,
    probe: Probe,
    wired_ms: float = 0.0,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Delays]:
    """Every measure of `probe` through the relay, net of the host's baseline (measured first,
    printed, subtracted): the one-way directions at once (each its own socket pair), then the
    round trip on its own (an echo would put the uplink's probes on the downlink too)."""
    if os.geteuid() != 0:
        raise HostError("testbed fidelity needs root (network namespaces and TUN devices)")
    sends = schedule(probe, radio.pattern().period_s, seed)
    span = (sends[-1] if sends else 0.0) + 1.0
    out: dict[str, Delays] = {}
    one_way = [m for m in probe.measures if m != "rtt"]
    with _link(radio, wired_ms, seed) as (ue, gnb, link):
        base = host_baseline(ue, gnb, link)
        if progress:
            progress(
                f"    host baseline (the relay with no radio), subtracted: uplink "
                f"{base['uplink']:.3f} ms, downlink {base['downlink']:.3f} ms"
            )
        if one_way:
            if progress:
                progress(f"    {len(sends)} probes each way over {span:.0f} s")
            period = radio.pattern().period_s
            got = _one_way(ue, gnb, one_way, sends, probe.size, period, base)
            for measure, ms in got.items():
                net = [None if d is None else d - base[measure] for d in ms]
                out[measure] = Delays(net, _radio_counters(link, measure), base[measure])
        if "rtt" in probe.measures:
            ready = CTX.Event()
            start = aligned(time.monotonic() + LEAD_S, radio.pattern().period_s)
            until = start + span
            echo = in_namespace(gnb, _echo, ready, GNB_ADDR, PORT + 9, until + 0.5)
            ready.wait(5)
            if progress:
                progress(f"    {len(sends)} echoes over {span:.0f} s")
            early = base["uplink"] / 1000.0  # (as the one-way probes)
            got_rtt = in_namespace(
                ue, _ping, GNB_ADDR, PORT + 9, sends, probe.size, start - early, until
            ).result(span + 30)
            echo.result(span + 30)
            both = base["uplink"] + base["downlink"]
            ms = [got_rtt.get(k) for k in range(len(sends))]
            net = [None if d is None else d - both for d in ms]
            counters = {d: _radio_counters(link, d) for d in ("uplink", "downlink")}
            out["rtt"] = Delays(net, counters, both)
    return out
