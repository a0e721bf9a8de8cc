"""Link emulation for a run: which backend carries the links, how each link's two ends come to
exist, and one controller that changes live links.

Nouns:
- `BackendChoice` / `choose_backend(scenario)`: `auto` is `tc` where the kernel takes a netem
  qdisc (`testbed.check.netem_status`, the one probe, found by trying) and `userspace`
  elsewhere. An explicit `tc` on a kernel without netem is refused (HostError, exit 3) only
  when the scenario needs netem (delay, jitter, loss, outages); pure rate shaping is HTB.
- `TunRelayEnds`: the userspace backend as a `LinkEnds`: each link's two interfaces are TUN
  devices made by one relay process (`netem.userspace.UserspaceLink`), whose pid goes into the
  run state and whose control socket lives in the run's state folder.
- `LinkController`: what the timeline player and the link self-test call on live links:
  `apply` (the scenario's profiles), `set` (profile fields in place), `shape`/`clear`
  (Wondershaper-style caps on a node's interface), `outage`, `trace`. `TcController` does it
  with qdiscs at the gNB end of each link (`netem.tc.shaping_end`); `UserspaceController` asks
  each link's relay. Caps (`shape`) are HTB/IFB on both backends (HTB works on TUN devices).

Trace replay on the tc backend (the relay replays traces itself): a csv trace's rows become
HTB rate changes at their times; a mahimahi trace is turned into a rate per 100 ms window
(`netem.traces.Trace.rate_steps`, the same binning the replay uses), applied window by
window. A rate of 0 (no opportunity in a window) becomes 8 bit/s, HTB's smallest useful rate.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

from netem.nr import slot_s
from netem.profile import HTB_MIN_RATE_BPS, LinkProfile
from netem.shaping import NodeShaper, check_caps
from netem.sniff import LinkSniffer, SniffConfig, SniffError
from netem.tc import TcLinkBackend, shaping_end
from netem.tc_plan import needs_netem
from netem.traces import Trace, load_trace
from netem.userspace import RelayError, UserspaceLink
from nodes.recording.jsonfile import write_json
from testbed import check
from testbed import state as st
from testbed.errors import BadInput, HostError, TestbedError
from testbed.namespaces import EndNames, VethEnds
from testbed.scenario.model import (
    ClearEvent,
    Event,
    HandoverEvent,
    LinkKind,
    Links,
    LinkSpec,
    OutageEvent,
    Scenario,
    SetEvent,
    ShapeEvent,
)

# ---- what the links need of the topology -------------------------------------------------------
# Declared here, not imported: the topology builds on this module, so this module states the
# little it reads of a built network (the topology's Node, Link and Net satisfy it).


class Node(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def role(self) -> str: ...
    @property
    def netns(self) -> str: ...


class Link(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def kind(self) -> LinkKind: ...
    @property
    def lower(self) -> Node: ...
    @property
    def upper(self) -> Node: ...
    @property
    def spec(self) -> LinkSpec | None: ...
    @property
    def ends(self) -> EndNames: ...


class Net(Protocol):
    """A built (or dry-run) network: its nodes and links by name, and how it was built."""

    @property
    def run_id(self) -> str: ...
    @property
    def mode(self) -> str: ...
    @property
    def dry_run(self) -> bool: ...
    @property
    def scenario(self) -> Scenario: ...
    @property
    def backend(self) -> object: ...
    @property
    def nodes(self) -> Mapping[str, Node]: ...
    @property
    def links(self) -> Mapping[str, Link]: ...

    def record_pid(self, pid: int, what: str) -> None: ...

    def emulates(self, link: str) -> bool:
        """Whether this process applies `link`'s emulation (on one host of a topology across
        hosts, only the links it holds the emulating end of)."""
        ...

    def prepare_handover(self, vehicle: str) -> None: ...

    def hand_over(self, vehicle: str, target: str) -> None: ...


BackendName = Literal["tc", "userspace"]
Direction = Literal["uplink", "downlink"]
Directions = Literal["uplink", "downlink", "both"]
DIRECTIONS: tuple[Direction, Direction] = ("uplink", "downlink")

#: Bytes a link carries per IP packet beyond the packet itself: HTB on a veth counts the
#: 14-byte Ethernet header, the relay counts IP packets as read from the TUN device.
FRAME_OVERHEAD = {"tc": 14, "userspace": 0}
#: The netem fields a profile may change; `set` events naming any of them need netem on tc.
NETEM_FIELDS = ("delay_s", "jitter_s", "loss", "gilbert_elliott")
#: In a run's link-state folder (state dir, not the results folder): the backend, and each
#: relay's pid and control socket (what `down`, `status` and `clean` read).
LINK_STATE_FILE = "link-backend.json"


# ---- which backend -------------------------------------------------------------------------


@dataclass(frozen=True)
class BackendChoice:
    """The backend a run uses, and why (what run.json and `testbed up` print)."""

    name: BackendName
    reason: str

    def describe(self) -> str:
        return f"{self.name} ({self.reason})"


def netem_needs(scenario: Scenario) -> list[str]:
    """What in `scenario` only a netem qdisc can do on the tc backend, one phrase each."""
    needs = []
    for spec in scenario.links.links:
        for direction in DIRECTIONS:
            if needs_netem(spec.profile(direction)):
                needs.append(f"{spec.name} {direction} (delay/jitter/loss)")
    for event in scenario.timeline:
        if isinstance(event, SetEvent) and any(
            event.changes.get(f) not in (None, 0, 0.0) for f in NETEM_FIELDS
        ):
            needs.append(f"the `set` event on {event.link} at {event.at_s:g} s")
        elif isinstance(event, OutageEvent):
            needs.append(f"the outage of {event.link} at {event.at_s:g} s")
    return needs


def choose_backend(
    scenario: Scenario, probe: Callable[[], tuple[bool, str]] = check.netem_status
) -> BackendChoice:
    """The backend for `scenario` on this kernel; HostError if it asks for one that cannot work."""
    wanted = scenario.links.backend
    if wanted == "userspace":
        return BackendChoice("userspace", "asked for by the scenario")
    radios = [s.name for s in scenario.links.links if s.uplink.radio or s.downlink.radio]
    if wanted == "auto" and radios:
        # The loader refuses `tc` with a radio; `auto` must not pick it either.
        return BackendChoice(
            "userspace", f"auto: {', '.join(radios)} have an NR radio, which only the relay models"
        )
    states = [s.name for s in scenario.links.links if s.uplink.rrc is not None]
    if wanted == "auto" and states:
        return BackendChoice(
            "userspace", f"auto: {', '.join(states)} have RRC states, which only the relay models"
        )
    ok, detail = probe()
    if wanted == "auto":
        if ok:
            return BackendChoice("tc", "auto: the kernel has sch_netem")
        return BackendChoice("userspace", f"auto: {detail.split(';')[0]}")
    if ok:
        return BackendChoice("tc", "asked for by the scenario")
    needs = netem_needs(scenario)
    if needs:
        shown = ", ".join(needs[:3]) + (f" and {len(needs) - 3} more" if len(needs) > 3 else "")
        raise HostError(
            f"links.backend is `tc`, but this kernel cannot add a netem qdisc "
            f"({detail.split(';')[0]}), and the scenario needs netem for {shown}. "
            "Use `backend: userspace` (the TUN relay) or `backend: auto`."
        )
    return BackendChoice("tc", "asked for; rate shaping only (HTB), the kernel has no sch_netem")


def ends_for(choice: BackendChoice, mode: st.Mode, scenario: Scenario) -> VethEnds | TunRelayEnds:
    """The `LinkEnds` of a backend: veth pairs for tc, relay-made TUN pairs for userspace."""
    if choice.name == "tc":
        return VethEnds()
    # `up` leaves the network to outlive this process; a `run` owns it (its relays die with it).
    return TunRelayEnds(scenario.links, die_with_parent=mode == "run", seed=scenario.seed)


# ---- the userspace backend's link ends -----------------------------------------------------


def link_state_dir(run_id: str) -> Path:
    """Where a run keeps its relays' control sockets, logs and `link-backend.json`: in the
    state dir, beside the run's state file (not the results folder under runs/)."""
    return st.state_dir() / run_id


class TunRelayEnds:
    """A link's two interfaces as TUN devices made by one relay process per link.

    The relay (`python -m netem.relay`) opens one TUN in each namespace, named as
    `link.ends` says, and brings both up; it is started with the link's profiles (uplink =
    lower -> upper), so the link shapes from its first packet. Addresses and routes are added
    afterwards by the topology as for veth (the relay is given none, so nothing is done
    twice). Each relay's pid is recorded in the run state right after it starts (`down` and
    `clean` stop it; `clean` also finds relays by the namespaces on their command line, for a
    crash between start and record). `relays` maps link names to their `UserspaceLink`.

    The air links of one gNB whose profiles have an NR radio share one relay, attached to the
    first of them, and its slots (`netem.cell`): a cell serves all its UEs, by the cell's
    `scheduler`.
    """

    name = "userspace"

    def __init__(self, links: Links, die_with_parent: bool = True, seed: int = 0) -> None:
        self.specs = {spec.name: spec for spec in links.links}
        self.die_with_parent = die_with_parent
        self.seed = seed
        self.relays: dict[str, UserspaceLink] = {}
        self.cell_hosts: dict[str, UserspaceLink] = {}  # gNB -> the relay its cell lives in

    def _relay(
        self,
        ends: EndNames,
        control: str | None = None,
        log_dir: Path | None = None,
        **cell: Any,
    ) -> UserspaceLink:
        # ends are named after the peers: the lower node's interface is the upper's name
        spec = self.specs.get(f"{ends.upper_ifname}-{ends.lower_ifname}")
        up = spec.uplink if spec is not None else LinkProfile()
        down = spec.downlink if spec is not None else LinkProfile()
        return UserspaceLink(
            ends.lower_netns,
            ends.upper_netns,
            dev_a=ends.lower_ifname,
            dev_b=ends.upper_ifname,
            uplink=up,
            downlink=down,
            seed=f"{self.seed}:{ends.lower_ifname}-{ends.upper_ifname}",
            control_path=control,
            log_dir=log_dir,
            die_with_parent=self.die_with_parent,
            **cell,
        )

    def _cell_of(self, link: Link, net: Net) -> dict[str, Any]:
        """How `link` joins its gNB's cell: nothing (no radio), as the cell's host, or
        attached to the host's relay."""
        spec = self.specs.get(link.name)
        if link.kind != "air" or spec is None:
            return {}
        if spec.uplink.radio is None and spec.downlink.radio is None:
            return {}
        gnb = link.upper.name
        cells = {c.gnb: c for c in net.scenario.topology.cells}
        scheduler = cells[gnb].scheduler if gnb in cells else "rr"
        host = self.cell_hosts.get(gnb)
        joined: dict[str, Any] = {"name": link.name, "cell": gnb, "scheduler": scheduler}
        return joined if host is None else {**joined, "host": host}

    def commands(self, ends: EndNames) -> list[str]:
        relay = self._relay(ends, control="<state dir>/<run id>/<n>.sock")
        return [" ".join(_shell_word(w) for w in relay.command()) + " &"]

    def create(self, link: Link, net: Net) -> None:
        folder = link_state_dir(net.run_id)
        folder.mkdir(parents=True, exist_ok=True)
        n = len(self.relays)
        control = folder / f"{n}.sock"  # short: unix socket paths are <108 B
        logs = folder / f"{n}.log.d"  # the relay's log lives with the run, not in /tmp
        logs.mkdir(exist_ok=True)
        cell = self._cell_of(link, net)
        relay = self._relay(link.ends, control=str(control), log_dir=logs, **cell)
        try:
            relay.start()
        except RelayError as err:
            raise TestbedError(f"link {link.name}: {err}") from None
        self.relays[link.name] = relay
        if cell and "host" not in cell:
            self.cell_hosts[cell["cell"]] = relay
        net.record_pid(relay.pid or 0, f"relay {link.name}")
        _write_relay_file(folder, self.relays)


def _shell_word(word: str) -> str:
    return (
        word if re.fullmatch(r"[\w@%+=:,./<>-]+", word) else "'" + word.replace("'", "'\\''") + "'"
    )


def _write_relay_file(folder: Path, relays: dict[str, UserspaceLink]) -> None:
    """`link-backend.json`: each relay's pid and control socket (for `down`/`clean`)."""
    data = {
        "backend": "userspace",
        "relays": [
            {
                "link": name,
                "pid": relay.pid,
                "control": relay.control_path,
            }
            for name, relay in relays.items()
        ],
    }
    write_json(folder / LINK_STATE_FILE, data)


def write_backend(run_id: str, choice: BackendChoice) -> None:
    """Record the run's backend in its `link-backend.json` (what `down`/`status` read)."""
    folder = link_state_dir(run_id)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LINK_STATE_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        data = {}
    data.update(backend=choice.name, reason=choice.reason)
    write_json(path, data)


def remove_link_state(run_id: str) -> None:
    """Remove a run's link-state folder: relay sockets, relay logs, `link-backend.json` (after
    the relays stopped)."""
    shutil.rmtree(link_state_dir(run_id), ignore_errors=True)


def relay_pids(namespaces: list[str]) -> list[int]:
    """Relay processes whose command line names one of `namespaces` (found in /proc)."""
    wanted = {ns.encode() for ns in namespaces}
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"netem.relay" in argv and any(
            a == b"--netns-a" and i + 1 < len(argv) and argv[i + 1] in wanted
            for i, a in enumerate(argv)
        ):
            found.append(int(entry))
    return found


# ---- live links ------------------------------------------------------------------------------


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
        the target (`Net.hand_over`)."""
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


def shaped_interface(net: Net, node_name: str) -> tuple[Node, str]:
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

    def __init__(self, net: Net) -> None:
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

    def _link(self, name: str) -> Link:
        if name not in self.net.links:
            raise BadInput(f"no link {name!r} in this run ({', '.join(self.net.links)})")
        if not self.net.emulates(name):
            raise BadInput(f"link {name} is emulated on another host of the topology, not here")
        return self.net.links[name]

    @staticmethod
    def _directions(direction: Directions) -> tuple[Direction, ...]:
        return DIRECTIONS if direction == "both" else (direction,)

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

    def __init__(self, net: Net, ends: TunRelayEnds) -> None:
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
            for d in DIRECTIONS if "rrc" in changes else self._directions(direction):
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

    def __init__(self, net: Net, dry_run: bool = False) -> None:
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
        # for what arrives there, after the far end's qdiscs (`netem.sniff`).
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
            for d in self._directions(direction):
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


def controller_for(net: Net) -> LinkController:
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
