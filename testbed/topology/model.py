"""The parts of a run's network: `Route`, `Node` (a namespace), `Link` (two nodes and a /30), `Net`
(the whole run, a context manager that tears itself down)."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from ipaddress import IPv4Address, IPv4Interface, IPv4Network
from typing import Any

from pyroute2 import IPRoute
from pyroute2.netlink.exceptions import NetlinkError as PyNetlinkError

from netem.errors import NetlinkError
from netem.netns import netns_path
from netem.tc.link import shaping_end
from testbed import links
from testbed import state as st
from testbed.addressing import LinkAddresses
from testbed.errors import TestbedError
from testbed.namespaces import GSO_MAX_SIZE, EndNames, LinkEnds, Netns, VethEnds
from testbed.scenario.model import Cell, LinkKind, LinkSpec, Role, Scenario
from testbed.topology import vxlan
from testbed.topology.names import OWNER_TAG
from testbed.topology.teardown import Removed, remove_run
from testbed.topology.vxlan import Transit

# ---- the parts of a network ----------------------------------------------------------------


@dataclass(frozen=True)
class Route:
    """`dst` ('default' or a network) via `via` out of interface `dev`, from `src` (a vehicle
    behind a UPF sends from its UE address, not from its air link's)."""

    dst: str
    via: IPv4Address
    dev: str
    src: IPv4Address | None = None


@dataclass(eq=False)
class Node:
    """A vehicle, gNB or core: a namespace with interfaces (named after their peers)."""

    name: str
    role: Role
    netns: str
    net: Net = field(repr=False)
    interfaces: dict[str, IPv4Interface] = field(default_factory=dict)
    routes: list[Route] = field(default_factory=list)
    forwarding: bool = False
    #: A vehicle behind a UPF: its address from the UE pool (a /32 on its air interface).
    ue_address: IPv4Address | None = None
    #: Interfaces whose MTU is not the link's: a UE's air interface leaves room for GTP-U.
    mtus: dict[str, int] = field(default_factory=dict)
    #: The machine it is on (`topology.hosts`); None when the topology names no hosts.
    host: str | None = None
    ns: Netns | None = field(default=None, repr=False)  # None in a dry run or after teardown

    def addresses(self) -> str:
        """'gnb1 10.200.0.1/30' per interface, comma separated."""
        return ", ".join(f"{ifname} {addr}" for ifname, addr in self.interfaces.items())

    def address_towards(self, peer: str) -> IPv4Address:
        """This node's address on the link to `peer` (its interface is named after `peer`)."""
        return self.interfaces[peer].ip

    @property
    def ipr(self) -> IPRoute:
        """The netlink socket inside this node's namespace (owned by the Net; don't close)."""
        return self._ns().ipr

    @contextlib.contextmanager
    def entered(self) -> Iterator[None]:
        """Run the calling thread inside this node's namespace for the block."""
        with self._ns().entered():
            yield

    def socket(
        self, family: int = socket.AF_INET, type: int = socket.SOCK_DGRAM, proto: int = 0
    ) -> socket.socket:
        """A socket inside this node's namespace (no process needed)."""
        return self._ns().socket(family, type, proto)

    def nsenter_argv(self, argv: Sequence[str]) -> list[str]:
        """`argv` prefixed to run inside this node's namespace (nsenter setns()s, then execs)."""
        return ["nsenter", f"--net={netns_path(self.netns)}", "--", *argv]

    def popen(self, argv: Sequence[str], what: str = "", **kwargs: Any) -> subprocess.Popen[Any]:
        """Start `argv` inside this namespace; the run's state records it, so `down`/`clean`
        stop it even if this process dies."""
        self._ns()
        proc = subprocess.Popen(self.nsenter_argv(argv), **kwargs)
        self.net.adopt(proc, what or f"{self.name}: {argv[0]}")
        return proc

    def read_sysctl(self, key: str) -> str:
        return self._ns().read_sysctl(key)

    def ns_here(self) -> Netns:
        """This namespace through an rtnetlink socket of the calling thread's: a pyroute2
        socket must not be shared between threads, and the timeline plays handovers in its
        own (`ipr` is the building thread's). Opened once per thread, closed at teardown."""
        if threading.current_thread() is threading.main_thread():
            return self._ns()
        self._ns()
        key = (threading.get_ident(), self.name)
        with self.net._thread_lock:
            ns = self.net._thread_ns.get(key)
            if ns is None:
                ns = self.net._thread_ns[key] = Netns.open(self.netns)
        return ns

    def _ns(self) -> Netns:
        if self.ns is None:
            raise TestbedError(f"node {self.name} has no namespace (dry run or torn down)")
        return self.ns


@dataclass(eq=False)
class Link:
    """Two nodes joined by a /30; `lower` is the vehicle (air), the gNB (backhaul, N3, N6 at
    the cell) or the UPF (N6)."""

    name: str
    kind: LinkKind
    lower: Node
    upper: Node
    addresses: LinkAddresses
    spec: LinkSpec | None = None  # the scenario's profiles for it, when the scenario has them

    @property
    def ends(self) -> EndNames:
        return EndNames(
            lower_netns=self.lower.netns,
            lower_ifname=self.upper.name,
            upper_netns=self.upper.netns,
            upper_ifname=self.lower.name,
        )

    def end_namespaces(self) -> tuple[Netns, Netns]:
        """The two nodes' namespaces (what a `LinkEnds` backend creates the interfaces in)."""
        return self.lower._ns(), self.upper._ns()


class RelayLeg:
    """A link across hosts as its relay sees it: one end in the lower node's namespace (as on
    one host), the other in the link's transit namespace instead of the upper node's (which is
    on another host). What `testbed.links.TunRelayEnds` is given to start the relay."""

    def __init__(self, link: Link, transit: Transit) -> None:
        self.link = link
        self.transit = transit

    @property
    def name(self) -> str:
        return self.link.name

    @property
    def kind(self) -> LinkKind:
        return self.link.kind

    @property
    def lower(self) -> Node:
        return self.link.lower

    @property
    def upper(self) -> Node:
        return self.link.upper

    @property
    def spec(self) -> LinkSpec | None:
        return self.link.spec

    @property
    def ends(self) -> EndNames:
        return EndNames(
            lower_netns=self.link.lower.netns,
            lower_ifname=self.link.upper.name,
            upper_netns=self.transit.netns,
            upper_ifname=self.transit.relay_end,
        )


class Net:
    """A run's network. Build it with `build`; use it as a context manager to tear it down."""

    def __init__(
        self,
        scenario: Scenario,
        run_id: str,
        pool: IPv4Network,
        mode: st.Mode,
        backend: LinkEnds,
        dry_run: bool,
        host: str | None = None,
    ) -> None:
        self.scenario = scenario
        self.run_id = run_id
        self.pool = pool
        self.mode = mode
        self.backend = backend
        self.dry_run = dry_run
        #: The host whose part this is (`testbed up --host`); None: every node is built here.
        self.host = host
        self.nodes: dict[str, Node] = {}
        self.links: dict[str, Link] = {}
        #: This host's ends of the links to nodes on other hosts, by link name (`vxlan`).
        self.tunnels: dict[str, vxlan.Tunnel] = {}
        self._transit: dict[str, Netns] = {}  # transit namespaces, by link name
        self.state: st.RunState | None = None
        # What carries the links (`links.choose_backend`), and the controller of the live
        # links; None when the caller chose plain ends itself (links not emulated).
        self.link_backend: links.BackendChoice | None = None
        self.control: links.LinkController | None = None
        self._children: list[subprocess.Popen[Any]] = []
        self._removed: Removed | None = None
        #: The GTP-U endpoints and tunnel routes (`testbed.topology.corepath.CorePath`, which
        #: builds on this module, so not imported here) of a scenario whose cells have a UPF.
        self.core: Any = None
        # Other threads' sockets into the nodes' namespaces (`Node.ns_here`).
        self._thread_ns: dict[tuple[int, str], Netns] = {}
        self._thread_lock = threading.Lock()

    def __getitem__(self, name: str) -> Node:
        return self.nodes[name]

    def __enter__(self) -> Net:
        return self

    def __exit__(self, *exc: object) -> None:
        self.teardown()

    # ---- which part is this host's -----------------------------------------------------

    def here(self, node: Node) -> bool:
        """Whether `node` is built by this process: every node, or this host's."""
        return self.host is None or node.host == self.host

    def local_nodes(self) -> list[Node]:
        return [n for n in self.nodes.values() if self.here(n)]

    def local_links(self) -> list[Link]:
        """The links whose two ends are here (made by the backend, as on one host)."""
        return [ln for ln in self.links.values() if self.here(ln.lower) and self.here(ln.upper)]

    def emulating_node(self, link: Link) -> Node:
        """The node at whose end `link` is emulated: the lower one's, where its relay runs
        (userspace), or the shaping end's, where its qdiscs sit (tc)."""
        if self.backend.name == "userspace":
            return link.lower
        return link.upper if shaping_end(link.kind) == "upper" else link.lower

    def emulates(self, link: str) -> bool:
        """Whether this process applies `link`'s emulation: every link's, or on one host of a
        topology across hosts those it holds the emulating end of."""
        return self.host is None or self.here(self.emulating_node(self.links[link]))

    # ---- resources other modules add ---------------------------------------------------

    def record_pid(self, pid: int, what: str = "") -> None:
        """Record a process that belongs to this run (teardown/clean stop it)."""
        if self.state is not None:
            self.state.record_pid(st.ProcessRef.of(pid, what))

    def adopt(self, proc: subprocess.Popen[Any], what: str = "") -> None:
        """Record a child process; teardown also reaps it."""
        self._children.append(proc)
        self.record_pid(proc.pid, what)

    def record_cgroup(self, path: str | os.PathLike[str]) -> None:
        """Record a cgroup directory BEFORE creating it; teardown/clean remove it."""
        if self.state is not None:
            self.state.record_cgroup(str(path))

    # ---- plan --------------------------------------------------------------------------

    def commands(self) -> list[str]:
        """The `ip` commands equivalent to what `build` does (what `--dry-run` prints)."""
        nodes = self.local_nodes()
        cmds = [f"ip netns add {n.netns}" for n in nodes]
        cmds += [f"ip netns add {t.transit.netns}" for t in self.tunnels.values() if t.transit]
        cmds += [f"ip -n {n.netns} link set lo up" for n in nodes]
        cmds += [
            f"ip -n {t.transit.netns} link set lo up" for t in self.tunnels.values() if t.transit
        ]
        for link in self.local_links():
            cmds += self.backend.commands(link.ends)
        for name, tunnel in self.tunnels.items():
            if tunnel.transit is not None:
                cmds += self.backend.commands(RelayLeg(self.links[name], tunnel.transit).ends)
            cmds += tunnel.commands()
        for node, ifname in self._local_ends():
            cmds.append(f"ip -n {node.netns} addr add {node.interfaces[ifname]} dev {ifname}")
            if ifname in node.mtus:
                cmds.append(f"ip -n {node.netns} link set {ifname} mtu {node.mtus[ifname]}")
            cmds.append(f"ip -n {node.netns} link set {ifname} up")
        for node in nodes:
            if node.ue_address is not None:
                dev = next(iter(node.interfaces))
                cmds.append(f"ip -n {node.netns} addr add {node.ue_address}/32 dev {dev}")
        for node in nodes:
            for r in node.routes:
                src = f" src {r.src}" if r.src else ""
                cmds.append(f"ip -n {node.netns} route add {r.dst} via {r.via} dev {r.dev}{src}")
        for node in nodes:
            if node.forwarding:
                cmds.append(f"ip netns exec {node.netns} sysctl -w net.ipv4.ip_forward=1")
        return cmds

    def _local_ends(self) -> list[tuple[Node, str]]:
        """(node, interface) of every link end in a namespace of this host's nodes: both ends
        of a local link, the near end of a link across hosts."""
        return [
            (node, ifname)
            for link in self.links.values()
            for node, ifname in ((link.lower, link.upper.name), (link.upper, link.lower.name))
            if self.here(node)
        ]

    # ---- realise -----------------------------------------------------------------------

    def _realise(self) -> None:
        tag = f"{OWNER_TAG}{self.state.path if self.state else '?'}"
        step = ""
        index: dict[tuple[str, str], int] = {}  # (node, ifname) -> ifindex, looked up once
        nodes = self.local_nodes()
        try:
            for node in nodes:
                step = f"creating namespace {node.netns}"
                node.ns = Netns.create(node.netns)
                # lo up, and tagged with the owning state file so `clean` run against another
                # state directory can tell this namespace is somebody's, not an orphan.
                node.ns.ipr.link("set", index=1, state="up", ifalias=tag)
            for name, tunnel in self.tunnels.items():
                if tunnel.transit is not None:
                    step = f"creating transit namespace {tunnel.transit.netns}"
                    ns = self._transit[name] = Netns.create(tunnel.transit.netns)
                    ns.ipr.link("set", index=1, state="up", ifalias=tag)
            for link in self.local_links():
                step = f"creating link {link.name} ({self.backend.name})"
                self.backend.create(link, self)
            step = f"waiting for the links' ends ({self.backend.name})"
            self.backend.settle()
            for name, tunnel in self.tunnels.items():
                link = self.links[name]
                if tunnel.transit is not None:
                    step = f"creating link {name}'s relay to {tunnel.transit.netns}"
                    self.backend.create(RelayLeg(link, tunnel.transit), self)
                    self.backend.settle()
                step = (
                    f"creating link {name}'s VXLAN tunnel (VNI {tunnel.vni}, {tunnel.local} to "
                    f"host {tunnel.peer_host} at {tunnel.remote}) in {tunnel.netns}"
                )
                near = link.lower if self.here(link.lower) else link.upper
                into = self._transit.get(name) or near._ns()
                vxlan.create(tunnel, into)
                if tunnel.transit is not None:
                    step = f"routing {tunnel.transit.netns} between the relay and the tunnel"
                    vxlan.configure_transit(tunnel, into)
                elif isinstance(self.backend, VethEnds):  # qdiscs on it: as on a veth end
                    into.ipr.link("set", index=into.ifindex(tunnel.ifname),
                                  gso_max_size=GSO_MAX_SIZE)  # fmt: skip
            for node, ifname in self._local_ends():
                step = f"configuring {ifname} in {node.netns}"
                ns = node._ns()
                idx = index[node.name, ifname] = ns.ifindex(ifname)
                addr = node.interfaces[ifname]
                ns.ipr.addr(
                    "add", index=idx, address=str(addr.ip), prefixlen=addr.network.prefixlen
                )
                if ifname in node.mtus:
                    ns.ipr.link("set", index=idx, mtu=node.mtus[ifname])
                ns.ipr.link("set", index=idx, state="up")
            for node in nodes:
                if node.ue_address is not None:
                    step = f"adding UE address {node.ue_address} in {node.netns}"
                    dev = next(iter(node.interfaces))  # a vehicle has its air interface
                    node._ns().ipr.addr(
                        "add", index=index[node.name, dev], address=str(node.ue_address),
                        prefixlen=32,
                    )  # fmt: skip
            for node in nodes:
                for r in node.routes:
                    step = f"adding route {r.dst} via {r.via} in {node.netns}"
                    dst = "0.0.0.0/0" if r.dst == "default" else r.dst
                    extra = {"prefsrc": str(r.src)} if r.src else {}
                    node._ns().ipr.route(
                        "add", dst=dst, gateway=str(r.via), oif=index[node.name, r.dev], **extra
                    )
            for node in nodes:
                if node.forwarding:
                    step = f"enabling forwarding in {node.netns}"
                    node._ns().write_sysctl("net.ipv4.ip_forward", "1")
        except PyNetlinkError as err:
            raise NetlinkError(f"{step}: the kernel said: {err.args[-1]}") from None
        except OSError as err:
            raise NetlinkError(f"{step}: {err.strerror or err}") from None

    # ---- teardown ----------------------------------------------------------------------

    def teardown(self) -> Removed:
        """Remove everything this run created (idempotent)."""
        if self._removed is not None:
            return self._removed
        if self.control is not None:
            self.control.close()  # helper threads first; a run's own relays stop with it
        if self.core is not None:
            self.core.close()  # its final counters; the processes are the run's anyway
        with self._thread_lock:
            for ns in self._thread_ns.values():
                ns.close()
            self._thread_ns.clear()
        if self.dry_run or self.state is None:
            self._removed = Removed(self.run_id)
            return self._removed
        removed = remove_run(self.state, children=self._children, open_ns=self._open_ns())
        for node in self.nodes.values():
            node.ns = None
        self._transit.clear()
        self._removed = removed
        return removed

    def vehicle_address(self, vehicle: str) -> IPv4Address:
        """The address a vehicle's applications use: its UE address behind a UPF, else its
        air link's."""
        node = self.nodes[vehicle]
        if node.ue_address is not None:
            return node.ue_address
        gnb = next(v.gnb for v in self.scenario.topology.vehicles if v.name == vehicle)
        return node.address_towards(gnb)

    def prepare_handover(self, vehicle: str) -> None:
        """Open, in the calling thread, the sockets `hand_over` will use for `vehicle`, so
        that a handover on time costs no socket set-up."""
        self.nodes[vehicle].ns_here()
        if self.core is not None:
            upf = next(s.upf for s in self.core.sessions if s.vehicle == vehicle)
            self.nodes[upf].ns_here()

    def hand_over(self, vehicle: str, target: str) -> None:
        """Move `vehicle`'s traffic to gNB `target` (a handover; the vehicle has an air link
        to it): its default route goes through the target's link, and, on the core path,
        its UPF's route into the target's N3 tunnel (the path switch). The gNBs' routes to
        the UE are there from the start (`corepath`: sessions prepared at every gNB)."""
        node = self.nodes[vehicle]
        ns = node.ns_here()
        via = self.links[f"{vehicle}-{target}"].addresses.upper.ip
        extra = {"prefsrc": str(node.ue_address)} if node.ue_address is not None else {}
        try:
            ns.ipr.route(
                "replace", dst="0.0.0.0/0", gateway=str(via), oif=ns.ifindex(target), **extra
            )
        except PyNetlinkError as err:
            raise NetlinkError(
                f"moving {vehicle}'s default route to {target} in {node.netns}: the kernel "
                f"said: {err.args[-1]}"
            ) from None
        if self.core is not None:
            self.core.switch(vehicle, target)

    def server_address(self, cell: Cell) -> IPv4Address:
        """The edge server's address that the cell's vehicles reach it at."""
        server = self.nodes[cell.server]
        if not cell.tunnelled:
            return server.address_towards(cell.gnb)
        return server.address_towards(cell.gnb if cell.placement == "cell" else cell.uplink_peer)

    def backend_text(self) -> str:
        """The link backend as run.json and `testbed up` name it."""
        if self.link_backend is None:
            return f"none (plain {self.backend.name}, links not emulated)"
        return self.link_backend.describe()

    def _open_ns(self) -> list[Netns]:
        return [n.ns for n in self.nodes.values() if n.ns is not None] + list(
            self._transit.values()
        )
