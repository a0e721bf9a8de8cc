"""Live links: `LinkController`, what the timeline player and the link self-test call on a
run's links: `apply` (the scenario's profiles), `set` (profile fields in place), `shape`/`clear`
(Wondershaper-style caps on a node's interface), `outage`, `trace`. `TcController` does it with
qdiscs at the gNB end of each link (`netem.tc.link.shaping_end`); `UserspaceController` asks each
link's relay. Caps (`shape`) are HTB/IFB on both backends (HTB works on TUN devices).

Trace replay on the tc backend (the relay replays traces itself): a csv trace's rows become
HTB rate changes at their times; a mahimahi trace is turned into a rate per 100 ms window
(`netem.traces.Trace.rate_steps`, the same binning the replay uses), applied window by
window. A rate of 0 (no opportunity in a window) becomes 8 bit/s, HTB's smallest useful rate.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

from netem.directions import DIRECTIONS, Direction, Directions, directions
from netem.nr.phy import slot_s
from netem.profile import HTB_MIN_RATE_BPS, LinkProfile
from netem.relay.client import RelayError, UserspaceLink
from netem.tc.link import TcLinkBackend, shaping_end
from netem.tc.shaping import NodeShaper, check_caps
from netem.tc.sniff import LinkSniffer, SniffConfig, SniffError
from netem.traces import Trace, load_trace
from testbed.errors import BadInput, HostError
from testbed.links.relay_ends import TunRelayEnds
from testbed.links.views import (
    BackendName,
    LinkView,
    NetView,
    NodeView,
)
from testbed.scenario.model import ClearEvent, Event, HandoverEvent, ShapeEvent

#: Bytes a link carries per IP packet beyond the packet itself: HTB on a veth counts the
#: 14-byte Ethernet header, the relay counts IP packets as read from the TUN device.
FRAME_OVERHEAD = {"tc": 14, "userspace": 0}


class LinkController(Protocol):
    """Changes a run's live links; one implementation per backend (`controller_for`)."""

    backend: BackendName
    frame_overhead: int
    #: Whether `counters` counts packets (the relays do; the tc backend's are not read).
    counts: bool

    def apply(self) -> None:
        """Put every link's scenario profiles in place."""
        ...

    def profile(self, link: str, direction: Direction) -> LinkProfile:
        """The profile a link direction has now."""
        ...

    def set(self, link: str, direction: Directions, changes: dict[str, Any]) -> None:
        """Change the named profile fields of one direction (or both) in place."""
        ...

    def prepare(self, events: Sequence[Event]) -> None:
        """Open what `events` will need (netlink sockets of shaped nodes) ahead of time, so
        applying them on time costs no socket set-up."""
        ...

    def shape(self, node: str, uplink_bps: float | None, downlink_bps: float | None) -> None:
        """Wondershaper: cap what `node` sends (uplink) / receives (downlink) on its interface
        towards its gNB (a gNB: towards its core)."""
        ...

    def clear(self, node: str) -> None:
        """Lift the caps `shape` put on `node` (link profiles stay)."""
        ...

    def outage(self, link: str, seconds: float) -> None:
        """Drop every packet on the link, both directions, for `seconds` from now."""
        ...

    def trace(self, link: str, direction: Direction, path: Path, fmt: str, loop: bool) -> None:
        """Let a bandwidth trace set the direction's rate from now on."""
        ...

    def handover(self, event: HandoverEvent) -> None:
        """Hand a vehicle over: its two air links stop for the interruption (the source's
        packets held, or dropped when lossy; the target's held), then its routes switch to
        the target (`NetView.hand_over`)."""
        ...

    def failure(self) -> str | None:
        """Why the links stopped working (a relay died), or None."""
        ...

    def watch(self, on_death: Callable[[str], None] | None = None) -> None:
        """Start noticing helpers that die (relays): `failure()` then says why, and `on_death`
        is called. A backend with nothing that can die (qdiscs) has nothing to watch."""
        ...

    def counters(self, link: str) -> dict[str, Any] | None:
        """The link's packet and byte counters per direction (a relay's `counters` reply), or
        None where the backend does not count (the tc backend's qdisc statistics are not read)."""
        ...

    def capture(self, link: str, path: Path) -> None:
        """Write what the link delivers, both directions, to the pcapng file `path`."""
        ...

    def stop_capture(self, link: str) -> dict[str, Any]:
        """Finish the link's capture: {path, packets, dropped} per direction ({} if none)."""
        ...

    def realisation(self, link: str) -> dict[str, Any]:
        """How the backend realises the link, for the run folder's links.json: the relay's
        command line and stages; nothing per link on tc (see `commands`)."""
        ...

    def commands(self) -> list[str]:
        """The shell lines that `apply` amounts to now (on tc, rendered by a dry-run twin with
        the live profiles; on the relays, none: their command lines carry the profiles)."""
        ...

    def close(self) -> None:
        """Stop helper threads (and, for a run that owns them, the relays)."""
        ...


def shaped_interface(net: NetView, node_name: str) -> tuple[NodeView, str]:
    """The node and its interface that `shape` caps: a vehicle's or core's interface towards its
    gNB, a gNB's towards its core or UPF, a UPF's towards its (first) gNB, an edge server's
    N6."""
    if node_name not in net.nodes:
        raise BadInput(f"shape: no node {node_name!r} in this run ({', '.join(net.nodes)})")
    node = net.nodes[node_name]
    topo = net.scenario.topology
    if node.role == "vehicle":
        peer = next(v.gnb for v in topo.vehicles if v.name == node_name)
    elif node.role == "gnb":
        peer = topo.cell_of_gnb(node_name).uplink_peer
    elif node.role == "core":
        peer = next(c.gnb for c in topo.cells if c.core == node_name)
    elif node.role == "upf":
        peer = next(c.gnb for c in topo.cells if c.upf == node_name)
    else:  # an edge server: its N6 link, towards the UPF or the gNB of a cell it sits at
        cell = next(c for c in topo.cells if c.edge == node_name)
        peer = cell.gnb if cell.placement == "cell" else cell.uplink_peer
    return node, peer


class _Base:
    """What both controllers share: profile bookkeeping, caps, trace and outage timers."""

    backend: BackendName

    def __init__(self, net: NetView) -> None:
        self.net = net
        self.frame_overhead = FRAME_OVERHEAD[self.backend]
        self.profiles: dict[tuple[str, Direction], LinkProfile] = {}
        for link in net.links.values():
            spec = link.spec
            for d in DIRECTIONS:
                self.profiles[link.name, d] = spec.profile(d) if spec else LinkProfile()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        # Per shaped node: its caps' sockets, held open.
        self._caps: dict[str, NodeShaper] = {}

    def _link(self, name: str) -> LinkView:
        if name not in self.net.links:
            raise BadInput(f"no link {name!r} in this run ({', '.join(self.net.links)})")
        if not self.net.emulates(name):
            raise BadInput(f"link {name} is emulated on another host of the topology, not here")
        return self.net.links[name]

    def profile(self, link: str, direction: Direction) -> LinkProfile:
        self._link(link)
        return self.profiles[link, direction]

    def prepare(self, events: Sequence[Event]) -> None:
        for event in events:
            if isinstance(event, ShapeEvent | ClearEvent):
                shaper = self._shaper(event.node)
            if isinstance(event, ShapeEvent):
                shaper.prepare(event.uplink_bps is not None, event.downlink_bps is not None)
            if isinstance(event, HandoverEvent):
                self.net.prepare_handover(event.vehicle)

    def _shaper(self, node: str) -> NodeShaper:
        """What `shape` changes on a node, opened once per run."""
        if node not in self._caps:
            where, ifname = shaped_interface(self.net, node)
            self._caps[node] = NodeShaper(where.netns, ifname)
        return self._caps[node]

    def shape(self, node: str, uplink_bps: float | None, downlink_bps: float | None) -> None:
        check_caps(uplink_bps, downlink_bps)  # before any socket is opened for the node
        shaper = self._shaper(node)
        with self._lock:
            shaper.shape(uplink_bps, downlink_bps)

    def clear(self, node: str) -> None:
        shaper = self._shaper(node)
        with self._lock:
            shaper.clear()

    def _later(self, name: str, fn: Callable[[], None]) -> None:
        thread = threading.Thread(target=fn, name=name, daemon=True)
        self._threads.append(thread)
        thread.start()

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2)
        for shaper in self._caps.values():
            shaper.close()
        self._caps.clear()


class UserspaceController(_Base):
    """Live links of the userspace backend: each link's relay does what is asked in place."""

    backend: BackendName = "userspace"
    counts = True

    def __init__(self, net: NetView, ends: TunRelayEnds) -> None:
        super().__init__(net)
        self.relays = ends.relays
        self._failure: str | None = None
        self.died = threading.Event()

    def watch(self, on_death: Callable[[str], None] | None = None) -> None:
        """Watch every relay; when one dies, `failure()` says so and `on_death` is called
        (within 0.2 s)."""

        def died(err: RelayError) -> None:
            if self._failure is None:
                self._failure = str(err)
            self.died.set()
            if on_death is not None:
                on_death(str(err))

        for relay in self.relays.values():
            relay.watch(died, interval_s=0.2)

    def failure(self) -> str | None:
        return self._failure

    def _relay(self, link: str) -> UserspaceLink:
        self._link(link)
        return self.relays[link]

    def apply(self) -> None:
        for name in self.net.links:
            if not self.net.emulates(name):
                continue  # its relay runs on the other host
            for d in DIRECTIONS:
                self._relay(name).set(d, self.profiles[name, d])

    def set(self, link: str, direction: Directions, changes: dict[str, Any]) -> None:
        relay = self._relay(link)
        with self._lock:
            relay.set(direction, dict(changes))
            # RRC states are the UE's: a change of `rrc` reaches both directions.
            for d in DIRECTIONS if "rrc" in changes else directions(direction):
                self.profiles[link, d] = relay.profiles[d]

    def outage(self, link: str, seconds: float) -> None:
        self._relay(link).outage(seconds, "both")

    def handover(self, event: HandoverEvent) -> None:
        source, target = self._relay(event.source_link), self._relay(event.target_link)
        if event.interruption_s > 0:
            # The gap starts on both links before the routes move, so no packet slips
            # through either while the switch is made. Lossless, the target delivers what
            # the source forwarded first and its own from the next slot on (PDCP's order):
            # the two links' relays would otherwise race at the gap's end.
            radio = self.profiles[event.target_link, "downlink"].radio
            slot = slot_s(radio.numerology) if radio is not None and event.lossless else 0.0
            source.interrupt(event.interruption_s, "hold" if event.lossless else "drop")
            target.interrupt(event.interruption_s + slot, "hold")
        self.net.hand_over(event.vehicle, event.target)

    def trace(self, link: str, direction: Direction, path: Path, fmt: str, loop: bool) -> None:
        self._relay(link).play_trace(direction, path, fmt, loop)

    def counters(self, link: str) -> dict[str, Any] | None:
        return self._relay(link).counters()

    def capture(self, link: str, path: Path) -> None:
        self._relay(link).capture(path, label=link)

    def stop_capture(self, link: str) -> dict[str, Any]:
        return self._relay(link).stop_capture()

    def realisation(self, link: str) -> dict[str, Any]:
        relay = self._relay(link)
        out: dict[str, Any] = {"relay_command": relay.command()}
        try:
            counters = relay.counters()
            out["stages"] = {d: list(counters[d]["stages"]) for d in DIRECTIONS if d in counters}
        except Exception as err:  # the configuration is still worth keeping
            out["stages"] = f"unavailable: {err}"
        return out

    def commands(self) -> list[str]:
        return []  # the relays start with their profiles: see the relay command lines

    def close(self) -> None:
        super().close()
        if self.net.mode == "run":
            for relay in reversed(self.relays.values()):  # a cell's attached links first
                relay.close()


class TcController(_Base):
    """Live links of the tc backend: a `TcLinkBackend` at the gNB end of each link."""

    backend: BackendName = "tc"
    counts = False

    def __init__(self, net: NetView, dry_run: bool = False) -> None:
        super().__init__(net)
        self.dry_run = dry_run
        self.shapers: dict[str, TcLinkBackend] = {}
        for link in net.links.values():
            if not net.emulates(link.name):
                continue  # its shaping end is on another host, which shapes it
            end = shaping_end(link.kind)
            node = link.upper if end == "upper" else link.lower
            ifname = link.ends.upper_ifname if end == "upper" else link.ends.lower_ifname
            sends: Direction = "downlink" if end == "upper" else "uplink"
            self.shapers[link.name] = TcLinkBackend(node.netns, ifname, sends, dry_run=dry_run)
        self._outage_until: dict[str, float] = {}
        self._sniffers: dict[str, LinkSniffer] = {}  # link -> its capture (`capture`)

    def apply(self) -> None:
        for name, shaper in self.shapers.items():
            shaper.apply(self.profiles[name, "uplink"], self.profiles[name, "downlink"])

    def commands(self) -> list[str]:
        if self.dry_run:
            return [line for shaper in self.shapers.values() for line in shaper.commands]
        # The live shapers keep no text: a dry-run twin renders the same profiles.
        twin = TcController(self.net, dry_run=True)
        try:
            twin.profiles = dict(self.profiles)
            twin.apply()
            return twin.commands()
        finally:
            twin.close()

    def failure(self) -> str | None:
        return None  # qdiscs cannot die on their own

    def watch(self, on_death: Callable[[str], None] | None = None) -> None:
        pass  # nothing of the tc backend runs on its own: nothing to watch

    def counters(self, link: str) -> dict[str, Any] | None:
        self._link(link)
        return None

    def capture(self, link: str, path: Path) -> None:
        # No relay sees these packets: a capture process listens on both ends' interfaces
        # for what arrives there, after the far end's qdiscs (`netem.tc.sniff`).
        ln = self._link(link)
        if link in self._sniffers:
            raise BadInput(f"record.pcap: link {link} is captured already")
        config = SniffConfig(
            link, str(path), ln.lower.netns, ln.ends.lower_ifname,
            ln.upper.netns, ln.ends.upper_ifname,
        )  # fmt: skip
        try:
            sniffer = LinkSniffer(config).start()
        except SniffError as err:
            raise HostError(f"record.pcap: {err}") from None
        self.net.record_pid(sniffer.pid or 0, f"capture {link}")
        self._sniffers[link] = sniffer

    def stop_capture(self, link: str) -> dict[str, Any]:
        self._link(link)
        sniffer = self._sniffers.pop(link, None)
        return {} if sniffer is None else sniffer.close()

    def realisation(self, link: str) -> dict[str, Any]:
        self._link(link)
        return {}

    def _change(self, link: str, direction: Direction, profile: LinkProfile) -> None:
        self.shapers[link].change(direction, profile)

    def set(self, link: str, direction: Directions, changes: dict[str, Any]) -> None:
        self._link(link)
        with self._lock:
            for d in directions(direction):
                # via a dict, so a Gilbert-Elliott model given as a mapping becomes one again
                profile = LinkProfile.from_dict({**self.profiles[link, d].to_dict(), **changes})
                if self._outage_until.get(link, 0) <= time.monotonic():
                    self._change(link, d, profile)
                self.profiles[link, d] = profile  # an outage's end restores this

    def handover(self, event: HandoverEvent) -> None:
        # Unreachable from a scenario: a handover needs the channel, the channel an NR
        # radio, and the loader refuses `tc` with a radio.
        raise BadInput(
            f"handover of {event.vehicle} at {event.at_s:g} s: handovers need the userspace "
            "relay (links.backend userspace or auto)"
        )

    def outage(self, link: str, seconds: float) -> None:
        self._link(link)
        with self._lock:
            self._outage_until[link] = time.monotonic() + seconds
            for d in DIRECTIONS:
                self._change(link, d, self.profiles[link, d].replace(loss=1.0))

        def restore() -> None:
            if self._stop.wait(max(0.0, self._outage_until[link] - time.monotonic())):
                return
            with self._lock:
                if self._outage_until[link] > time.monotonic():
                    return  # a later outage extended it; its own timer restores
                for d in DIRECTIONS:
                    self._change(link, d, self.profiles[link, d])

        self._later(f"outage-{link}", restore)

    def trace(self, link: str, direction: Direction, path: Path, fmt: str, loop: bool) -> None:
        self._link(link)
        steps = trace_rate_steps(load_trace(path, fmt))  # type: ignore[arg-type]
        start = time.monotonic()

        def replay() -> None:
            for at_s, rate in _steps_forever(steps, loop):
                if self._stop.wait(max(0.0, start + at_s - time.monotonic())):
                    return
                # a window with no opportunity: HTB cannot send at 0 bit/s
                self.set(link, direction, {"rate_bps": max(HTB_MIN_RATE_BPS, rate)})

        self._later(f"trace-{link}-{direction}", replay)

    def close(self) -> None:
        super().close()
        for link in list(self._sniffers):  # a capture never outlives its run
            self.stop_capture(link)
        for shaper in self.shapers.values():
            shaper.close()


def trace_rate_steps(trace: Trace) -> tuple[list[tuple[float, float]], float]:
    """A trace as `(time_s, rate_bps)` steps over one period (`Trace.rate_steps`, the
    binning the replay uses too), and the period."""
    return trace.rate_steps(), trace.duration_s


def _steps_forever(
    steps_and_period: tuple[list[tuple[float, float]], float], loop: bool
) -> Iterator[tuple[float, float]]:
    steps, period = steps_and_period
    offset = 0.0
    while True:
        for at_s, rate in steps:
            yield offset + at_s, rate
        if not loop or period <= 0:
            return
        offset += period


def controller_for(net: NetView) -> LinkController:
    """The controller of a built (or dry-run) net, by the backend its links were made with."""
    if isinstance(net.backend, TunRelayEnds):
        return UserspaceController(net, net.backend)
    return TcController(net, dry_run=net.dry_run)


@contextlib.contextmanager
def neutral(controller: LinkController, link: str, direction: Direction) -> Iterator[None]:
    """Run the block with one link direction unshaped (delay 0, no loss, no rate), then put
    its profile back: the baseline of the link self-test."""
    before = controller.profile(link, direction)
    flat = LinkProfile(queue_packets=before.queue_packets)
    controller.set(link, direction, {f: getattr(flat, f) for f in flat.to_dict()})
    try:
        yield
    finally:
        controller.set(link, direction, before.to_dict())
