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
from testbed.scenario.patterns import NODE_NAME_PATTERN
from testbed.topology.model import Link, Net, Node, Route
from testbed.topology.names import NODE_NAME_RE, netns_name, transit_netns_name
from testbed.topology.vxlan import Transit, Tunnel, vnis

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


def check_host(scenario: Scenario, host: str | None) -> None:
    """`host` (one host's part of the topology) must be one of `topology.hosts`."""
    if host is None:
        return
    names = [h.name for h in scenario.topology.hosts]
    where = f"{scenario.source}: " if scenario.source is not None else ""
    if not names:
        raise BadInput(
            f"--host {host}: {where}the scenario has no topology.hosts, so all of it is built on "
            "one host; leave --host out"
        )
    if host not in names:
        raise BadInput(f"--host {host}: {where}topology.hosts has {', '.join(names)}, not {host}")


def plan(
    scenario: Scenario,
    run_id: str,
    pool: IPv4Network,
    mode: st.Mode = "up",
    backend: LinkEnds | None = None,
    dry_run: bool = True,
    host: str | None = None,
) -> Net:
    """The Net a scenario asks for, fully addressed and routed, with nothing created yet.

    With `host` (a topology across hosts), the plan is still the whole topology, so that
    addresses and routes are the same on every host, but only that host's nodes are built and
    its ends of the links to other hosts are tunnels (`Net.tunnels`)."""
    check_names(scenario)
    check_host(scenario, host)
    net = Net(scenario, run_id, pool, mode, backend or VethEnds(), dry_run, host)
    topo = scenario.topology
    for name in topo.node_names():
        node = Node(name, topo.role_of(name), netns_name(run_id, name), net)
        node.host = topo.host_of(name)
        net.nodes[name] = node
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
    net.tunnels = plan_tunnels(net, relay=net.backend.name == "userspace")
    return net


def plan_tunnels(net: Net, relay: bool) -> dict[str, Tunnel]:
    """This host's tunnels: one per link with one end here and the other on another host.
    `relay`: the links are the userspace backend's, so the lower node's host emulates each
    through a transit namespace. Empty when the net is not one host's part."""
    if net.host is None:
        return {}
    topo = net.scenario.topology
    across = [link for link in net.links.values() if link.lower.host != link.upper.host]
    numbers = vnis(net.run_id, [link.name for link in across])
    out: dict[str, Tunnel] = {}
    for link in across:
        near, far = (link.lower, link.upper) if net.here(link.lower) else (link.upper, link.lower)
        if not net.here(near):
            continue  # both ends on other hosts: theirs to build
        assert near.host is not None and far.host is not None
        transit = None
        if relay and near is link.lower:
            transit = Transit(
                transit_netns_name(net.run_id, link.name), link.lower.name, link.addresses.upper.ip
            )
        out[link.name] = Tunnel(
            link=link.name,
            vni=numbers[link.name],
            local=topo.host(near.host).address,
            remote=topo.host(far.host).address,
            peer_host=far.host,
            netns=transit.netns if transit is not None else near.netns,
            ifname=far.name,
            transit=transit,
        )
    return out


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
