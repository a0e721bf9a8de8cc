"""The emulated network of a run: one namespace per node, one link per vehicle–gNB and gNB–core
pair, addresses, routes, forwarding — built, torn down, and cleaned up after crashes.

Nouns (Mininet-like):
- `Node`: a vehicle, gNB or core, living in its own namespace `el-<runid>-<name>`. It can open
  sockets inside its namespace (`node.socket()`), step a thread into it (`node.entered()`),
  start processes there (`node.popen(argv)`, via nsenter) and hands out its netlink socket
  (`node.ipr`) to whoever configures it further (qdiscs, TUN devices).
- `Link`: two nodes, a /30, and the two interfaces (each named after the peer node) that a
  `LinkEnds` backend creates (`VethEnds` by default).
- `Net`: the whole run: nodes, links, the pool, the state file. A context manager:
  `with build(scenario, mode="run") as net: ...` tears everything down on exit, exceptions and
  Ctrl-C included.
- `build`, `teardown_run`, `clean`: what `testbed up`, `down` and `clean` call.

Routing: a vehicle's default route goes via its gNB; a core routes the whole pool via its gNB;
a gNB only has connected routes and is the only node with ip_forward=1. Cells do not route to
each other (a vehicle reaches its own cell's core; vehicles of one cell reach each other).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from ipaddress import IPv4Address, IPv4Interface, IPv4Network
from pathlib import Path
from typing import Any, Literal

from pyroute2 import IPRoute
from pyroute2.netlink.exceptions import NetlinkError as PyNetlinkError

from netem.errors import NetlinkError
from netem.netns import delete_netns, list_netns, netns_identity, netns_path
from netem.profile import LinkProfile
from nodes.ros.env import domain_id_for
from testbed import cgroups, check, links
from testbed import state as st
from testbed.addressing import LinkAddresses, assign, choose_pool, host_networks
from testbed.errors import BadInput, TestbedError
from testbed.namespaces import EndNames, LinkEnds, Netns, VethEnds, require_root
from testbed.scenario.model import Cell, Links, LinkSpec, Role, Scenario, Topology, Vehicle
from testbed.scenario.schema_v1 import NODE_NAME_PATTERN

NODE_NAME_RE = re.compile(NODE_NAME_PATTERN)  # the schema's: one pattern for names
NETNS_PREFIX = "el-"
RUN_NETNS_RE = re.compile(r"^el-([0-9a-f]{6})-")
OWNER_TAG = "edgeloc-testbed state="  # lo's alias in each namespace: which state file owns it
STOP_GRACE_S = 0.5  # SIGTERM, then SIGKILL after this long

Echo = Callable[[str], None]


def netns_name(run_id: str, node: str) -> str:
    return f"{NETNS_PREFIX}{run_id}-{node}"


# ---- the parts of a network ----------------------------------------------------------------


@dataclass(frozen=True)
class Route:
    """`dst` ('default' or a network) via `via` out of interface `dev`."""

    dst: str
    via: IPv4Address
    dev: str


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

    def _ns(self) -> Netns:
        if self.ns is None:
            raise TestbedError(f"node {self.name} has no namespace (dry run or torn down)")
        return self.ns


@dataclass(eq=False)
class Link:
    """Two nodes joined by a /30; `lower` is the vehicle (air) or the gNB (backhaul)."""

    name: str
    kind: Literal["air", "backhaul"]
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


@dataclass
class Removed:
    """What a teardown removed."""

    run_id: str
    namespaces: int = 0
    processes: int = 0
    cgroups: int = 0
    problems: list[str] = field(default_factory=list)

    def summary(self) -> str:
        text = (
            f"{self.namespaces} namespace(s), {self.processes} process(es), "
            f"{self.cgroups} cgroup(s) removed"
        )
        if self.problems:
            text += "; could not remove: " + "; ".join(self.problems)
        return text


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
    ) -> None:
        self.scenario = scenario
        self.run_id = run_id
        self.pool = pool
        self.mode = mode
        self.backend = backend
        self.dry_run = dry_run
        self.nodes: dict[str, Node] = {}
        self.links: dict[str, Link] = {}
        self.state: st.RunState | None = None
        # What carries the links (`links.choose_backend`), and the controller of the live
        # links; None when the caller chose plain ends itself (links not emulated).
        self.link_backend: links.BackendChoice | None = None
        self.control: links.LinkController | None = None
        self._children: list[subprocess.Popen[Any]] = []
        self._removed: Removed | None = None

    def __getitem__(self, name: str) -> Node:
        return self.nodes[name]

    def __enter__(self) -> Net:
        return self

    def __exit__(self, *exc: object) -> None:
        self.teardown()

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
        cmds = [f"ip netns add {n.netns}" for n in self.nodes.values()]
        cmds += [f"ip -n {n.netns} link set lo up" for n in self.nodes.values()]
        for link in self.links.values():
            cmds += self.backend.commands(link.ends)
        for link in self.links.values():
            for node, ifname in ((link.lower, link.upper.name), (link.upper, link.lower.name)):
                cmds.append(f"ip -n {node.netns} addr add {node.interfaces[ifname]} dev {ifname}")
                cmds.append(f"ip -n {node.netns} link set {ifname} up")
        for node in self.nodes.values():
            for r in node.routes:
                cmds.append(f"ip -n {node.netns} route add {r.dst} via {r.via} dev {r.dev}")
        for node in self.nodes.values():
            if node.forwarding:
                cmds.append(f"ip netns exec {node.netns} sysctl -w net.ipv4.ip_forward=1")
        return cmds

    # ---- realise -----------------------------------------------------------------------

    def _realise(self) -> None:
        tag = f"{OWNER_TAG}{self.state.path if self.state else '?'}"
        step = ""
        index: dict[tuple[str, str], int] = {}  # (node, ifname) -> ifindex, looked up once
        try:
            for node in self.nodes.values():
                step = f"creating namespace {node.netns}"
                node.ns = Netns.create(node.netns)
                # lo up, and tagged with the owning state file so `clean` run against another
                # state directory can tell this namespace is somebody's, not an orphan.
                node.ns.ipr.link("set", index=1, state="up", ifalias=tag)
            for link in self.links.values():
                step = f"creating link {link.name} ({self.backend.name})"
                self.backend.create(link, self)
            for link in self.links.values():
                for node, ifname in ((link.lower, link.upper.name), (link.upper, link.lower.name)):
                    step = f"configuring {ifname} in {node.netns}"
                    ns = node._ns()
                    idx = index[node.name, ifname] = ns.ifindex(ifname)
                    addr = node.interfaces[ifname]
                    ns.ipr.addr(
                        "add", index=idx, address=str(addr.ip), prefixlen=addr.network.prefixlen
                    )
                    ns.ipr.link("set", index=idx, state="up")
            for node in self.nodes.values():
                for r in node.routes:
                    step = f"adding route {r.dst} via {r.via} in {node.netns}"
                    dst = "0.0.0.0/0" if r.dst == "default" else r.dst
                    node._ns().ipr.route(
                        "add", dst=dst, gateway=str(r.via), oif=index[node.name, r.dev]
                    )
            for node in self.nodes.values():
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
        if self.dry_run or self.state is None:
            self._removed = Removed(self.run_id)
            return self._removed
        removed = _remove_run(self.state, children=self._children, open_ns=self._open_ns())
        for node in self.nodes.values():
            node.ns = None
        self._removed = removed
        return removed

    def backend_text(self) -> str:
        """The link backend as run.json and `testbed up` name it."""
        if self.link_backend is None:
            return f"none (plain {self.backend.name}, links not emulated)"
        return self.link_backend.describe()

    def _open_ns(self) -> list[Netns]:
        return [n.ns for n in self.nodes.values() if n.ns is not None]


# ---- plan ----------------------------------------------------------------------------------


def _check_names(scenario: Scenario) -> None:
    """The loader checks these too; repeat the few that would make unsafe names here."""
    topo = scenario.topology
    names = topo.node_names()
    for name in names:
        if not NODE_NAME_RE.match(name):
            raise BadInput(
                f"node name {name!r} must match {NODE_NAME_PATTERN} "
                "(it becomes an interface and namespace name)"
            )
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise BadInput(f"node names must be unique; repeated: {', '.join(dupes)}")
    gnbs = {c.gnb for c in topo.cells}
    for v in topo.vehicles:
        if v.gnb not in gnbs:
            raise BadInput(f"vehicle {v.name} attaches to unknown gNB {v.gnb!r}")
    if not topo.vehicles or not topo.cells:
        raise BadInput("a topology needs at least one vehicle and one cell")


def _link_pairs(scenario: Scenario) -> list[tuple[str, Literal["air", "backhaul"], str, str]]:
    """(name, kind, lower, upper) for every link: backhauls first, so adding vehicles never
    moves a backhaul's addresses."""
    topo = scenario.topology
    pairs: list[tuple[str, Literal["air", "backhaul"], str, str]] = [
        (f"{c.gnb}-{c.core}", "backhaul", c.gnb, c.core) for c in topo.cells
    ]
    pairs += [(f"{v.name}-{v.gnb}", "air", v.name, v.gnb) for v in topo.vehicles]
    return pairs


def plan(
    scenario: Scenario,
    run_id: str,
    pool: IPv4Network,
    mode: st.Mode = "up",
    backend: LinkEnds | None = None,
    dry_run: bool = True,
) -> Net:
    """The Net a scenario asks for, fully addressed and routed, with nothing created yet."""
    _check_names(scenario)
    net = Net(scenario, run_id, pool, mode, backend or VethEnds(), dry_run)
    topo = scenario.topology
    for name in topo.node_names():
        net.nodes[name] = Node(name, topo.role_of(name), netns_name(run_id, name), net)
    pairs = _link_pairs(scenario)
    addrs = assign(pool, [p[0] for p in pairs])
    specs = {s.name: s for s in scenario.links.links}
    for name, kind, lower, upper in pairs:
        a = addrs[name]
        link = Link(name, kind, net.nodes[lower], net.nodes[upper], a, specs.get(name))
        net.links[name] = link
        link.lower.interfaces[upper] = a.lower
        link.upper.interfaces[lower] = a.upper
    for v in topo.vehicles:
        gnb_addr = net.links[f"{v.name}-{v.gnb}"].addresses.upper.ip
        net.nodes[v.name].routes.append(Route("default", gnb_addr, v.gnb))
    for c in topo.cells:
        gnb_addr = net.links[f"{c.gnb}-{c.core}"].addresses.lower.ip
        net.nodes[c.core].routes.append(Route(str(pool), gnb_addr, c.gnb))
        net.nodes[c.gnb].forwarding = True
    return net


# ---- build ---------------------------------------------------------------------------------


def _live_pools(runs: list[st.RunState]) -> dict[str, IPv4Network]:
    return {r.run_id: IPv4Network(r.pool) for r in runs if r.pool and r.liveness() != "dead"}


def _ids_in_use(runs: list[st.RunState]) -> set[str]:
    ids = {r.run_id for r in runs}
    for name in list_netns():
        m = RUN_NETNS_RE.match(name)
        if m:
            ids.add(m.group(1))
    return ids


def build(
    scenario: Scenario,
    dry_run: bool = False,
    echo: Echo | None = None,
    run_id: str | None = None,
    mode: st.Mode = "up",
    backend: LinkEnds | None = None,
) -> Net:
    """Build the scenario's network and return it.

    `mode="up"`: left running after this process exits (`testbed up`; the run becomes
    'detached'); `mode="run"`: owned by this process (dead if it dies). `dry_run` creates and
    records nothing and passes each equivalent `ip` and `tc` command (and relay command line)
    to `echo`. If building fails or is interrupted, everything created so far is removed
    before the error propagates.

    Links: with `backend=None` the scenario's `links.backend` decides (`links.choose_backend`)
    and every link's profiles are applied once the network is up (`net.control` then changes
    them live). An explicit `backend` (plain `VethEnds` in topology tests and benchmarks)
    builds those ends as they are, unshaped.
    """
    if run_id is not None and not st.RUN_ID_RE.match(run_id):
        raise BadInput(f"run id {run_id!r} must be 6 lowercase hex characters")
    if not dry_run:
        require_root()
    _check_names(scenario)
    choice: links.BackendChoice | None = None
    if backend is None:
        choice = links.choose_backend(scenario)
        backend = links.ends_for(choice, mode, scenario)
    n_links = len(_link_pairs(scenario))
    source = str(scenario.source) if scenario.source else None
    with st.locked() if not dry_run else contextlib.nullcontext():
        runs = st.list_runs()
        in_use = _ids_in_use(runs)
        if run_id is None:
            # A ROS domain of its own too: runs are apart by namespaces already, but a stray
            # process started with a run's environment must not meet another run's nodes.
            run_id = st.fresh_run_id(in_use, key=domain_id_for)
        elif run_id in in_use:
            raise BadInput(f"run id {run_id} is already in use (testbed status lists runs)")
        pool = choose_pool(
            scenario.topology.address_pool, n_links, host_networks(), _live_pools(runs)
        )
        net = plan(scenario, run_id, pool, mode, backend, dry_run)
        net.link_backend = choice
        if dry_run:
            lines = net.commands()
            if choice is not None and choice.name == "tc":  # relays start with their profiles
                net.control = links.controller_for(net)
                net.control.apply()
                lines += net.control.commands()
            for line in lines:
                if echo is not None:
                    echo(line)
            return net
        # Write-ahead: every namespace is on file before the first one exists.
        net.state = st.new_run(scenario.name, source, mode, run_id, str(pool))
        net.state.record_namespaces([n.netns for n in net.nodes.values()])
    try:
        if choice is not None:
            links.write_backend(run_id, choice)
        net._realise()
        if choice is not None:
            net.control = links.controller_for(net)
            net.control.apply()
        net.state.set_phase("up")
    except BaseException:
        net.teardown()
        raise
    return net


# ---- teardown, down, clean -----------------------------------------------------------------


def _processes_in(identities: set[tuple[int, int]]) -> list[st.ProcessRef]:
    """Every process (but us) whose network namespace is one of `identities`."""
    found = []
    me = os.getpid()
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == me:
            continue
        try:
            s = os.stat(f"/proc/{entry}/ns/net")
        except OSError:
            continue
        if (s.st_dev, s.st_ino) in identities:
            found.append(st.ProcessRef.of(int(entry), "in namespace"))
    return found


def _stop(refs: Sequence[st.ProcessRef], children: Sequence[subprocess.Popen[Any]] = ()) -> int:
    """SIGTERM the processes that are still the ones recorded, SIGKILL what is left after a
    grace period, reap our own children. Returns how many were running."""
    alive = [r for r in refs if r.alive()]
    for r in alive:
        with contextlib.suppress(ProcessLookupError):
            os.kill(r.pid, signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    pending = list(alive)
    while pending and time.monotonic() < deadline:
        for c in children:
            c.poll()  # reap, so a dead child stops looking alive
        pending = [r for r in pending if r.alive()]
        if pending:
            time.sleep(0.01)
    for r in pending:
        if r.alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(r.pid, signal.SIGKILL)
    for c in children:
        with contextlib.suppress(subprocess.TimeoutExpired):
            c.wait(timeout=STOP_GRACE_S)
    return len(alive)


#: How long `clean` waits for killed tasks to be reaped before a cgroup counts as stuck.
CGROUP_RMDIR_WAIT_S = 5.0


def _remove_cgroup(path: str) -> str | None:
    """rmdir a recorded cgroup after killing what is in it; only under /sys/fs/cgroup."""
    p = Path(path)
    if not p.is_absolute() or Path("/sys/fs/cgroup") not in p.parents:
        return f"cgroup {path} (not under /sys/fs/cgroup; left alone)"
    if not p.is_dir():
        return None
    # children first (a backend may nest), then this one
    for sub in sorted((d for d in p.rglob("*") if d.is_dir()), key=lambda d: -len(d.parts)):
        problem = _remove_cgroup(str(sub))
        if problem:
            return problem
    try:
        pids = [int(x) for x in (p / "cgroup.procs").read_text().split()]
    except OSError:
        pids = []
    _stop([st.ProcessRef.of(pid, "in cgroup") for pid in pids])
    # A killed task keeps its cgroup busy until it is reaped (kernels >= 5.0 keep zombies in
    # their cgroup); an orphan waits for init to reap it, so give that a moment.
    deadline = time.monotonic() + CGROUP_RMDIR_WAIT_S
    while True:
        try:
            p.rmdir()
            return None
        except OSError as err:
            if err.errno != errno.EBUSY or time.monotonic() > deadline:
                return f"cgroup {path} ({err.strerror})"
        time.sleep(0.05)


def _remove_namespaces(names: Sequence[str], removed: Removed, open_ns: Sequence[Netns]) -> None:
    identities = {i for i in (netns_identity(n) for n in names) if i is not None}
    # Link relays live in the host namespace with TUN ends in ours: found by command line.
    relays = [st.ProcessRef.of(pid, "link relay") for pid in links.relay_pids(list(names))]
    if identities or relays:
        removed.processes += _stop([*(_processes_in(identities) if identities else []), *relays])
    for ns in open_ns:
        ns.close()  # our sockets keep a namespace alive after it is unregistered
    for name in names:
        try:
            if delete_netns(name):
                removed.namespaces += 1
        except OSError as err:
            removed.problems.append(f"namespace {name} ({err.strerror})")


def _remove_run(
    state: st.RunState,
    children: Sequence[subprocess.Popen[Any]] = (),
    open_ns: Sequence[Netns] = (),
) -> Removed:
    """Remove exactly what `state` records, then its state file (kept if something stayed)."""
    removed = Removed(state.run_id)
    if state.path.exists():
        state.set_phase("tearing-down")
    removed.processes += _stop(state.pids, children)
    _remove_namespaces(state.namespaces, removed, open_ns)
    for cg in reversed(state.cgroups):
        problem = _remove_cgroup(cg)
        if problem:
            removed.problems.append(problem)
        elif not Path(cg).exists():
            removed.cgroups += 1
    # The run's cgroup parent (`edgeloc/<run>`) is not recorded itself; remove the whole tree.
    removed.cgroups += len(cgroups.remove_all(state.run_id))
    links.remove_link_state(state.run_id)  # relay sockets and logs
    if not removed.problems:
        state.delete()
    return removed


def _describe_runs(runs: Sequence[st.RunState]) -> str:
    return ", ".join(f"{r.run_id} ({r.liveness()}, {r.scenario})" for r in runs) or "none"


def teardown_run(run_id: str | None) -> Removed:
    """`testbed down`: tear down one run (default: the only one that is not dead)."""
    require_root()
    runs = st.list_runs()
    alive = [r for r in runs if r.liveness() != "dead"]
    if run_id is None:
        if not alive:
            dead = [r for r in runs if r.liveness() == "dead"]
            hint = (
                f" (dead runs: {_describe_runs(dead)}; `testbed clean` removes them)"
                if dead
                else ""
            )
            raise BadInput("no live run to tear down" + hint)
        if len(alive) > 1:
            raise BadInput(
                f"several live runs: {_describe_runs(alive)}; name one: testbed down <run id>"
            )
        target = alive[0]
    else:
        found = [r for r in runs if r.run_id == run_id]
        if not found:
            raise BadInput(f"no run {run_id!r}; live runs: {_describe_runs(alive)}")
        target = found[0]
    if target.liveness() == "live" and target.owner.pid != os.getpid():
        raise BadInput(
            f"run {target.run_id} is being used by process {target.owner.pid} "
            f"({target.mode}, {target.phase}); stop that process (Ctrl-C) instead"
        )
    return _remove_run(target)


def _owner_tag(name: str) -> str | None:
    """The state file path written on lo of a run namespace, or None if it carries none."""
    try:
        ns = Netns.open(name)
    except OSError:
        return None
    try:
        links = ns.ipr.get_links(1)
        alias = links[0].get_attr("IFLA_IFALIAS") if links else None
    except PyNetlinkError:
        alias = None
    finally:
        ns.close()
    if alias and alias.startswith(OWNER_TAG):
        return alias[len(OWNER_TAG) :]
    return None


def _is_orphan(name: str, claimed: set[str]) -> bool:
    """A run-named namespace that no state file owns: none of ours claims it, and its owner tag
    (if any) names a state file that no longer exists."""
    if name in claimed or not RUN_NETNS_RE.match(name):
        return False
    owner = _owner_tag(name)
    return owner is None or not Path(owner).exists()


def clean(include_detached: bool = False) -> str:
    """`testbed clean`: remove dead runs (and detached ones with `include_detached`), then
    namespaces named like ours that no state file claims. Never touches anything else."""
    require_root()
    runs = st.list_runs()
    targets = [
        r
        for r in runs
        if r.liveness() == "dead" or (include_detached and r.liveness() == "detached")
    ]
    totals = Removed("*")
    for run in targets:
        r = _remove_run(run)
        totals.namespaces += r.namespaces
        totals.processes += r.processes
        totals.cgroups += r.cgroups
        totals.problems += r.problems
    claimed = {n for r in st.list_runs() for n in r.namespaces}
    orphans = [n for n in list_netns() if _is_orphan(n, claimed)]
    orphan_removed = Removed("orphans")
    _remove_namespaces(orphans, orphan_removed, ())
    totals.processes += orphan_removed.processes
    totals.problems += orphan_removed.problems
    # Budget trees of runs that neither a state file nor a namespace claims any more.
    live_ids = {r.run_id for r in st.list_runs()} | {
        m.group(1) for n in list_netns() if (m := RUN_NETNS_RE.match(n))
    }
    for run_id in cgroups.run_ids():
        if st.RUN_ID_RE.match(run_id) and run_id not in live_ids:
            totals.cgroups += len(cgroups.remove_all(run_id))
    preflight = check.remove_leftovers()  # what a SIGKILLed `testbed check` left
    _remove_stale_temp_files()
    left = [r for r in st.list_runs() if r.liveness() == "detached"]
    text = (
        f"cleaned {len(targets)} run(s), {orphan_removed.namespaces} orphan namespace(s) and "
        f"{len(preflight)} preflight leftover(s): " + totals.summary()
    )
    if left:
        text += (
            f"; {len(left)} detached run(s) left up ({', '.join(r.run_id for r in left)}): "
            "`testbed clean --all` or `testbed down <id>` removes them"
        )
    return text


def _remove_stale_temp_files() -> None:
    """Temp files of state writes interrupted by a kill (`.<id>.json.<pid>.tmp`)."""
    directory = st.state_dir()
    if not directory.is_dir():
        return
    for tmp in directory.glob(".*.json.*.tmp"):
        pid = tmp.name.split(".")[-2]
        if pid.isdigit() and st.proc_start_time(int(pid)) is None:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()


def example_scenario(
    vehicles: int = 1, cells: int = 1, name: str = "example", pool: IPv4Network | None = None
) -> Scenario:
    """A minimal scenario: `vehicles` vehicles (av1, av2, ...) spread round-robin over `cells`
    cells (gnb1/core1, ...), unshaped links. For benchmarks, tests and demos."""
    cell_list = tuple(Cell(f"gnb{i + 1}", f"core{i + 1}") for i in range(cells))
    vehicle_list = tuple(Vehicle(f"av{i + 1}", cell_list[i % cells].gnb) for i in range(vehicles))
    topo = Topology(vehicle_list, cell_list, pool)
    flat = LinkProfile()
    specs = [
        LinkSpec(f"{c.gnb}-{c.core}", "backhaul", c.gnb, c.core, flat, flat) for c in cell_list
    ]
    specs += [LinkSpec(f"{v.name}-{v.gnb}", "air", v.name, v.gnb, flat, flat) for v in vehicle_list]
    return Scenario(name, 0, 60.0, topo, Links("auto", tuple(specs)))
