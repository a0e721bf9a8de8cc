"""The topology's rules: the names of nodes and links, defined once and referred to correctly.

`topology:` names the nodes (vehicles, gNBs, cores, UPFs and edge servers), each name once
across all of them; the parts that check out give the links their names (`vehicle-gnb`,
`gnb-core`, ...), against which the later sections' references are checked (`check_node`,
`check_link`, `check_links_named`). Besides: a cell has a core, or a UPF and an edge; an edge
server shared by cells sits in one place; the address pool has room for the links and stays
apart from the UE pool; QoS rules name the sessions' flows; `topology.hosts` gives each host an
underlay address of its own and each node one host, and an air link with a radio stays on one.
"""

from __future__ import annotations

import dataclasses
import ipaddress
from collections.abc import Callable
from typing import Any

from yaml.nodes import Node

from testbed.scenario import channel, model, schema_v1
from testbed.scenario.building import Builder
from testbed.scenario.issues import did_you_mean
from testbed.scenario.kinds import Items, Section, item

#: Names of this scenario (nodes, links, splits) are short words, so a misspelt one is matched
#: more loosely than a key of the schema (`kinds.SPELLING_CUTOFF`).
NAME_CUTOFF = 0.5


def listing(names: list[str], limit: int = 8) -> str:
    """`names` for a message: the first `limit` of them, or "none"."""
    shown = names[:limit] + (["..."] if len(names) > limit else [])
    return ", ".join(shown) if shown else "none"


ROLE_TEXT = {"core": "a core", "upf": "a UPF", "edge": "an edge server", "vehicle": "a vehicle"}


def _edge_name(cell: Section) -> str | None:
    """A cell's edge server, written as a name or as {name, placement}."""
    edge = cell.get("edge")
    return edge.get("name") if isinstance(edge, Section) else edge


def build(b: Builder) -> model.Topology | None:
    """The `Topology`, or None when a part is wrong (reported). On the way it records the
    names of the nodes (`b.roles`) and of the links (`b.link_kinds`) later sections name."""
    topo: Section | None = b.root.get("topology")
    if topo is None:
        return None
    cells: Items | None = topo.get("cells")
    vehicles: Items | None = topo.get("vehicles")
    first: dict[str, tuple[str, Node]] = {}  # name -> (path, node) where first defined

    def define(section: Section, key: str, role: str, name: str | None = None) -> None:
        name = section.get(key) if name is None else name
        if not isinstance(name, str):
            return  # not written, or an edge mapping without its name (the schema said so)
        if name in first and role in ("upf", "edge") and b.roles.get(name) == role:
            return  # cells may share one UPF and one edge server
        if name in first:
            where, node = first[name]
            b.ctx.add(
                section.at(key),
                section.path_of(key),
                "a name not used by another node (names are unique across vehicles, "
                "gNBs and cores)",
                f"{name!r}, already used at {where} (line {node.start_mark.line + 1})",
                "names become namespace and interface names, so each must be unique",
            )
            return
        first[name] = (section.path_of(key), section.at(key))
        b.roles[name] = role

    for _, cell, _ in cells.good() if cells else ():
        define(cell, "gnb", "gnb")
        define(cell, "core", "core")
        define(cell, "upf", "upf")
        define(cell, "edge", "edge", _edge_name(cell))
        _check_cell_form(b, cell)
    _check_shared_edges(b, cells)
    for _, vehicle, _ in vehicles.good() if vehicles else ():
        define(vehicle, "name", "vehicle")
    gnbs = [n for n, r in b.roles.items() if r == "gnb"]
    if cells is not None:
        for _, vehicle, _ in vehicles.good() if vehicles else ():
            gnb = vehicle.get("gnb")
            if gnb is None or gnb in gnbs:
                continue
            role = b.roles.get(gnb)
            hint = (
                f"{gnb!r} is {ROLE_TEXT.get(role, role)}, not a gNB"
                if role
                else did_you_mean(gnb, gnbs, NAME_CUTOFF)
            )
            b.ctx.add(
                vehicle.at("gnb"),
                vehicle.path_of("gnb"),
                f"the name of a gNB defined in topology.cells ({listing(gnbs)})",
                repr(gnb),
                hint,
            )
    b.topology_ok = topo.clean and not b.ctx.issues
    # Link names come from the parts that checked out, so later references can be checked.
    handover = channel.wants_handover(b.root)
    for _, vehicle, _ in vehicles.good() if vehicles else ():
        if vehicle.get("name") and vehicle.get("gnb") in gnbs:
            b.link_kinds[f"{vehicle['name']}-{vehicle['gnb']}"] = "air"
    # With handovers a vehicle has a link to every gNB (`model.Scenario.gnbs_of`).
    for _, vehicle, _ in vehicles.good() if vehicles and handover else ():
        if vehicle.get("name") and vehicle.get("gnb") in gnbs:
            for gnb in gnbs:
                b.link_kinds.setdefault(f"{vehicle['name']}-{gnb}", "air")
    for _, cell, _ in cells.good() if cells else ():
        gnb, core, upf, edge = (
            cell.get("gnb"),
            cell.get("core"),
            cell.get("upf"),
            _edge_name(cell),
        )
        if gnb and core:
            b.link_kinds[f"{gnb}-{core}"] = "backhaul"
        elif gnb and upf and edge:
            b.link_kinds[f"{gnb}-{upf}"] = "n3"
            lower = gnb if channel.placement(cell) == "cell" else upf
            b.link_kinds[f"{lower}-{edge}"] = "n6"
    pool = topo.get("address_pool")
    ue_pool = topo.get("ue_pool") or model.DEFAULT_UE_POOL
    if pool is not None and ue_pool.overlaps(pool):
        b.ctx.add(
            topo.at("ue_pool") if topo.written("ue_pool") else topo.at("address_pool"),
            topo.path_of("ue_pool") if topo.written("ue_pool") else topo.path_of("address_pool"),
            f"a UE pool apart from the link addresses (address_pool {pool})",
            f"'{ue_pool}'",
            "a packet to a vehicle would match a link's route; pick another private range",
        )
    if pool is not None and cells is not None and vehicles is not None:
        needed = len(b.link_kinds)
        room = 2 ** max(0, 30 - pool.prefixlen) if pool.prefixlen <= 30 else 0
        if room < needed:
            prefix = 30 - max(0, (needed - 1).bit_length())
            b.ctx.add(
                topo.at("address_pool"),
                topo.path_of("address_pool"),
                f"a network with room for one /30 per link ({needed} links need a "
                f"/{prefix} or larger)",
                f"'{pool}' (room for {room})",
            )
    qos = _qos(b, topo.get("qos"))
    hosts = _hosts(b, topo)
    if not b.topology_ok or qos is None or hosts is None:
        return None
    assert cells is not None and vehicles is not None
    return model.Topology(
        vehicles=tuple(schema_v1.VEHICLE.build(v) for _, v, _ in vehicles.good()),
        cells=tuple(_cell(b, c) for _, c, _ in cells.good()),
        address_pool=pool,
        ue_pool=ue_pool,
        ue_mtu=topo.get("ue_mtu", model.MAX_UE_MTU),
        qos=qos,
        hosts=hosts,
    )


def _hosts(b: Builder, topo: Section) -> tuple[model.Host, ...] | None:
    """`topology.hosts`: each host's underlay address and nodes; None when one is wrong
    (reported). A node is on one host at most; hosts have addresses of their own; and the
    link addresses must be the same on every host, so the pool is written down."""
    hosts: dict[str, Any] | None = topo.get("hosts")
    if not hosts:
        return ()  # every node on this host (a broken `hosts` is reported already)
    ok = True
    built: list[model.Host] = []
    owner: dict[ipaddress.IPv4Address, str] = {}  # address -> the host that has it
    for name, host in hosts.items():
        if not isinstance(host, Section) or not host.clean:
            ok = False
            continue
        address = _underlay_address(b, host, owner.get)
        if address is None:
            ok = False
        else:
            owner.setdefault(address, name)
        nodes: Items | None = host.get("nodes")
        for i, node, at in nodes.good() if nodes else ():
            path = item(nodes.path, i) if nodes else ""
            if b.topology_ok and node not in b.roles:
                ok = False
                b.ctx.add(
                    at,
                    path,
                    f"the name of a node of this topology ({listing(list(b.roles))})",
                    repr(node),
                    did_you_mean(node, list(b.roles), NAME_CUTOFF),
                )
            elif node in b.placed:
                ok = False
                other, where, first = b.placed[node]
                b.ctx.add(
                    at,
                    path,
                    "each node on one host",
                    f"{node!r} again (already on host {other!r} at {where}, line "
                    f"{first.start_mark.line + 1})",
                    "a node is one namespace on one machine; list it under one host",
                )
            else:
                b.placed[node] = (name, path, at)
        if address is not None:
            listed = tuple(node for _, node, _ in nodes.good()) if nodes else ()
            built.append(model.Host(name, address, listed))
    if len(hosts) > 1 and topo.get("address_pool") is None:
        ok = False
        b.ctx.add(
            b.ctx.key_of.get(id(topo.at("hosts")), topo.at("hosts")),
            topo.path_of("address_pool"),
            "topology.address_pool with topology.hosts",
            f"{len(hosts)} hosts and no address_pool",
            "every host must give the links the same addresses, so write the pool "
            "down (a private network none of the hosts uses, e.g. 10.77.0.0/16)",
        )
    return tuple(built) if ok else None


def _underlay_address(
    b: Builder, host: Section, taken: Callable[[ipaddress.IPv4Address], str | None]
) -> ipaddress.IPv4Address | None:
    """A host's `address` as an IPv4 address another host can send VXLAN to; None when
    it is not one (reported). `taken(address)` names a host that has it already."""
    text = host["address"]
    expected = "a unicast IPv4 address of this host that the other hosts reach"
    try:
        address = ipaddress.IPv4Address(text)
    except ValueError as err:
        b.ctx.add(host.at("address"), host.path_of("address"), expected, repr(text),
                     str(err))  # fmt: skip
        return None
    why = (
        "it is a loopback address, which no other host reaches"
        if address.is_loopback
        else "VXLAN here is unicast from host to host"
        if address.is_multicast
        else "it is no host's address"
        if address.is_unspecified or address.is_reserved
        else None
    )
    other = taken(address)
    if why is None and other is not None:
        expected = "an address of its own"
        why = f"host {other} has it too; each host's tunnels end at its own address"
    if why is not None:
        b.ctx.add(host.at("address"), host.path_of("address"), expected, repr(text), why)
        return None
    return address


def check_links_across_hosts(b: Builder, topology: model.Topology, links: model.Links) -> None:
    """An air link whose profiles have an NR radio stays on one host: the air links of a
    gNB share its cell's slots in one relay, which cannot reach across a tunnel."""
    for spec in links.links:
        if spec.uplink.radio is None and spec.downlink.radio is None:
            continue
        lower, upper = topology.host_of(spec.lower), topology.host_of(spec.upper)
        if lower == upper:
            continue
        # At least one end is listed (unlisted nodes share the first host): report there.
        node = spec.lower if spec.lower in b.placed else spec.upper
        _, path, at = b.placed[node]
        b.ctx.add(
            at,
            path,
            "the two ends of an air link with a radio on one host",
            f"{spec.lower} on host {lower!r}, {spec.upper} on host {upper!r} ({spec.name})",
            f"the gNB's NR slots are scheduled in one relay on its host; put "
            f"{spec.lower} on host {upper!r} with {spec.upper}",
        )


def _qos(b: Builder, qos: Section | None) -> model.Qos | None:
    """The sessions' QoS flows; None when a rule or the default names a QFI the flows lack
    (reported: a G-PDU would carry a flow its session does not have)."""
    if qos is None:
        return model.Qos()
    if not qos.clean:
        return None
    flows = tuple(qos["flows"])
    known = ", ".join(str(q) for q in flows)
    ok = True
    if qos["default_qfi"] not in flows:
        b.ctx.add(
            qos.at("default_qfi"),
            qos.path_of("default_qfi"),
            f"a QFI of the sessions' flows ({known})",
            f"QFI {qos['default_qfi']}",
            "add it to qos.flows",
        )
        ok = False
    rules: list[model.QosRule] = []
    written: Items | None = qos.get("rules")
    for i, rule, _ in written.good() if written is not None else ():
        if rule["qfi"] not in flows:
            b.ctx.add(
                rule.at("qfi"),
                rule.path_of("qfi"),
                f"a QFI of the sessions' flows ({known})",
                f"unknown QFI {rule['qfi']} (rule {i})",
                "add it to qos.flows, or map the rule to one of them",
            )
            ok = False
            continue
        rules.append(
            model.QosRule(
                rule["qfi"], rule.get("dscp"), tuple(rule.get("ports") or ()), rule.get("dds")
            )
        )
    if not ok:
        return None
    if written is None:  # the default rules whose flow the sessions have
        rules = [r for r in model.Qos().rules if r.qfi in flows]
    return model.Qos(flows, qos["default_qfi"], tuple(rules))


def _check_cell_form(b: Builder, cell: Section) -> None:
    """A cell has a core, or a UPF and an edge (see `model.Cell`), never a mix."""
    has = {k: cell.written(k) for k in ("core", "upf", "edge")}
    if has["core"] and (has["upf"] or has["edge"]):
        key = "upf" if has["upf"] else "edge"
        b.ctx.add(
            cell.at(key),
            cell.path_of(key),
            "either core (a router hosting the edge server) or upf and edge (the 5G core "
            "path), not both",
            f"{key} beside core {cell['core']!r}",
            "drop core to tunnel this cell's traffic over N3 to the UPF",
        )
    elif has["upf"] != has["edge"]:
        there, missing = ("upf", "edge") if has["upf"] else ("edge", "upf")
        b.ctx.add(
            cell.at(there),
            cell.path_of(there),
            f"{there} together with {missing}",
            f"{there} without {missing}",
            "the UPF sends the cell's traffic over N6 to an edge server; name both",
        )
    elif not has["core"] and not has["upf"]:
        b.ctx.add(
            cell.node,
            cell.path,
            "a cell with core, or with upf and edge",
            "neither",
            "e.g. {gnb: gnb1, upf: upf1, edge: edge1}",
        )


def _check_shared_edges(b: Builder, cells: Items | None) -> None:
    """An edge server shared by cells sits in one place (behind one UPF, or at cells)."""
    first: dict[str, tuple[str, str]] = {}  # edge -> (where it is, the path that said so)
    for _, cell, _ in cells.good() if cells else ():
        edge = _edge_name(cell)
        if edge is None or not cell.written("upf"):
            continue
        where = "placement cell" if channel.placement(cell) == "cell" else f"behind {cell['upf']}"
        if edge not in first:
            first[edge] = (where, cell.path_of("edge"))
        elif first[edge][0] != where:
            b.ctx.add(
                cell.at("edge"),
                cell.path_of("edge"),
                f"edge {edge!r} where {first[edge][1]} puts it ({first[edge][0]})",
                where,
                "an edge server has one place; give this cell an edge of its own",
            )


def _cell(b: Builder, cell: Section) -> model.Cell:
    """A cell, its scheduler written as its own field or in its `radio` (not both)."""
    built: model.Cell = schema_v1.CELL.build(cell)
    if cell.written("site"):
        built = dataclasses.replace(built, site=channel.site(cell))  # type: ignore[arg-type]
    if cell.written("edge"):
        built = dataclasses.replace(built, edge=_edge_name(cell), placement=channel.placement(cell))
    radio = cell.get("radio")
    if not isinstance(radio, Section) or "scheduler" not in radio:
        return built
    if cell.written("scheduler") and cell["scheduler"] != radio["scheduler"]:
        b.ctx.add(
            radio.at("scheduler"),
            radio.path_of("scheduler"),
            f"the cell's scheduler ({cell['scheduler']}, at {cell.path_of('scheduler')}) "
            "or no scheduler here",
            repr(radio["scheduler"]),
            "write the scheduler in one place",
        )
    return dataclasses.replace(built, scheduler=radio["scheduler"])


def check_links_named(b: Builder, section: Section, key: str) -> None:
    """Each link a list at `section[key]` names is a link of the topology."""
    names = section.get(key)
    if not isinstance(names, Items) or not b.topology_ok:
        return
    for i, name, node in names.good():
        if name not in b.link_kinds:
            _unknown_link(b, node, item(names.path, i), name)


def _unknown_link(b: Builder, node: Node, path: str, name: str) -> None:
    """Report `name` as no link of the topology, with the likeliest one it meant."""
    lower, _, upper = name.partition("-")
    reversed_name = f"{upper}-{lower}"
    hint = (
        f"links are named lower-upper (vehicle-gnb, gnb-core): {reversed_name}"
        if reversed_name in b.link_kinds
        else did_you_mean(name, list(b.link_kinds), NAME_CUTOFF)
    )
    b.ctx.add(
        node,
        path,
        f"the name of a link of this topology ({listing(list(b.link_kinds))})",
        repr(name),
        hint,
    )


def check_link(b: Builder, section: Section, key: str) -> bool:
    """Whether `section[key]` names a link of the topology (reported when it does not)."""
    name = section.get(key)
    if name is None:
        return False
    if name in b.link_kinds:
        return True
    if b.topology_ok:
        _unknown_link(b, section.at(key), section.path_of(key), name)
    return False


def check_node(b: Builder, section: Section, key: str) -> None:
    """Report `section[key]` where it names no node of the topology."""
    name = section.get(key)
    if name is None or name in b.roles or not b.topology_ok:
        return
    b.ctx.add(
        section.at(key),
        section.path_of(key),
        f"the name of a node of this topology ({listing(list(b.roles))})",
        repr(name),
        did_you_mean(name, list(b.roles), NAME_CUTOFF),
    )
