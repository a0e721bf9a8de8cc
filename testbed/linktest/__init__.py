"""Link self-test: measure what every link of a built network really does and compare it with
its profile.

    with build(scenario, mode="run") as net:
        report = LinkTest(net, quick=True).run()
    print(report.table()); report.ok

Per link: the RTT (median, p99) of a UDP echo. Per direction: one-way delay (median, p99,
jitter sd) of sparse stamped datagrams, and the same with the direction made neutral for a
moment (the *baseline*: what the path costs with no emulated delay); loss over >= 10,000
datagrams; TCP goodput; UDP goodput at 1.2x the configured rate. Senders and receivers are
forked processes that step into the namespaces (`in_namespace`), so the link, not one
interpreter's GIL, is what is measured; both ends share the host's monotonic clock, so a
datagram's send stamp gives its one-way delay exactly.

Verdicts (SPEC §7): delay median within `DELAY_TOL_S` of configured + baseline; rate within
`RATE_TOL` of configured x payload fraction (TCP 1448, UDP 1472 bytes of payload per 1500-byte
IP packet, plus 14 bytes of Ethernet header on the tc backend's veth), judged on TCP when the
direction has no random loss (TCP backs off on loss, so its goodput then says nothing about the
rate) and on UDP otherwise; loss within `LOSS_TOL` of the profile's expected loss. The report
also says how busy the host's CPUs were meanwhile (`testbed.hostload`): on a loaded host a link
misses its rate because its relay and endpoints wait for a CPU, not because it is wrong.

The measurement functions (`udp_send`, `udp_receive`, `tcp_send`, `tcp_receive`,
`in_namespace`) are shared with the benchmarks (tests/bench/bench_relay.py, bench_links.py).
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import os
import socket
import statistics
import struct
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from netem.netns import netns_path
from netem.profile import LinkProfile
from nodes.recording import linktable
from testbed.connectivity import echo_rtts
from testbed.errors import BadInput, TestbedError
from testbed.hostload import CpuLoad, CpuSample, TimerFloor, cpu_load_between, timer_floor
from testbed.links import DIRECTIONS, Direction, LinkController, neutral
from testbed.namespaces import inside

if TYPE_CHECKING:
    from netem.nr import DelayOracle, Grid, Radio
    from testbed.topology import Link, Net, Node

STAMP = struct.Struct("!dI")  # send time (monotonic), sequence number
CTX = mp.get_context("fork")
PORT = 9100
DELAY_TOL_S = 0.0005
#: A radio direction's delay distribution may be this far from the oracle (Wasserstein-1),
#: the sum of two parts (W1 obeys the triangle inequality). The host's: the relay's timer
#: lateness and the receiving stack add ~0.1-0.3 ms here, so RADIO_TOL_S, or RADIO_TOL_MARGIN_S
#: over the 99th percentile of this host's timed wake-ups (measured at the start of the test,
#: `hostload.timer_floor`, and printed) or over the baseline probes' mean deviation from their
#: median, where either is larger (`LinkTest.host_tolerance_s`). The probes': a finite sample
#: of the oracle itself is this far from it, by chance; its 99th percentile over
#: SAMPLING_DRAWS draws of as many probes (`sampling_chance`; `testbed link-test` prints it:
#: 0.757 ms for 100 probes of OAI's uplink, whose 10% HARQ tail is 5 ms away).
RADIO_TOL_S = 0.0003
RADIO_TOL_MARGIN_S = 0.00025
SAMPLING_DRAWS = 400
#: Probabilities at which a radio direction's measured and closed-form CDFs are kept.
CDF_QUANTILES = tuple(k / 100 for k in range(1, 100))
#: A measured HARQ share may be this many binomial standard deviations from the BLER (4:
#: a false alarm once in ~16,000 directions).
HARQ_SIGMAS = 4.0
#: Below this many transport blocks the HARQ shares are printed but not judged.
HARQ_MIN_BLOCKS = 200
#: Spacing of a radio direction's delay probes, in grid periods, beyond the oracle's 99th
#: percentile: not a whole number, so their phases cover the period, and more than one
#: retransmission's delay on a 5 ms pattern, so a probe held up by HARQ seldom holds up the
#: next (PDCP's in-order delivery), and each finds the UE idle (no grant of the last probe's
#: to share), as the oracle assumes.
RADIO_PROBE_PERIODS = 2.1373
#: The delay probes' UDP payload, and the IP packet the radio carries.
PROBE_PAYLOAD = 64
PROBE_PACKET = PROBE_PAYLOAD + 28
RATE_TOL = 0.05
LOSS_TOL = 0.005
LOSS_PACKETS = 10_000
TCP_PAYLOAD, UDP_PAYLOAD, IP_PACKET = 1448, 1472, 1500
#: Above this rate the Python UDP sender cannot offer 1.2x the rate; UDP goodput is skipped.
UDP_MAX_BPS = 400e6


# ---- measurement primitives (run inside a namespace) ---------------------------------------


class Worker:
    """A forked process running one function inside a namespace; `result()` waits for it."""

    def __init__(self, netns: str, fn: Any, *args: Any, nice: int = -10) -> None:
        self.queue: Any = CTX.Queue()
        self.what = f"{getattr(fn, '__name__', fn)} in {netns}"

        def run() -> None:
            # Endpoints get the relay's priority: on a shared 2-core host an endpoint that
            # waits for a CPU would be measured as link delay.
            with contextlib.suppress(OSError):
                os.nice(nice)
            try:
                with inside(netns_path(netns)):
                    self.queue.put(("ok", fn(*args)))
            except BaseException as err:  # reported to the parent, never lost
                self.queue.put(("error", f"{type(err).__name__}: {err}"))

        self.proc = CTX.Process(target=run, daemon=True)
        self.proc.start()

    def result(self, timeout_s: float = 60.0) -> Any:
        try:
            status, value = self.queue.get(timeout=timeout_s)
        except Exception:
            self.proc.kill()
            raise TestbedError(
                f"a measurement process ({self.what}) gave no result in {timeout_s:.0f} s"
            ) from None
        finally:
            self.proc.join(5)
        if status != "ok":
            raise TestbedError(f"a measurement process ({self.what}) failed: {value}")
        return value


def in_namespace(netns: str, fn: Any, *args: Any) -> Worker:
    """Start `fn(*args)` in a forked process inside namespace `netns` (a name in /run/netns)."""
    return Worker(netns, fn, *args)


def udp_receive(
    ready: Any, addr: str, port: int, duration_s: float, idle_s: float = 0.0
) -> list[tuple[float, float, int, int]]:
    """(receive time, send stamp, sequence, size) of each datagram, for up to `duration_s`;
    with `idle_s`, also stop once nothing has come for that long after the first datagram."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind((addr, port))
    sock.settimeout(0.05)
    ready.set()
    out: list[tuple[float, float, int, int]] = []
    end = time.monotonic() + duration_s
    buf = bytearray(65535)
    last = 0.0
    while (now := time.monotonic()) < end:
        if idle_s and out and now - last > idle_s:
            break
        try:
            n = sock.recv_into(buf)
        except TimeoutError:
            continue
        last = time.monotonic()
        sent, seq = STAMP.unpack_from(buf)
        out.append((last, sent, seq, n))
    sock.close()
    return out


#: getsockopt(IPPROTO_IP, IP_MTU) on a connected socket: the MTU of its route (linux/in.h).
IP_MTU = 14


def route_mtu(addr: str) -> int:
    """The MTU of this namespace's route to `addr` (a UE's air interface: 1456, room for
    GTP-U on N3)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect((addr, PORT))
        return int(sock.getsockopt(socket.IPPROTO_IP, IP_MTU))


def udp_send(addr: str, port: int, count: int, size: int, rate_bps: float) -> int:
    """Send `count` stamped datagrams of `size` bytes, paced at `rate_bps` of UDP payload."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    pad = bytes(max(0, size - STAMP.size))
    t0 = time.monotonic()
    for seq in range(count):
        due = t0 + seq * size * 8 / rate_bps
        wait = due - time.monotonic()
        if wait > 0.0005:
            time.sleep(wait)
        # A full local queue loses the datagram, as on a real host; it counts as lost.
        with contextlib.suppress(OSError):
            sock.sendto(STAMP.pack(time.monotonic(), seq) + pad, (addr, port))
    sock.close()
    return count


def tcp_receive(ready: Any, addr: str, port: int, duration_s: float) -> list[tuple[float, int]]:
    """(time, bytes so far) after each recv, for `duration_s` after the connection opens."""
    server = socket.create_server((addr, port))
    server.settimeout(10)
    ready.set()
    conn, _ = server.accept()
    conn.settimeout(1.0)
    buf = bytearray(1 << 20)
    marks: list[tuple[float, int]] = []
    total = 0
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        try:
            n = conn.recv_into(buf)
        except TimeoutError:
            continue
        if n == 0:
            break
        total += n
        marks.append((time.monotonic(), total))
    conn.close()
    server.close()
    return marks


def tcp_send(addr: str, port: int, duration_s: float) -> int:
    """Send as fast as TCP lets us for `duration_s`; returns the bytes sent."""
    sock = socket.create_connection((addr, port), timeout=5)
    chunk = bytes(1 << 20)
    end = time.monotonic() + duration_s
    sent = 0
    with contextlib.suppress(OSError):
        while time.monotonic() < end:
            sent += sock.send(chunk)
    sock.close()
    return sent


def goodput_bps(marks: list[tuple[float, int]], start_s: float, end_s: float) -> float:
    """Goodput between `start_s` and `end_s` after the first mark, from (time, total) marks."""
    if not marks:
        return 0.0
    first = marks[0][0]
    window = [m for m in marks if first + start_s <= m[0] <= first + end_s]
    if len(window) < 2 or window[-1][0] <= window[0][0]:
        return 0.0
    return (window[-1][1] - window[0][1]) * 8 / (window[-1][0] - window[0][0])


def udp_stream(
    src_ns: str, dst_ns: str, addr: str, count: int, size: int, rate_bps: float, tail_s: float
) -> list[tuple[float, float, int, int]]:
    """Send `count` datagrams src -> dst and return what arrived (see `udp_receive`)."""
    ready = CTX.Event()
    duration = count * size * 8 / rate_bps
    receiver = in_namespace(dst_ns, udp_receive, ready, addr, PORT, duration + tail_s + 2, tail_s)
    if not ready.wait(5):
        raise TestbedError(f"the UDP receiver in {dst_ns} did not start")
    in_namespace(src_ns, udp_send, addr, PORT, count, size, rate_bps).result(duration + 30)
    return receiver.result(duration + tail_s + 30)


def tcp_goodput(src_ns: str, dst_ns: str, addr: str, seconds: float, warm_s: float) -> float:
    """Steady-state TCP goodput src -> dst (bit/s), skipping the first `warm_s`."""
    ready = CTX.Event()
    receiver = in_namespace(dst_ns, tcp_receive, ready, addr, PORT, seconds + 0.5)
    if not ready.wait(5):
        raise TestbedError(f"the TCP receiver in {dst_ns} did not start")
    sender = in_namespace(src_ns, tcp_send, addr, PORT, seconds)
    marks = receiver.result(seconds + 30)
    sender.result(30)
    return goodput_bps(marks, warm_s, seconds - 0.05)


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]


# ---- verdicts ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Verdict:
    """One compared figure: what was measured, what the profile says, and the tolerance."""

    what: str
    measured: float
    expected: float
    tolerance: str
    ok: bool


@dataclass
class DirectionResult:
    """What one direction of a link did (delays in ms, rates in Mbit/s, loss in %)."""

    link: str
    direction: Direction
    src: str
    dst: str
    profile: dict[str, Any]
    baseline_ms: float | None = None
    owd_median_ms: float | None = None
    owd_p99_ms: float | None = None
    jitter_sd_ms: float | None = None
    loss_pct: float | None = None
    loss_packets: int = 0
    tcp_mbit: float | None = None
    udp_mbit: float | None = None
    #: A radio direction's figures (`oracle_comparison`, `harq_shares`, `slot_goodput`).
    radio: dict[str, Any] | None = None
    verdicts: list[Verdict] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(v.ok for v in self.verdicts)


@dataclass
class LinkResult:
    link: str
    rtt_median_ms: float | None
    rtt_p99_ms: float | None
    directions: list[DirectionResult]

    @property
    def ok(self) -> bool:
        return self.rtt_median_ms is not None and all(d.ok for d in self.directions)


@dataclass
class LinkTestReport:
    """Every link's figures and verdicts; `ok` when all are within tolerance."""

    backend: str
    quick: bool
    links: list[LinkResult]
    seconds: float = 0.0
    host_cpu: CpuLoad | None = None  # the host's CPUs over the test (None: not measured)
    #: The links' rates against the host's data plane beforehand (`CapacityCheck.to_dict`;
    #: None: not checked).
    capacity: dict[str, Any] | None = None
    #: How late this host's timed wake-ups were (measured when a link has a radio).
    timer: TimerFloor | None = None

    @property
    def ok(self) -> bool:
        return bool(self.links) and all(link.ok for link in self.links)

    def to_dict(self) -> dict[str, Any]:
        return {
            "backend": self.backend,
            "quick": self.quick,
            "ok": self.ok,
            "seconds": self.seconds,
            "host_cpu": None if self.host_cpu is None else self.host_cpu.to_dict(),
            "capacity": self.capacity,
            "timer_floor": None if self.timer is None else self.timer.to_dict(),
            "tolerances": {
                "delay_ms": DELAY_TOL_S * 1000,
                "rate_fraction": RATE_TOL,
                "loss_pp": LOSS_TOL * 100,
            },
            "links": [
                {
                    **asdict(link),
                    "ok": link.ok,
                    "directions": [_dir_dict(d) for d in link.directions],
                }
                for link in self.links
            ],
        }

    def text(self) -> str:
        """The table (`nodes.recording.linktable`, the columns the report prints too)."""
        data = self.to_dict()
        lines = [linktable.text(data), *linktable.radio_lines(data)]
        if self.host_cpu is not None:
            lines.append(f"host during the test: {self.host_cpu.text()}")
        return "\n".join(lines)

    def warning(self) -> str:
        """The line `testbed run` prints when a link is out of tolerance: with the host's load,
        since a busy host is the usual reason a link misses its rate."""
        text = "warning: a link is out of tolerance (see linktest.json)"
        if self.host_cpu is None:
            return text
        return f"{text}; the host meanwhile: {self.host_cpu.text()}"


def _cpu_sample() -> CpuSample | None:
    try:
        return CpuSample.read()
    except (OSError, ValueError):  # no /proc/stat (a container without procfs): no figure
        return None


def _dir_dict(d: DirectionResult) -> dict[str, Any]:
    return {**asdict(d), "ok": d.ok}


def _profile_summary(p: LinkProfile) -> dict[str, Any]:
    return {
        "rate_mbit": None if p.rate_bps is None else p.rate_bps / 1e6,
        "delay_ms": p.delay_s * 1000,
        "jitter_ms": p.jitter_s * 1000,
        "loss_pct": p.expected_loss * 100,
    }


# ---- the test --------------------------------------------------------------------------------


def check_link_names(known: Sequence[str], links: Sequence[str] | None, where: str) -> None:
    """Raise BadInput naming each of `links` that is not one of `known` (the links of
    `where`), and those it has."""
    unknown = [n for n in links or () if n not in known]
    if unknown:
        raise BadInput(
            f"no link {', '.join(map(repr, unknown))} in {where}; its links: {', '.join(known)}"
        )


class LinkTest:
    """Measures every link of `net` (built with emulated links), or the `links` named, against
    its profile."""

    def __init__(
        self,
        net: Net,
        quick: bool = False,
        progress: Any = None,
        links: Sequence[str] | None = None,
    ) -> None:
        if net.control is None:
            raise TestbedError("the link self-test needs a network built with emulated links")
        check_link_names(list(net.links), links, "this network")
        self.net = net
        self.links = [net.links[n] for n in net.links if links is None or n in links]
        self.control: LinkController = net.control
        self.quick = quick
        self.progress = progress or (lambda _line: None)
        self.timer: TimerFloor | None = None  # measured before the first radio direction

    def host_tolerance_s(self, netns: str, base_ms: list[float]) -> float:
        """The host's part of a radio direction's W1 tolerance (see RADIO_TOL_S).

        `base_ms` are the direction's baseline one-way delays, taken just before at the
        probes' spacing with the link neutral: their mean distance from their median is the
        most the host's own noise can move the measured distribution (W1(X + N, X) <= E|N|),
        and on a noisy host it is what the timed wake-ups at the start missed (CI's 2-vCPU
        VM once measured W1 1.61 ms against a 1.56 ms bound from a calm timer floor).
        """
        if self.timer is None:
            self.timer = in_namespace(netns, timer_floor).result()
        spread_s = 0.0
        if base_ms:
            mid = statistics.median(base_ms)
            spread_s = statistics.fmean(abs(x - mid) for x in base_ms) / 1000
        return max(RADIO_TOL_S, RADIO_TOL_MARGIN_S + max(self.timer.p99_s, spread_s))

    def run(self) -> LinkTestReport:
        t0 = time.monotonic()
        cpu0 = _cpu_sample()
        results = []
        for link in self.links:
            self.progress(f"link test: {link.name}")
            results.append(self.link(link))
            self._check_alive()
        cpu1 = _cpu_sample()
        load = cpu_load_between(cpu0, cpu1) if cpu0 is not None and cpu1 is not None else None
        backend = self.net.backend_text()
        report = LinkTestReport(backend, self.quick, results, time.monotonic() - t0, load)
        report.timer = self.timer
        return report

    def _check_alive(self) -> None:
        failure = self.control.failure()
        if failure:
            raise TestbedError(f"a link failed during the link self-test: {failure}")

    def link(self, link: Link) -> LinkResult:
        rtts = self.rtt(link.lower, link.upper, 30 if self.quick else 200)
        directions = [self.direction(link, d) for d in DIRECTIONS]
        return LinkResult(
            link.name,
            statistics.median(rtts) if rtts else None,
            percentile(rtts, 0.99) if rtts else None,
            directions,
        )

    def rtt(self, src: Node, dst: Node, count: int) -> list[float]:
        """RTTs (ms) of a UDP echo src -> dst, one datagram at a time."""
        return echo_rtts(src, dst, str(dst.address_towards(src.name)), count=count, port=PORT)

    def direction(self, link: Link, direction: Direction) -> DirectionResult:
        src, dst = (link.lower, link.upper) if direction == "uplink" else (link.upper, link.lower)
        addr = str(dst.address_towards(src.name))
        profile = self.control.profile(link.name, direction)
        result = DirectionResult(
            link.name, direction, src.name, dst.name, _profile_summary(profile)
        )
        tail = profile.delay_s + 4 * profile.jitter_s + 0.3

        def owd_ms(count: int, rate_pps: float) -> list[float]:
            bps = rate_pps * PROBE_PAYLOAD * 8
            got = udp_stream(src.netns, dst.netns, addr, count, PROBE_PAYLOAD, bps, tail)
            return [(r - s) * 1000 for r, s, _, _ in got]

        # Baseline: the same probe with this direction neutral for a moment. A radio's probes
        # are sparse, and a host that idles between packets wakes later (~0.2 ms more here at
        # 10 ms than at 2 ms): its baseline is taken at the same spacing.
        radio = profile.radio
        oracle = None
        base_pps = 500.0
        if radio is not None:
            oracle = radio.oracle(direction, size_bytes=PROBE_PACKET)
            period = radio.grid(direction).period_s
            periods = math.ceil(oracle.quantile(0.99) / period) + RADIO_PROBE_PERIODS
            base_pps = 1 / (periods * period)
        with neutral(self.control, link.name, direction):
            base = owd_ms(100 if self.quick else 300, base_pps)
        # Sparse datagrams (5 ms apart): a link that keeps order must not hold one back
        # behind its predecessor's jitter, or the median would measure the clamping. Enough
        # of them that the median's standard error (1.25 sd / sqrt(n)) stays near 0.15 ms
        # (0.1 ms in a full test) when the profile jitters.
        jitter_ms = profile.jitter_s * 1000
        low, per_sd, high = (100, 8.4, 600) if self.quick else (300, 12.5, 1500)
        count = int(min(high, max(low, (per_sd * jitter_ms) ** 2)))
        # A radio's probes, a whole number and 0.1373 of its periods apart, land at phases
        # spread evenly over the period (every 5 ms on a 5 ms pattern would see one phase:
        # the aliasing of srsRAN's ping sawtooth), which is what the oracle's uniform
        # arrivals assume.
        owd = owd_ms(count, 200 if radio is None else base_pps)
        if base:
            result.baseline_ms = statistics.median(base)
        if len(owd) >= 2:
            result.owd_median_ms = statistics.median(owd)
            result.owd_p99_ms = percentile(owd, 0.99)
            result.jitter_sd_ms = statistics.stdev(owd)
        chance: Chance | None = None
        if oracle is not None and len(owd) >= 2 and result.baseline_ms is not None:
            # The measured delay distribution beside the closed form, net of the wired delay
            # and of the path without the link.
            net = [x - profile.delay_s * 1000 - result.baseline_ms for x in owd]
            host_ms = self.host_tolerance_s(src.netns, base) * 1000
            chance = sampling_chance(oracle, len(net))
            sampling_ms = chance.w1_s * 1000
            tol_ms = host_ms + sampling_ms
            result.radio = oracle_comparison(net, oracle)
            result.radio.update(
                tolerance_ms=tol_ms, host_tolerance_ms=host_ms, sampling_tolerance_ms=sampling_ms
            )
            w1 = result.radio["w1_ms"]
            result.verdicts.append(
                Verdict("radio W1 ms", w1, 0.0, f"<= {tol_ms:.3g} ms from the oracle", w1 <= tol_ms)
            )
        if result.owd_median_ms is not None and result.baseline_ms is not None:
            want = profile.delay_s * 1000 + result.baseline_ms
            tol_ms = DELAY_TOL_S * 1000
            if oracle is not None:
                # A radio's delays spread over its period and HARQ tail, so the median of a
                # few probes is off the oracle's by chance too.
                want += oracle.quantile(0.5) * 1000
                if chance is not None:
                    tol_ms += chance.median_s * 1000
            result.verdicts.append(
                Verdict(
                    "delay ms",
                    result.owd_median_ms,
                    want,
                    f"±{tol_ms:.3g} ms",
                    abs(result.owd_median_ms - want) <= tol_ms,
                )
            )
        else:
            result.verdicts.append(Verdict("delay ms", float("nan"), 0.0, "no echo", False))
        capped = _radio_capped(profile, direction)
        before = self._radio_counters(link.name, direction) if radio else None
        self.loss(result, capped, src, dst, addr, tail)
        saturated = self._radio_counters(link.name, direction) if radio else None
        self.rate(result, capped, src, dst, addr)
        if radio is not None and before is not None and saturated is not None:
            after = self._radio_counters(link.name, direction)
            if after is not None:
                self._radio_air(result, radio, direction, before, saturated, after)
        return result

    def _radio_counters(self, link: str, direction: Direction) -> dict[str, Any] | None:
        """The radio counters of one direction and its bytes delivered (None: no relay)."""
        counters = self.control.counters(link)
        if not counters or "radio" not in counters.get(direction, {}):
            return None
        snap = counters[direction]
        return {**snap["radio"], "bytes_out": snap["total"]["bytes_out"], "t": time.monotonic()}

    def _radio_air(
        self,
        result: DirectionResult,
        radio: Radio,
        direction: Direction,
        before: dict[str, Any],
        saturated: dict[str, Any],
        after: dict[str, Any],
    ) -> None:
        """HARQ shares over the whole test of this direction, and what a slot carried while
        the rate test saturated it."""
        harq = harq_shares(before, after, radio.bler, radio.max_retx)
        slots = slot_goodput(saturated, after, radio.grid(direction), radio.bler)
        result.radio = {**(result.radio or {}), "harq": harq, "slots": slots}
        if harq["blocks"] >= HARQ_MIN_BLOCKS:
            failed, bound = harq["first_failed"], harq["bound"]
            result.verdicts.append(
                Verdict(
                    "HARQ retx %",
                    failed * 100,
                    radio.bler * 100,
                    f"±{bound * 100:.2g} pp ({HARQ_SIGMAS:g} sigma, {harq['blocks']} blocks)",
                    abs(failed - radio.bler) <= bound,
                )
            )

    def loss(
        self,
        result: DirectionResult,
        profile: LinkProfile,
        src: Node,
        dst: Node,
        addr: str,
        tail_s: float,
    ) -> None:
        wire = (64 + 28 + self.control.frame_overhead) * 8
        pps = 20_000.0
        if profile.rate_bps is not None:
            pps = min(pps, 0.4 * profile.rate_bps / wire)  # well below the rate: no queue drops
        if profile.queue_packets is not None:
            # and the delay line must stay well inside the queue limit
            line_s = profile.delay_s + 3 * profile.jitter_s + 0.001
            pps = min(pps, 0.25 * profile.queue_packets / line_s)
        got = udp_stream(src.netns, dst.netns, addr, LOSS_PACKETS, 64, pps * 64 * 8, tail_s)
        lost = 1 - len({seq for _, _, seq, _ in got}) / LOSS_PACKETS
        result.loss_pct, result.loss_packets = lost * 100, LOSS_PACKETS
        want = profile.expected_loss
        result.verdicts.append(
            Verdict("loss %", lost * 100, want * 100, "±0.5 pp", abs(lost - want) <= LOSS_TOL)
        )

    def rate(
        self, result: DirectionResult, profile: LinkProfile, src: Node, dst: Node, addr: str
    ) -> None:
        packet = IP_PACKET + self.control.frame_overhead
        seconds = 1.5 if self.quick else 3.0
        lossy = profile.expected_loss > 0
        if not (self.quick and lossy):
            tcp = tcp_goodput(src.netns, dst.netns, addr, seconds, 0.5)
            result.tcp_mbit = tcp / 1e6
            if profile.rate_bps is not None and not lossy:
                want = profile.rate_bps * TCP_PAYLOAD / packet
                result.verdicts.append(_rate_verdict("tcp Mbit/s", tcp, want))
        udp_ok = profile.rate_bps is not None and profile.rate_bps * 1.2 <= UDP_MAX_BPS
        if udp_ok and (lossy or not self.quick):
            assert profile.rate_bps is not None
            # Datagrams that fill the sender's route MTU: one a UE (MTU 1456) sized for 1500
            # would leave in two IP fragments and measure fragmentation, not the link.
            mtu = min(IP_PACKET, in_namespace(src.netns, route_mtu, addr).result(10))
            payload = mtu - (IP_PACKET - UDP_PAYLOAD)
            want = profile.rate_bps * payload / (mtu + self.control.frame_overhead)
            count = int(1.2 * want * seconds / (payload * 8))
            got = udp_stream(
                src.netns, dst.netns, addr, count, payload, 1.2 * want, profile.delay_s + 0.3
            )
            if got:
                first = got[0][0]
                start, end = first + 0.3, first + seconds - 0.2
                size = sum(n for r, _, _, n in got if start <= r <= end)
                udp = size * 8 / (end - start)
            else:
                udp = 0.0
            result.udp_mbit = udp / 1e6
            result.verdicts.append(_rate_verdict("udp Mbit/s", udp, want))


def oracle_comparison(net_ms: list[float], oracle: DelayOracle) -> dict[str, Any]:
    """Measured one-way delays (ms, net of everything but the radio) against the closed form:
    both CDFs at `CDF_QUANTILES`, the Wasserstein-1 distance (the mean gap between their
    quantile functions) and the Kolmogorov-Smirnov statistic (the largest gap between the
    CDFs)."""
    ordered = sorted(net_ms)
    n = len(ordered)
    w1 = statistics.fmean(
        abs(x - oracle.quantile((i + 0.5) / n) * 1000) for i, x in enumerate(ordered)
    )
    ks = 0.0
    for i, x in enumerate(ordered):
        f = oracle.cdf(x / 1000)
        ks = max(ks, (i + 1) / n - f, f - i / n)
    return {
        "samples": n,
        "w1_ms": w1,
        "ks": ks,
        "quantiles": list(CDF_QUANTILES),
        "measured_ms": [percentile(ordered, q) for q in CDF_QUANTILES],
        "oracle_ms": [oracle.quantile(q) * 1000 for q in CDF_QUANTILES],
    }


@dataclass(frozen=True)
class Chance:
    """How far `n` delays drawn from an oracle fall from it by chance (seconds): the 99th
    percentile over SAMPLING_DRAWS draws of their Wasserstein-1 distance from it, and of
    their median's distance from its median."""

    w1_s: float
    median_s: float


def sampling_chance(oracle: DelayOracle, n: int, q: float = 0.99, seed: int = 0) -> Chance:
    """`Chance` of `n` probes of `oracle`. W1 is the area between the CDFs, integrated on a
    fine grid; the oracle's pieces are uniform, so a draw picks a piece by its mass and a
    point in it."""
    pieces = np.array([p for p in oracle.pieces if p[2] > 0 and p[1] > p[0]])
    low, high, weight = pieces[:, 0], pieces[:, 1], pieces[:, 2]
    mass = (high - low) * weight
    mass /= mass.sum()
    xs = np.linspace(low.min(), high.max(), 4001)
    cdf = (np.clip(xs[:, None] - low, 0.0, high - low) * weight).sum(axis=1)
    cdf /= cdf[-1]
    median = oracle.quantile(0.5)
    rng = np.random.default_rng(seed)
    distances, medians = [], []
    for _ in range(SAMPLING_DRAWS):
        k = rng.choice(len(mass), size=n, p=mass)
        drawn = np.sort(low[k] + rng.random(n) * (high[k] - low[k]))
        empirical = np.searchsorted(drawn, xs, side="right") / n
        distances.append(np.abs(empirical - cdf).sum() * (xs[1] - xs[0]))
        medians.append(abs(float(np.median(drawn)) - median))
    return Chance(float(np.quantile(distances, q)), float(np.quantile(medians, q)))


def _tries_between(before: dict[str, Any], after: dict[str, Any]) -> list[int]:
    """Blocks by the HARQ retransmissions they needed, between two reads of a radio's
    counters (the last entry: given up on after all of them)."""
    was = before["retransmissions"]
    return [a - (was[k] if k < len(was) else 0) for k, a in enumerate(after["retransmissions"])]


def harq_shares(
    before: dict[str, Any], after: dict[str, Any], bler: float, max_retx: int
) -> dict[str, Any]:
    """Transport blocks by the HARQ retransmissions they needed between two reads of a radio's
    counters (the last share: given up on), beside the shares a first-transmission BLER
    implies (retry k: bler^k (1 - bler)); `bound` is HARQ_SIGMAS binomial deviations of the
    share of blocks whose first transmission failed."""
    tries = _tries_between(before, after)
    blocks = sum(tries)
    expected = [bler**k * (1 - bler) for k in range(max_retx + 1)] + [bler ** (max_retx + 1)]
    shares = [t / blocks if blocks else 0.0 for t in tries]
    return {
        "blocks": blocks,
        "shares": shares,
        "expected": expected[: len(shares)],
        "first_failed": 1 - shares[0] if blocks else 0.0,
        "bound": HARQ_SIGMAS * math.sqrt(bler * (1 - bler) / max(blocks, 1)) + 1 / max(blocks, 1),
    }


def slot_goodput(
    before: dict[str, Any], after: dict[str, Any], grid: Grid, bler: float
) -> dict[str, Any]:
    """What a slot carried while the rate test saturated the direction.

    A saturated UE fills every occasion it gets with one transport block: a new one or a
    retransmission of an earlier one (which takes the whole occasion, its block being full).
    So the occasions it used are its new blocks plus their retransmissions, and the bytes
    delivered per occasion used should be the mean transport block less the share `bler`
    of them that goes to resends (1 - bler: each new block takes 1 / (1 - bler) tries on
    average). Also: bytes per new block (a whole block), and, from the times of the two
    reads, the share of the direction's occasions in that time the UE used.
    """
    blocks = after["blocks"] - before["blocks"]
    tries = _tries_between(before, after)
    resends = sum(k * t for k, t in enumerate(tries[:-1])) + (len(tries) - 2) * tries[-1]
    used = blocks + resends
    delivered = after["bytes_out"] - before["bytes_out"]
    capacity = statistics.fmean(o.capacity_bytes for o in grid.occasions)
    per_s = len(grid.occasions) / grid.period_s
    seconds = after.get("t", 0.0) - before.get("t", 0.0)
    return {
        "blocks": blocks,
        "occasions": used,
        "bytes_per_occasion": delivered / used if used else None,
        "expected_bytes_per_occasion": capacity * (1 - bler),
        "bytes_per_block": delivered / blocks if blocks else None,
        "block_bytes": capacity,
        "occasions_per_s": per_s,
        "seconds": seconds,
        "used_share": used / (seconds * per_s) if seconds > 0 else None,
    }


def _radio_capped(profile: LinkProfile, direction: Direction) -> LinkProfile:
    """`profile` with the rate its radio's transport blocks allow (IP bytes per second)."""
    if profile.radio is None:
        return profile
    cap = profile.radio.goodput_bps(direction)
    return profile.replace(rate_bps=cap if profile.rate_bps is None else min(cap, profile.rate_bps))


def _rate_verdict(what: str, measured_bps: float, want_bps: float) -> Verdict:
    return Verdict(
        what,
        measured_bps / 1e6,
        want_bps / 1e6,
        f"±{RATE_TOL:.0%}",
        abs(measured_bps / want_bps - 1) <= RATE_TOL,
    )


class CapacityNote(Protocol):
    """A check of the links' rates against the host's data plane, as `link_test` prints and
    reports it (`testbed.capacity.CapacityCheck`; declared here since that module builds on
    this one's traffic helpers)."""

    def lines(self) -> list[str]: ...
    def to_dict(self) -> dict[str, Any]: ...


def link_test(
    scenario: Any,
    quick: bool = False,
    progress: Any = None,
    capacity: CapacityNote | None = None,
    links: Sequence[str] | None = None,
) -> LinkTestReport:
    """`testbed link-test`: print `capacity` (which link rates this host's data plane cannot
    carry; kept in the report), build the scenario's network, measure every link (or the
    `links` named), tear down."""
    from testbed.topology import build

    if capacity is not None and progress is not None:
        for line in capacity.lines():
            progress(line)
    with build(scenario, mode="run") as net:
        assert net.control is not None
        if hasattr(net.control, "watch"):
            net.control.watch()
        report = LinkTest(net, quick=quick, progress=progress, links=links).run()
    report.capacity = None if capacity is None else capacity.to_dict()
    return report
