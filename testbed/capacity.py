"""Can this host emulate a scenario's links? The userspace data plane's capacity, measured once,
against every link direction's rate, checked before a run rather than found out after it.

    plane = host_data_plane(progress=print)     # cached for a day per host and netem/ code
    for warning in check_links(scenario, plane):
        print(warning.text())

The relay (`netem.relay`) is one Python process per link. Through one direction it carries TCP
as TUN super-packets (`netem.gso`) at several Gbit/s, but whatever it must handle one wire
packet at a time (UDP datagrams sent without UDP GSO, as ROS 2 DDS sends them; every packet of
a direction replaying a bandwidth trace) costs it the same per packet whatever its size: tens
of thousands of packets per second. So a rate above the first figure is never reached (the
relay, not the link, sets it), one above the second only by traffic the kernel hands over in
super-packets. The tc backend's links are kernel qdiscs and none of this applies to them.

`measure_data_plane` finds both figures on this host: two throwaway namespaces
(`elchk-<hex>-a`/`-b`, the prefix of `testbed check`'s sandboxes, so `testbed clean` removes
what a SIGKILL left) joined by one unshaped `UserspaceLink`; about a second of TCP goodput,
then about a second of a flood of 1472-byte datagrams. Its `DataPlane` is kept in the state
dir (`CACHE_FILE`) and reused for `MAX_AGE_S` by `host_data_plane` while the kernel release,
the CPU count, the Python version and the netem/ sources stay the same.

Rates are compared as the link counts them (the relay counts IP packets): a TCP goodput `g`
is a link rate of `g x 1500 / 1448`, and `n` datagrams/s are `n x 1500 x 8` bit/s.

How the figures are used: `testbed validate --host FILE` warns per link direction, an error
when a rate is above what the relay carries even for TCP, a note when it is above the
one-packet-at-a-time figure (plain UDP faster than that is limited by the relay, not the link).
`testbed link-test` and `testbed run` print the same check before they start; it never fails a
run, and `testbed run --no-capacity-check` skips it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import platform
import secrets
import socket
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import netem
from netem.directions import DIRECTIONS, directions
from netem.netns import delete_netns
from netem.relay.client import UserspaceLink
from netem.traces import load_trace
from nodes.recording.jsonfile import write_json
from testbed import links as lk
from testbed import state as st
from testbed.check.sandbox import PROBE_PREFIX
from testbed.errors import TestbedError
from testbed.linktest import (
    CTX,
    IP_PACKET,
    PORT,
    STAMP,
    TCP_PAYLOAD,
    UDP_PAYLOAD,
    Worker,
    goodput_bps,
    in_namespace,
    tcp_receive,
    tcp_send,
    udp_receive,
)
from testbed.namespaces import Netns, require_root
from testbed.scenario.model import Links, LinkSpec, Scenario, SetEvent, TraceEvent
from testbed.units import format_rate

Progress = Callable[[str], None]
Level = Literal["error", "note"]

#: In the state dir: the last measurement (`DataPlane.to_dict`).
CACHE_FILE = "data-plane.json"
#: A cached figure older than this is measured again (a host's load and firmware change).
MAX_AGE_S = 24 * 3600.0
#: Seconds of each measurement, after `WARM_S` of ramp-up (TCP's slow start, the first
#: datagrams of a flood before the TUN queue is full).
MEASURE_S = 1.0
WARM_S = 0.3
ADDR_A, ADDR_B = "10.215.0.1", "10.215.0.2"  # inside the throwaway namespaces only


# ---- the host's figures ----------------------------------------------------------------------


def netem_sources_hash() -> str:
    """A hash of netem/*.py: a change to the data plane's code makes a cached figure stale."""
    digest = hashlib.sha256()
    for path in sorted(Path(netem.__file__).resolve().parent.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def usable_cpus() -> int:
    """The CPUs this process may run on (an affinity mask or a cpuset can hide some)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def host_key() -> dict[str, Any]:
    """What a cached figure must match to be reused on this host."""
    return {
        "kernel": platform.release(),
        "cpus": usable_cpus(),
        "python": platform.python_version(),
        "netem_hash": netem_sources_hash(),
    }


@dataclass(frozen=True)
class DataPlane:
    """What this host's userspace data plane sustains through one link direction.

    `tcp_bps`: TCP goodput through an unshaped, offloaded direction (super-packets).
    `datagram_pps`: MTU-sized (1472-byte payload) datagrams per second it delivers when
    flooded, one packet at a time; `datagram_bps` is that as a link rate (1500-byte packets).
    `measured_at` is a Unix time, `seconds` how long measuring took; the rest is the host key.
    `cached` says whether it was read from the state dir rather than measured by this process.
    """

    tcp_bps: float
    datagram_pps: float
    datagram_bps: float
    measured_at: float
    seconds: float
    kernel: str
    cpus: int
    python: str
    netem_hash: str
    cached: bool = field(default=False, compare=False)

    @property
    def tcp_link_bps(self) -> float:
        """The link rate at which TCP's goodput would be `tcp_bps` (what a rate compares with)."""
        return self.tcp_bps * IP_PACKET / TCP_PAYLOAD

    def key(self) -> dict[str, Any]:
        return {
            "kernel": self.kernel,
            "cpus": self.cpus,
            "python": self.python,
            "netem_hash": self.netem_hash,
        }

    def fresh(self, now: float | None = None) -> bool:
        """Younger than `MAX_AGE_S` (a time ahead of the clock is not trusted either)."""
        age = (time.time() if now is None else now) - self.measured_at
        return 0 <= age < MAX_AGE_S

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        del data["cached"]  # where it came from is this process's business
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DataPlane:
        return cls(
            tcp_bps=float(data["tcp_bps"]),
            datagram_pps=float(data["datagram_pps"]),
            datagram_bps=float(data["datagram_bps"]),
            measured_at=float(data["measured_at"]),
            seconds=float(data["seconds"]),
            kernel=str(data["kernel"]),
            cpus=int(data["cpus"]),
            python=str(data["python"]),
            netem_hash=str(data["netem_hash"]),
        )

    def text(self) -> str:
        """The figures in one line, in the units a scenario writes rates in."""
        return (
            f"TCP {_figure(self.tcp_bps)} goodput (offloaded; a {_figure(self.tcp_link_bps)} "
            f"link), {self.datagram_pps:,.0f} datagrams/s of {UDP_PAYLOAD} bytes (a "
            f"{_figure(self.datagram_bps)} link, per packet) through one relay direction; "
            f"{self.cpus} CPU(s)"
        )

    def source(self) -> str:
        """Where the figure comes from: measured by this process, or the cache's age."""
        if not self.cached:
            return f"measured now in {self.seconds:.1f} s"
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.measured_at))
        return f"cached from {when} (measured again after a day or when netem/ changes)"


def _figure(bps: float) -> str:
    """A measured rate to 3 significant digits, in scenario units (`9.52gbit`)."""
    return format_rate(float(f"{bps:.3g}"))


def cache_path() -> Path:
    return st.state_dir() / CACHE_FILE


def cached_data_plane(now: float | None = None) -> DataPlane | None:
    """The cached figure when it was measured on this host as it is now, within a day."""
    try:
        plane = DataPlane.from_dict(json.loads(cache_path().read_text()))
    except (OSError, ValueError, KeyError, TypeError):
        return None  # none yet, or unreadable: measure again
    if plane.key() != host_key() or not plane.fresh(now):
        return None
    return dataclasses.replace(plane, cached=True)


def save_data_plane(plane: DataPlane) -> Path:
    path = cache_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, plane.to_dict())
    return path


def host_data_plane(refresh: bool = False, progress: Progress | None = None) -> DataPlane:
    """This host's data plane: the cached figure, or (with `refresh`, or none fit) a new
    measurement, which is cached. Measuring needs root (HostError otherwise)."""
    if not refresh:
        plane = cached_data_plane()
        if plane is not None:
            return plane
    if progress is not None:
        progress(
            "measuring this host's userspace data plane (TCP, then datagrams, through a "
            "throwaway relay link; a few seconds)"
        )
    plane = measure_data_plane()
    try:
        save_data_plane(plane)
    except OSError as err:  # the figure is still good for this process
        if progress is not None:
            progress(f"warning: the figure is not cached ({err})")
    return plane


# ---- measuring -------------------------------------------------------------------------------


def udp_flood(addr: str, port: int, size: int, seconds: float) -> int:
    """Send stamped `size`-byte datagrams as fast as the socket takes them for `seconds`;
    returns how many were sent. Each is its own packet: no UDP GSO, as DDS sends."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    pad = bytes(max(0, size - STAMP.size))
    target = (addr, port)
    seq = 0
    end = time.monotonic() + seconds
    while (now := time.monotonic()) < end:
        # A full queue drops the datagram, as a flood does on a real host.
        with contextlib.suppress(OSError):
            sock.sendto(STAMP.pack(now, seq) + pad, target)
        seq += 1
    sock.close()
    return seq


@contextlib.contextmanager
def _throwaway_pair() -> Iterator[tuple[str, str]]:
    """Two fresh namespaces, removed on the way out whatever happens (Ctrl-C included)."""
    tag = secrets.token_hex(4)
    made: list[str] = []
    try:
        for end in ("a", "b"):
            name = f"{PROBE_PREFIX}{tag}-{end}"
            Netns.create(name).close()
            made.append(name)
        yield made[0], made[1]
    finally:
        for name in made:
            with contextlib.suppress(OSError):
                delete_netns(name)


def _tcp_goodput(ns_a: str, ns_b: str, seconds: float, workers: list[Worker]) -> float:
    """TCP goodput A -> B (bit/s) over `seconds` after `WARM_S` (`linktest.tcp_goodput`, with
    its processes kept in `workers` so that a measurement cut short can stop them)."""
    ready = CTX.Event()
    receiver = in_namespace(ns_b, tcp_receive, ready, ADDR_B, PORT, WARM_S + seconds + 0.5)
    workers.append(receiver)
    if not ready.wait(5):
        raise TestbedError(f"the TCP receiver in {ns_b} did not start")
    sender = in_namespace(ns_a, tcp_send, ADDR_B, PORT, WARM_S + seconds)
    workers.append(sender)
    marks = receiver.result(seconds + 30)
    sender.result(30)
    return goodput_bps(marks, WARM_S, WARM_S + seconds - 0.05)


def _delivered_pps(
    link: UserspaceLink, ns_a: str, ns_b: str, seconds: float, workers: list[Worker]
) -> float:
    """Datagrams per second the relay delivers A -> B while A floods, over `seconds` after
    `WARM_S`: from the relay's own counter, so a receiver that falls behind is not what is
    measured (one still reads them, or B would answer each with an ICMP error)."""
    ready = CTX.Event()
    flood_s = WARM_S + seconds + 0.2
    receiver = in_namespace(ns_b, udp_receive, ready, ADDR_B, PORT, flood_s + 2, 0.3)
    workers.append(receiver)
    if not ready.wait(5):
        raise TestbedError(f"the UDP receiver in {ns_b} did not start")
    sender = in_namespace(ns_a, udp_flood, ADDR_B, PORT, UDP_PAYLOAD, flood_s)
    workers.append(sender)

    def delivered() -> tuple[float, int]:
        return time.monotonic(), int(link.counters()["uplink"]["total"]["packets_out"])

    time.sleep(WARM_S)
    t0, n0 = delivered()
    time.sleep(seconds)
    t1, n1 = delivered()
    sender.result(seconds + 30)
    receiver.result(seconds + 30)
    return (n1 - n0) / (t1 - t0)


def measure_data_plane(seconds: float = MEASURE_S) -> DataPlane:
    """Measure this host's data plane now (about 2 x (`WARM_S` + `seconds`) plus set-up)."""
    require_root()
    t0 = time.monotonic()
    workers: list[Worker] = []
    try:
        with (
            _throwaway_pair() as (ns_a, ns_b),
            UserspaceLink(
                ns_a,
                ns_b,
                dev_a="cap0",
                dev_b="cap0",
                addr_a=f"{ADDR_A}/30",
                addr_b=f"{ADDR_B}/30",
                seed="capacity",
            ) as link,
        ):
            tcp = _tcp_goodput(ns_a, ns_b, seconds, workers)
            pps = _delivered_pps(link, ns_a, ns_b, seconds, workers)
    finally:
        # A measurement cut short (Ctrl-C, an error) leaves no sender or receiver behind.
        for worker in workers:
            if worker.proc.is_alive():
                worker.proc.kill()
                worker.proc.join(2)
    if tcp <= 0 or pps <= 0:
        raise TestbedError(
            f"no traffic came through the throwaway relay link (TCP {tcp:.0f} bit/s, "
            f"{pps:.0f} datagrams/s): the userspace data plane does not work on this host"
        )
    key = host_key()
    return DataPlane(
        tcp_bps=tcp,
        datagram_pps=pps,
        datagram_bps=pps * IP_PACKET * 8,
        measured_at=time.time(),
        seconds=time.monotonic() - t0,
        **key,
    )


# ---- checking a scenario ---------------------------------------------------------------------


@dataclass(frozen=True)
class CapacityWarning:
    """One rate the host's data plane cannot carry. `error`: not even TCP would reach it;
    `note`: traffic the relay handles one packet at a time would not. `link`/`direction` are
    None for all links together (and `direction` for both directions of one link)."""

    level: Level
    link: str | None
    direction: lk.Direction | None
    rate_bps: float
    host_bps: float
    message: str

    def text(self) -> str:
        return f"{self.level}: {self.message}"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class _Ask:
    """A rate one link direction will be asked for, and what asks it."""

    rate_bps: float
    origin: str  # "" for the profile's own rate


LinkSource = Scenario | Links | Iterable[LinkSpec]
TracePeak = Callable[[TraceEvent], float]


def trace_peak_bps(event: TraceEvent) -> float:
    """The highest rate a trace sets (per `Trace.rate_steps` window, what the relay plays)."""
    trace = load_trace(event.path, event.format)
    return max((rate for _, rate in trace.rate_steps()), default=0.0)


def _specs_and_events(source: LinkSource) -> tuple[list[LinkSpec], list[object]]:
    if isinstance(source, Scenario):
        return list(source.links.links), list(source.timeline)
    if isinstance(source, Links):
        return list(source.links), []
    return list(source), []


def _asks(
    specs: list[LinkSpec], events: list[object], trace_peak: TracePeak
) -> dict[tuple[str, lk.Direction], tuple[_Ask | None, _Ask | None]]:
    """Per link direction: the highest fixed rate (its profile's, or a `set` event's) and the
    highest rate a trace plays on it; None where nothing sets one (unlimited)."""
    fixed: dict[tuple[str, lk.Direction], list[_Ask]] = {}
    traced: dict[tuple[str, lk.Direction], list[_Ask]] = {}
    for spec in specs:
        for d in DIRECTIONS:
            rate = spec.profile(d).rate_bps
            fixed[spec.name, d] = [] if rate is None else [_Ask(rate, "")]
            traced[spec.name, d] = []
    for event in events:
        if isinstance(event, SetEvent) and event.changes.get("rate_bps") is not None:
            for d in directions(event.direction):
                ask = _Ask(float(event.changes["rate_bps"]), f"the `set` at {event.at_s:g} s")
                fixed.setdefault((event.link, d), []).append(ask)
        elif isinstance(event, TraceEvent):
            origin = f"the trace {event.path.name} at {event.at_s:g} s (its peak)"
            traced.setdefault((event.link, event.direction), []).append(
                _Ask(trace_peak(event), origin)
            )
    keys = list(dict.fromkeys([*fixed, *traced]))
    return {
        key: (
            max(fixed.get(key, []), key=lambda a: a.rate_bps, default=None),
            max(traced.get(key, []), key=lambda a: a.rate_bps, default=None),
        )
        for key in keys
    }


def _asked(ask: _Ask) -> str:
    rate = format_rate(ask.rate_bps)
    return f"rate {rate}" if not ask.origin else f"rate {rate} (from {ask.origin})"


#: What to do, said once per warning: the two ways out.
_REMEDY = "use a host whose kernel has sch_netem (links.backend: tc or auto)"


def check_links(
    source: LinkSource,
    plane: DataPlane,
    backend: lk.BackendName = "userspace",
    trace_peak: TracePeak = trace_peak_bps,
) -> list[CapacityWarning]:
    """What of `source`'s link rates this host's userspace data plane cannot carry.

    Per direction: a rate above the TCP figure is an error (the relay, not the link, would
    set even TCP's rate); one above the datagram figure a note (UDP sent without GSO would
    be limited by the relay, TCP would not); a direction replaying a trace moves every packet
    on its own, so a trace peak above the datagram figure is an error. Per link, its two
    directions share one relay process; all links together share the host's CPUs, at most
    one relay per CPU at its TCP figure. A direction without a rate (unlimited) asks nothing.
    Links of the tc backend are qdiscs, not relays: nothing to warn about.
    `source` is a scenario (its timeline's `set` rates and traces count too), its `links`,
    or link specs; `trace_peak` gives a trace event's highest rate (it reads the file).
    """
    if backend != "userspace":
        return []
    specs, events = _specs_and_events(source)
    asks = _asks(specs, events, trace_peak)
    tcp, datagram = plane.tcp_link_bps, plane.datagram_bps
    tcp_text, datagram_text = _figure(tcp), _figure(datagram)
    out: list[CapacityWarning] = []
    per_link: dict[str, list[float]] = {}
    errored: set[str] = set()
    for (name, d), (fixed, traced) in asks.items():
        where = f"{name} {d}"
        if traced is not None and traced.rate_bps > datagram:
            errored.add(name)
            out.append(
                CapacityWarning(
                    "error",
                    name,
                    d,
                    traced.rate_bps,
                    datagram,
                    f"{where}: {_asked(traced)} is more than this host's relay carries one "
                    f"packet at a time ({datagram_text}: {plane.datagram_pps:,.0f} packets/s), "
                    "and a direction replaying a trace moves every packet on its own, TCP's "
                    f"too: keep the trace at most {datagram_text}, or {_REMEDY}",
                )
            )
        if fixed is not None and fixed.rate_bps > tcp:
            errored.add(name)
            out.append(
                CapacityWarning(
                    "error",
                    name,
                    d,
                    fixed.rate_bps,
                    tcp,
                    f"{where}: {_asked(fixed)} is more than this host's relay carries even "
                    f"for TCP ({tcp_text} through one direction): the relay, not the link, "
                    f"would set the rate. Lower it to at most {tcp_text}, or {_REMEDY}",
                )
            )
        elif fixed is not None and fixed.rate_bps > datagram:
            out.append(
                CapacityWarning(
                    "note",
                    name,
                    d,
                    fixed.rate_bps,
                    datagram,
                    f"{where}: {_asked(fixed)} is more than this host's relay carries one "
                    f"packet at a time ({datagram_text}: {plane.datagram_pps:,.0f} packets/s of "
                    f"{IP_PACKET} bytes): UDP sent without GSO (ROS 2 DDS) above that is "
                    f"limited by the relay, TCP is not. Lower it to {datagram_text} if such "
                    f"traffic must reach the rate, or {_REMEDY}",
                )
            )
        top = max((a.rate_bps for a in (fixed, traced) if a is not None), default=None)
        if top is not None:
            per_link.setdefault(name, []).append(top)
    for name, rates in per_link.items():
        if len(rates) > 1 and name not in errored and sum(rates) > tcp:
            out.append(
                CapacityWarning(
                    "error",
                    name,
                    None,
                    sum(rates),
                    tcp,
                    f"{name}: its directions ask {format_rate(sum(rates))} together, more than "
                    f"one relay (one process) carries even for TCP ({tcp_text}): with both "
                    f"busy the relay, not the link, would set the rates. Lower them to "
                    f"{tcp_text} together, or {_REMEDY}",
                )
            )
    total = sum(sum(rates) for rates in per_link.values())
    budget = plane.cpus * tcp
    if len(per_link) > 1 and total > budget:
        n = sum(len(rates) for rates in per_link.values())
        out.append(
            CapacityWarning(
                "error",
                None,
                None,
                total,
                budget,
                f"all links: {n} directions ask {format_rate(total)} together, more than the "
                f"relays carry even for TCP on this host's {plane.cpus} CPU(s) "
                f"({_figure(budget)}, {tcp_text} each): with every link busy the relays, not "
                f"the links, would set the rates. Lower the rates to {_figure(budget)} "
                f"together, or {_REMEDY}",
            )
        )
    return out


@dataclass(frozen=True)
class CapacityCheck:
    """A scenario's links against this host: the backend they will use, the data plane's
    figure (None on the tc backend: nothing to measure) and the warnings."""

    backend: str
    plane: DataPlane | None
    warnings: tuple[CapacityWarning, ...] = ()

    @property
    def errors(self) -> list[CapacityWarning]:
        return [w for w in self.warnings if w.level == "error"]

    def lines(self) -> list[str]:
        """What a run or a link test prints before it starts."""
        if self.plane is None:
            return [f"link capacity: {self.backend}: kernel qdiscs, not limited by the relay"]
        out = [f"host data plane: {self.plane.text()}; {self.plane.source()}"]
        if not self.warnings:
            out.append("every link rate is within what this host's relay carries")
        return out + [w.text() for w in self.warnings]

    def to_dict(self) -> dict[str, Any]:
        return {
            "backend": self.backend,
            "data_plane": None if self.plane is None else self.plane.to_dict(),
            "source": None if self.plane is None else self.plane.source(),
            "warnings": [w.to_dict() for w in self.warnings],
        }


def check_scenario(
    scenario: Scenario, refresh: bool = False, progress: Progress | None = None
) -> CapacityCheck:
    """`check_links` for the backend `scenario` will get on this host (`links.choose_backend`,
    whose HostError it passes on), measuring the data plane only where that is the relay."""
    choice = lk.choose_backend(scenario)
    if choice.name != "userspace":
        return CapacityCheck(choice.describe(), None)
    plane = host_data_plane(refresh=refresh, progress=progress)
    return CapacityCheck(choice.describe(), plane, tuple(check_links(scenario, plane)))
