"""Planning a run's network from a scenario: names checked, the address pool chosen, nodes,
links, addresses and routes decided, nothing built (what `--dry-run` prints)."""

from __future__ import annotations

from ipaddress import IPv4Address, IPv4Network

from netem.profile import LinkProfile
from testbed import state as st
from testbed.addressing import assign
from testbed.errors import BadInput
from testbed.namespaces import LinkEnds, VethEnds
from testbed.scenario.model import Cell, LinkKind, Links, LinkSpec, Scenario, Topology, Vehicle
from testbed.scenario.schema_v1 import NODE_NAME_PATTERN
from testbed.topology.model import Link, Net, Node, Route
from testbed.topology.names import NODE_NAME_RE, netns_name

# ---- plan ----------------------------------------------------------------------------------


def check_names(scenario: Scenario) -> None:
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


def link_pairs(scenario: Scenario) -> list[tuple[str, LinkKind, str, str]]:
    """(name, kind, lower, upper) for every link: the cells' wired links first (a link that
    cells share, like one UPF's N6 to one edge, once), so adding vehicles never moves their
    addresses."""
    topo = scenario.topology
    pairs: list[tuple[str, LinkKind, str, str]] = []
    seen: set[str] = set()
    for c in topo.cells:
        for pair in c.wired():
            if pair[0] not in seen:
                seen.add(pair[0])
                pairs.append(pair)
    pairs += [(f"{v.name}-{v.gnb}", "air", v.name, v.gnb) for v in topo.vehicles]
    # With handovers, each vehicle's links to the other gNBs (after every first link, so a
    # scenario's addresses stay as they were without them).
    pairs += [
        (f"{v.name}-{g}", "air", v.name, g) for v in topo.vehicles for g in scenario.gnbs_of(v)[1:]
    ]
    return pairs


def ue_addresses(topo: Topology) -> dict[str, IPv4Address]:
    """Each vehicle of a cell with a UPF, its address in the UE pool, in the order the
    vehicles are written, from the pool's second host up: the first is the UPF's own, as
    Open5GS gives its `ogstun` 10.45.0.1 and its UEs 10.45.0.2 on."""
    hosts = topo.ue_pool.hosts()
    next(hosts)
    tunnelled = {c.gnb for c in topo.cells if c.tunnelled}
    return {v.name: next(hosts) for v in topo.vehicles if v.gnb in tunnelled}


def plan(
    scenario: Scenario,
    run_id: str,
    pool: IPv4Network,
    mode: st.Mode = "up",
    backend: LinkEnds | None = None,
    dry_run: bool = True,
) -> Net:
    """The Net a scenario asks for, fully addressed and routed, with nothing created yet."""
    check_names(scenario)
    net = Net(scenario, run_id, pool, mode, backend or VethEnds(), dry_run)
    topo = scenario.topology
    for name in topo.node_names():
        net.nodes[name] = Node(name, topo.role_of(name), netns_name(run_id, name), net)
    pairs = link_pairs(scenario)
    addrs = assign(pool, [p[0] for p in pairs])
    specs = {s.name: s for s in scenario.links.links}
    for name, kind, lower, upper in pairs:
        a = addrs[name]
        link = Link(name, kind, net.nodes[lower], net.nodes[upper], a, specs.get(name))
        net.links[name] = link
        link.lower.interfaces[upper] = a.lower
        link.upper.interfaces[lower] = a.upper
    ues = ue_addresses(topo)
    for v in topo.vehicles:
        gnb_addr = net.links[f"{v.name}-{v.gnb}"].addresses.upper.ip
        node = net.nodes[v.name]
        node.ue_address = ues.get(v.name)
        if node.ue_address is not None:
            node.mtus[v.gnb] = topo.ue_mtu
        node.routes.append(Route("default", gnb_addr, v.gnb, node.ue_address))
    for c in topo.cells:
        net.nodes[c.gnb].forwarding = True
        if not c.tunnelled:
            assert c.core is not None
            gnb_addr = net.links[f"{c.gnb}-{c.core}"].addresses.lower.ip
            net.nodes[c.core].routes.append(Route(str(pool), gnb_addr, c.gnb))
            continue
        # The tunnels' own routes (UE traffic into the gNB's and the UPF's TUN devices) come
        # with the GTP-U endpoints (`testbed.topology.corepath`); here the plain ones.
        upf, edge = net.nodes[c.uplink_peer], net.nodes[c.server]
        upf.forwarding = True
        near = c.gnb if c.placement == "cell" else c.uplink_peer  # the edge's N6 peer
        n6 = net.links[f"{near}-{c.server}"]
        route = Route(str(topo.ue_pool), n6.addresses.lower.ip, near)
        if route not in edge.routes:
            edge.routes.append(route)
    return net


def example_scenario(
    vehicles: int = 1, cells: int = 1, name: str = "example", pool: IPv4Network | None = None
) -> Scenario:
    """A minimal scenario: `vehicles` vehicles (av1, av2, ...) spread round-robin over `cells`
    cells (gnb1/core1, ...), unshaped links. For benchmarks, tests and demos."""
    cell_list = tuple(Cell(f"gnb{i + 1}", f"core{i + 1}") for i in range(cells))
    vehicle_list = tuple(Vehicle(f"av{i + 1}", cell_list[i % cells].gnb) for i in range(vehicles))
    topo = Topology(vehicle_list, cell_list, pool)
    flat = LinkProfile()
    specs = [LinkSpec(*pair, flat, flat) for c in cell_list for pair in c.wired()]
    specs += [LinkSpec(f"{v.name}-{v.gnb}", "air", v.name, v.gnb, flat, flat) for v in vehicle_list]
    return Scenario(name, 0, 60.0, topo, Links("auto", tuple(specs)))
