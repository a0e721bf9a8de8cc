"""The link self-test: every link of a built network measured against its profile.

Per link: the RTT (median, p99) of a UDP echo. Per direction: one-way delay (median, p99,
jitter sd) of sparse stamped datagrams, and the same with the direction made neutral for a
moment (the *baseline*: what the path costs with no emulated delay); loss over >= 10,000
datagrams; TCP goodput; UDP goodput at 1.2x the configured rate. A direction with a radio is
also judged against its delay oracle and its BLER (`testbed.linktest.radio`).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, Protocol

from netem.directions import DIRECTIONS, Direction
from netem.profile import LinkProfile
from testbed.connectivity import echo_rtts
from testbed.errors import BadInput, TestbedError
from testbed.hostload import CpuSample, TimerFloor, cpu_load_between, timer_floor
from testbed.links import LinkController, neutral
from testbed.linktest.measure import (
    IP_PACKET,
    PORT,
    TCP_PAYLOAD,
    UDP_PAYLOAD,
    in_namespace,
    percentile,
    route_mtu,
    tcp_goodput,
    udp_stream,
)
from testbed.linktest.radio import (
    HARQ_MIN_BLOCKS,
    HARQ_SIGMAS,
    RADIO_TOL_MARGIN_S,
    RADIO_TOL_S,
    Chance,
    _radio_capped,
    harq_shares,
    oracle_comparison,
    sampling_chance,
    slot_goodput,
)
from testbed.linktest.report import (
    DELAY_TOL_S,
    LOSS_TOL,
    DirectionResult,
    LinkResult,
    LinkTestReport,
    Verdict,
    _profile_summary,
    _rate_verdict,
)

if TYPE_CHECKING:
    from netem.nr.radio import Radio
    from testbed.topology import Link, Net, Node

#: Spacing of a radio direction's delay probes, in grid periods, beyond the oracle's 99th
#: percentile: not a whole number, so their phases cover the period, and more than one
#: retransmission's delay on a 5 ms pattern, so a probe held up by HARQ seldom holds up the
#: next (PDCP's in-order delivery), and each finds the UE idle (no grant of the last probe's
#: to share), as the oracle assumes.
RADIO_PROBE_PERIODS = 2.1373
#: The delay probes' UDP payload, and the IP packet the radio carries.
PROBE_PAYLOAD = 64
PROBE_PACKET = PROBE_PAYLOAD + 28
LOSS_PACKETS = 10_000
#: Above this rate the Python UDP sender cannot offer 1.2x the rate; UDP goodput is skipped.
UDP_MAX_BPS = 400e6


def _cpu_sample() -> CpuSample | None:
    try:
        return CpuSample.read()
    except (OSError, ValueError):  # no /proc/stat (a container without procfs): no figure
        return None


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
        probed: dict[str, list[DirectionResult]] = {}
        if self.quick and len(self.links) > 1:
            probed = self._delays_together()
        for link in self.links:
            self.progress(f"link test: {link.name}")
            done = probed.get(link.name)
            results.append(self.link(link) if done is None else self.link(link, done))
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

    def _delays_together(self) -> dict[str, list[DirectionResult]]:
        """A quick test's delay probes of every link and direction at once: they are sparse
        (a radio's tens of ms apart, most of its test) and each crosses its own link, so
        together they take the time of the slowest rather than of all in turn. The host's
        timer floor is measured first, alone, as a radio direction's tolerance needs it."""
        names = ", ".join(link.name for link in self.links)
        self.progress(f"link test: the delays of {names}, together")
        radio = next(
            (
                link
                for link in self.links
                if any(self.control.profile(link.name, d).radio for d in DIRECTIONS)
            ),
            None,
        )
        if radio is not None and self.timer is None:
            self.timer = in_namespace(radio.lower.netns, timer_floor).result()
        jobs = [(link, d) for link in self.links for d in DIRECTIONS]
        with ThreadPoolExecutor(len(jobs)) as pool:
            done = list(pool.map(lambda job: self.delays(*job), jobs))
        out: dict[str, list[DirectionResult]] = {}
        for (link, _), result in zip(jobs, done, strict=True):
            out.setdefault(link.name, []).append(result)
        return out

    def link(self, link: Link, probed: list[DirectionResult] | None = None) -> LinkResult:
        """One link: its round trips, each direction's delays (`probed`, where a quick test
        took them together with the other links'), then each direction's loss and rates."""
        rtts = self.rtt(link.lower, link.upper, 30 if self.quick else 200)
        if probed is None and self.quick:
            # The sparse delay probes of the two directions cross different queues (and a
            # radio's different slots), so a quick test sends them together: a radio link's
            # probes, tens of ms apart, are most of its time. Loss and rates, which load the
            # relay, stay one direction at a time.
            with ThreadPoolExecutor(len(DIRECTIONS)) as pool:
                probed = list(pool.map(lambda d: self.delays(link, d), DIRECTIONS))
        elif probed is None:
            probed = [self.delays(link, d) for d in DIRECTIONS]
        directions = [self.throughput(link, result) for result in probed]
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
        """One direction measured whole: its delays, then its loss and rates."""
        return self.throughput(link, self.delays(link, direction))

    def _ends(self, link: Link, direction: Direction) -> tuple[Node, Node, str]:
        src, dst = (link.lower, link.upper) if direction == "uplink" else (link.upper, link.lower)
        return src, dst, str(dst.address_towards(src.name))

    def delays(self, link: Link, direction: Direction) -> DirectionResult:
        """One direction's one-way delays, against its profile (and a radio's oracle)."""
        src, dst, addr = self._ends(link, direction)
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
        return result

    def throughput(self, link: Link, result: DirectionResult) -> DirectionResult:
        """Loss and rates of the direction `result` holds the delays of (and a radio's HARQ
        shares and slot goodput over them)."""
        direction = result.direction
        src, dst, addr = self._ends(link, direction)
        profile = self.control.profile(link.name, direction)
        radio = profile.radio
        tail = profile.delay_s + 4 * profile.jitter_s + 0.3
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
        # A quick test measures TCP where there is a rate to judge it against: an unshaped
        # direction's goodput is the host's, not the profile's (a full test still prints it).
        if not (self.quick and (lossy or profile.rate_bps is None)):
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


class CapacityNote(Protocol):
    """A check of the links' rates against the host's data plane, as `link_test` prints and
    reports it (`testbed.capacity.CapacityCheck`; declared here since that module builds on
    this package's traffic helpers, `testbed.linktest.measure`)."""

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
