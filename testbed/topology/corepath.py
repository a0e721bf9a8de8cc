"""The 5G core path of a run: PDU sessions, the GTP-U endpoints on N3, and the routes that send
each UE's packets through them (cells with `upf:`; see `testbed.scenario.model`).

- `PduSession`: one vehicle's session: its UE address, its gNB and UPF, the TEID of each
  direction and the two N3 addresses (`netem.gtpu.endpoint.Session` plus who is who).
- `sessions(net)`: the sessions a planned network has, TEIDs numbered as a UPF and a gNB would
  hand them out (uplink 0x1001.., allocated by the UPF; downlink 0x2001.., by the gNB).
- `CorePath`: started once the links are up. Per gNB an endpoint (`netem.gtpu.endpoint`, TUN `gtp0`)
  and per N3 link an endpoint at the UPF (TUN `gtp-<gnb>`), then the routes: at the gNB, what comes
  from the UE pool goes into `gtp0` (a rule to table `UE_TABLE`; an edge at the cell is reached
  directly, before the tunnel); at the UPF, each UE's address goes into its gNB's tunnel. Its
  processes are the run's (recorded, so `testbed clean` stops them); its TUN devices go with
  them. `close()` stops them and returns their counters.

Handovers (`channel.handover`): a vehicle's session is prepared at every gNB from the start
(each gNB's end knows it and routes the UE over its own air link), so that a handover only
moves routes: the UE's default route (`Net.hand_over`) and the UPF's route into the target's
tunnel (`CorePath.switch`, the path switch).

In a scenario a cell `{gnb: gnb1, upf: upf1, edge: edge1}` (or `edge: {name: rsu1, placement:
cell}` for an edge at the cell site, local breakout) gives the namespaces gnb1, upf1, edge1, the
links gnb1-upf1 (N3, defaults in `links.n3`, else `links.backhaul`) and upf1-edge1 (N6,
`links.n6`; gnb1-rsu1 for an edge at the cell), and one GTP-U endpoint per gNB and per N3 link at
the UPF. Vehicles get addresses from `topology.ue_pool` (default 10.45.0.0/16, Open5GS's; the
first UE is 10.45.0.2) on an air interface of MTU 1456 (`topology.ue_mtu`, 576..1456; more than
a 1500-byte N3 leaves room for is a file:line error). Cells may share a UPF and an edge. `testbed
up --dry-run` prints the tunnels and their routes; run.json records each vehicle's path
(address, TEIDs, edge and placement, each hop's delay) and the GTP-U overhead on N3, and the
report shows each hop's one-way delay as the link self-test measured it (net of the same path
with the link neutral) beside the configured one, with each vehicle's answers, median request
latency and error beside its path, so two placements compare in one table. The `{gnb, core}`
form keeps a plain routed backhaul; the replay's latency model is the same for both forms.

QoS flows (`topology.qos`): `flows` (QFIs, default [1, 2]), `default_qfi` (default 1) and
`rules`, first match wins, each a `qfi` and any of `dscp`, `ports` and `dds: discovery | data`
(the run's DDS domain by the RTPS ports of DDSI-RTPS §9.6.1.1: discovery on 7400 + 250 d and
7410 + 250 d + 2 p, data one port above each). By default DDS discovery rides QFI 2, EdgeLoc's
requests and answers QFI 1. Later IP fragments of a datagram ride the flow its first fragment
got (a large SEDP message is fragmented at the UE's MTU and carries no ports after the first
fragment). A rule or default naming a QFI the flows lack, or an unknown `dds` kind, is a
file:line error. run.json's `core_path.qos_flows` names them; the report counts G-PDUs per QFI
and direction.

tests/test_core_path_root.py builds such a network and checks N3 with tshark (TEIDs, PDU types,
the QFI each rule gives, the UE's inner source, no fragments, 1 MiB of TCP, nothing of the edge
at the cell on its N3); runs mec_placement through `testbed run` and dissects the run's own N3
capture (RTPS inside GTP-U, discovery in QFI 2, data in QFI 1); builds a core path on the tc
backend and reads its capture; and stops a core-path run by Ctrl-C and by kill -9 + `testbed
clean`, leaving nothing. Its RTT check: with N3 1 ms and N6 3 ms each way, the edge at the cell
saved 8.85-8.94 ms of RTT on a 2-vCPU VM, of which the delays' share, measured against the same
path with N3 and N6 at 0.2 ms, was 7.57-7.73 ms against 7.2 ms expected: each delayed traversal
of a userspace relay adds 0.09-0.13 ms for a sparse packet there, so the test allows 0.15 ms per
traversal beyond a 0.3 ms tolerance.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from ipaddress import IPv4Address, IPv4Network
from typing import Any

from pyroute2.netlink.exceptions import NetlinkError as PyNetlinkError

from netem.errors import NetlinkError
from netem.gtpu.endpoint import EndpointConfig, GtpEndpoint, GtpEndpointError, QosRule, Session
from netem.gtpu.wire import N3_OVERHEAD
from nodes.ros.env import domain_id_for, rtps_ports
from testbed import state as st
from testbed.errors import TestbedError
from testbed.scenario.model import Cell
from testbed.topology.model import Net, Node

#: The routing table a gNB looks up for packets from its UEs (a rule sends them there).
UE_TABLE = 100
UE_RULE_PRIORITY = 1000
GNB_TUN = "gtp0"
UL_TEID_BASE, DL_TEID_BASE = 0x1001, 0x2001


def upf_tun(gnb: str) -> str:
    """The UPF's TUN device of the N3 link to `gnb` (at most 14 characters: IFNAMSIZ)."""
    return f"gtp-{gnb}"


@dataclass(frozen=True)
class PduSession:
    vehicle: str
    gnb: str
    upf: str
    ue_address: IPv4Address
    ul_teid: int
    dl_teid: int
    gnb_n3: IPv4Address
    upf_n3: IPv4Address

    def session(self) -> Session:
        return Session(
            str(self.ue_address), self.ul_teid, self.dl_teid, str(self.gnb_n3), str(self.upf_n3)
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "vehicle": self.vehicle,
            "ue_address": str(self.ue_address),
            "gnb": self.gnb,
            "upf": self.upf,
            "ul_teid": self.ul_teid,
            "dl_teid": self.dl_teid,
            "gnb_n3": str(self.gnb_n3),
            "upf_n3": str(self.upf_n3),
        }


def sessions(net: Net) -> list[PduSession]:
    """One session per vehicle behind a UPF, in the order the vehicles are written; with
    handovers, each followed by the same session prepared at every other gNB (as Xn handover
    preparation sets it up at a target), so that routing alone decides which tunnel carries
    it."""
    topo = net.scenario.topology
    out = []
    vehicles = [v for v in topo.vehicles if net[v.name].ue_address is not None]
    for i, v in enumerate(vehicles):
        for gnb in net.scenario.gnbs_of(v):  # its first cell's session first
            cell = topo.cell_of_gnb(gnb)
            n3 = net.links[f"{cell.gnb}-{cell.uplink_peer}"].addresses
            ue = net[v.name].ue_address
            assert ue is not None
            out.append(
                PduSession(
                    v.name,
                    cell.gnb,
                    cell.uplink_peer,
                    ue,
                    UL_TEID_BASE + i,
                    DL_TEID_BASE + i,
                    n3.lower.ip,
                    n3.upper.ip,
                )
            )
    return out


@dataclass(frozen=True)
class TunnelRoute:
    """A route of the core path in node `node` (`dst` out of `dev`, via `via`, in `table`), or,
    with `rule`, the gNB's rule that sends packets from `dst` to table `UE_TABLE`."""

    node: str
    dst: str
    dev: str
    via: IPv4Address | None = None
    table: int | None = None
    rule: bool = False

    def command(self, netns: str) -> str:
        if self.rule:
            return f"ip -n {netns} rule add from {self.dst} lookup {UE_TABLE}"
        via = f" via {self.via}" if self.via else ""
        table = f" table {self.table}" if self.table is not None else ""
        return f"ip -n {netns} route add {self.dst}{via} dev {self.dev}{table}"


class CorePath:
    """The run's GTP-U endpoints and tunnel routes (see the module doc)."""

    def __init__(self, net: Net, die_with_parent: bool) -> None:
        self.net = net
        self.die_with_parent = die_with_parent
        self.sessions = sessions(net)
        #: The gNB whose tunnel carries each vehicle's downlink now (`switch` changes it).
        self.serving = {v.name: v.gnb for v in net.scenario.topology.vehicles}
        self.rules = self.qos_rules()  # the same for every end: made once
        self.endpoints: dict[str, GtpEndpoint] = {}  # "gnb1", "upf1/gnb1"
        self.final: dict[str, dict[str, Any]] = {}

    def start(self) -> CorePath:
        """Start every endpoint, then the routes into their TUN devices. On one host of a
        topology across hosts, only the ends of its own gNBs and UPFs (N3 may cross hosts:
        GTP-U is plain UDP to the tunnel)."""
        try:
            for cell in self._cells():
                mine = tuple(s for s in self.sessions if s.gnb == cell.gnb)
                gnb, upf = self.net[cell.gnb], self.net[cell.uplink_peer]
                n3 = self.net.links[f"{cell.gnb}-{cell.uplink_peer}"].addresses
                if self.net.here(gnb):
                    self._endpoint(cell.gnb, "gnb", gnb.netns, GNB_TUN, n3.lower.ip, mine)
                if self.net.here(upf):
                    self._endpoint(f"{upf.name}/{cell.gnb}", "upf", upf.netns,
                                   upf_tun(cell.gnb), n3.upper.ip, mine)  # fmt: skip
            # Launched together, waited for together: each is a Python process to start.
            for key, endpoint in self.endpoints.items():
                try:
                    endpoint.wait_ready()
                except GtpEndpointError as err:
                    raise TestbedError(f"GTP-U {key}: {err}") from None
            for cell in self._cells():
                gnb, upf = self.net[cell.gnb], self.net[cell.uplink_peer]
                routes = self._routes(cell)
                for node, tun in ((gnb, GNB_TUN), (upf, upf_tun(cell.gnb))):
                    if self.net.here(node):
                        self._route(node, tun, [r for r in routes if r.node == node.name])
        except BaseException:
            self.close()
            raise
        return self

    def _cells(self) -> list[Cell]:
        return [c for c in self.net.scenario.topology.cells if c.tunnelled]

    def _routes(self, cell: Cell) -> list[TunnelRoute]:
        """The routes and the rule that send a cell's UE traffic through its tunnel: at the
        gNB, the pool's packets to table `UE_TABLE` (an edge at the cell first, then the
        tunnel) and each UE back over its air link; at the UPF, each UE into its tunnel."""
        gnb, upf = cell.gnb, cell.uplink_peer
        out = []
        if cell.placement == "cell":
            # Local breakout: the edge at the cell is reached without crossing N3.
            edge = self.net.links[f"{gnb}-{cell.server}"].addresses
            out.append(TunnelRoute(gnb, str(edge.subnet), cell.server, table=UE_TABLE))
        out.append(TunnelRoute(gnb, "default", GNB_TUN, table=UE_TABLE))
        out.append(TunnelRoute(gnb, str(self.net.scenario.topology.ue_pool), "", rule=True))
        for s in (s for s in self.sessions if s.gnb == gnb):
            via = self.net.links[f"{s.vehicle}-{gnb}"].addresses.lower.ip
            out.append(TunnelRoute(gnb, f"{s.ue_address}/32", s.vehicle, via=via))
            if self.serving[s.vehicle] == gnb:  # a prepared session waits for its path switch
                out.append(TunnelRoute(upf, f"{s.ue_address}/32", upf_tun(gnb)))
        return out

    def switch(self, vehicle: str, gnb: str) -> None:
        """The path switch of a handover: the UPF sends `vehicle`'s downlink into the N3
        tunnel of `gnb` (where its session was prepared) from now on."""
        session = next((s for s in self.sessions if s.vehicle == vehicle and s.gnb == gnb), None)
        if session is None:
            raise TestbedError(f"no PDU session of {vehicle} prepared at {gnb}")
        upf = self.net[session.upf]
        ns = upf.ns_here()
        try:
            ns.ipr.route("replace", dst=f"{session.ue_address}/32", oif=ns.ifindex(upf_tun(gnb)))
        except PyNetlinkError as err:
            raise NetlinkError(
                f"switching {vehicle}'s path to {upf_tun(gnb)} in {upf.netns}: the kernel said: "
                f"{err.args[-1]}"
            ) from None
        self.serving[vehicle] = gnb

    def _endpoint(
        self, key: str, role: str, netns: str, tun: str, address: IPv4Address,
        mine: tuple[PduSession, ...],
    ) -> None:  # fmt: skip
        topo = self.net.scenario.topology
        config = EndpointConfig(
            role,  # type: ignore[arg-type]
            netns,
            tun,
            str(address),
            tuple(s.session() for s in mine),
            rules=self.rules,
            default_qfi=topo.qos.default_qfi,
            tun_mtu=topo.ue_mtu,
        )
        # Its files live with the run's relays (`testbed.links.link_state_dir`).
        workdir = st.state_dir() / self.net.run_id / f"gtp-{key.replace('/', '-')}"
        endpoint = GtpEndpoint(
            config, echo_interval_s=1.0, die_with_parent=self.die_with_parent, workdir=workdir
        )
        try:
            endpoint.launch()
        except GtpEndpointError as err:
            raise TestbedError(f"GTP-U {key}: {err}") from None
        self.endpoints[key] = endpoint
        assert endpoint.pid is not None
        self.net.record_pid(endpoint.pid, f"GTP-U {role} {key}")

    def qos_rules(self) -> tuple[QosRule, ...]:
        """The scenario's packet filters as the endpoints match them: a DDS rule becomes the
        RTPS ports of this run's ROS domain."""
        domain = domain_id_for(self.net.run_id)
        return tuple(
            QosRule(r.qfi, r.dscp, r.ports + (rtps_ports(domain, r.dds) if r.dds else ()))
            for r in self.net.scenario.topology.qos.rules
        )

    def _qos_text(self) -> str:
        qos = self.net.scenario.topology.qos
        rules = []
        for r in qos.rules:
            what = [f"DDS {r.dds}"] if r.dds else []
            what += [f"DSCP {r.dscp}"] if r.dscp is not None else []
            what += [f"ports {','.join(map(str, r.ports))}"] if r.ports else []
            rules.append(f"QFI {r.qfi} for {' + '.join(what)}")
        return "; ".join([*rules, f"QFI {qos.default_qfi} for the rest"])

    def _route(self, node: Node, tun: str, routes: list[TunnelRoute]) -> None:
        """Bring `tun` up in `node` and add `routes` there."""
        ns = node._ns()
        step = f"routing UE traffic into {tun} in {node.netns}"
        try:
            ns.ipr.link("set", index=ns.ifindex(tun), state="up")
            for r in routes:
                net = IPv4Network(r.dst if r.dst != "default" else "0.0.0.0/0")
                if r.rule:
                    ns.ipr.rule("add", src=str(net.network_address), src_len=net.prefixlen,
                                table=UE_TABLE, priority=UE_RULE_PRIORITY)  # fmt: skip
                    continue
                extra: dict[str, Any] = {"gateway": str(r.via)} if r.via else {}
                if r.table is not None:
                    extra["table"] = r.table
                ns.ipr.route("add", dst=str(net), oif=ns.ifindex(r.dev), **extra)
        except PyNetlinkError as err:
            raise NetlinkError(f"{step}: the kernel said: {err.args[-1]}") from None
        _loose_rp_filter(node, tun)

    def commands(self) -> list[str]:
        """What `start` amounts to, as shell lines (what `--dry-run` prints)."""
        out = []
        qos = f"# QoS flows: {self._qos_text()}"
        for cell in self._cells():
            gnb, upf = self.net[cell.gnb], self.net[cell.uplink_peer]
            n3 = self.net.links[f"{cell.gnb}-{cell.uplink_peer}"].addresses
            teids = ", ".join(
                f"UE {s.ue_address} UL 0x{s.ul_teid:x} DL 0x{s.dl_teid:x}"
                for s in self.sessions
                if s.gnb == cell.gnb
            )
            if self.net.here(gnb):
                out.append(f"# GTP-U gNB {cell.gnb} on {n3.lower.ip}:2152 (TUN {GNB_TUN}): {teids}")
                out.append(qos)
                out.append(
                    f"ip netns exec {gnb.netns} python -m netem.gtpu.endpoint <gnb config> &"
                )
            if self.net.here(upf):
                tun = upf_tun(cell.gnb)
                out.append(f"# GTP-U UPF {upf.name} on {n3.upper.ip}:2152 (TUN {tun})")
                out.append(
                    f"ip netns exec {upf.netns} python -m netem.gtpu.endpoint <upf config> &"
                )
            out += [
                r.command(self.net[r.node].netns)
                for r in self._routes(cell)
                if self.net.here(self.net[r.node])
            ]
        return out

    def stats(self) -> dict[str, dict[str, Any]]:
        """Each endpoint's latest counters (the final ones after `close`)."""
        if self.final:
            return self.final
        return {key: e.stats() for key, e in self.endpoints.items()}

    def close(self) -> dict[str, dict[str, Any]]:
        for key, endpoint in self.endpoints.items():
            self.final[key] = endpoint.close()
        self.endpoints = {}
        return self.final

    def describe(self) -> dict[str, Any]:
        """What run.json says of the core path: sessions, endpoints, GTP-U overhead."""
        stats = self.stats()
        n3 = sum(
            st.get("sent", {}).get("n3_bytes", 0) + st.get("received", {}).get("n3_bytes", 0)
            for k, st in stats.items()
            if "/" not in k  # the gNB ends: each N3 byte once
        )
        overhead = sum(st.get("overhead_bytes", 0) for k, st in stats.items() if "/" not in k)
        return {
            "ue_pool": str(self.net.scenario.topology.ue_pool),
            "sessions": [s.to_dict() for s in self.sessions],
            "gtp_overhead_bytes_per_packet": N3_OVERHEAD,
            "n3_bytes": n3,
            "gtp_overhead_bytes": overhead,
            "gtp_overhead_share": overhead / n3 if n3 else None,
            "qos_flows": self._qos_text(),
            "endpoints": stats,
        }


def _loose_rp_filter(node: Node, tun: str) -> None:
    """UE packets enter the gNB from the air and the UPF from a TUN; the reverse path of the
    gNB's tunnelled downlink is not where it came in, so strict filtering would drop it."""
    ns = node._ns()
    for key in ("all", "default", *node.interfaces, tun):
        with contextlib.suppress(OSError):  # an interface may be gone or not yet there
            ns.write_sysctl(f"net.ipv4.conf.{key}.rp_filter", "0")


def vehicle_paths(net: Net) -> list[dict[str, Any]]:
    """Each vehicle's path to its edge server as run.json and the report show it: addresses,
    nodes, the N3 tunnel's TEIDs, the edge's placement, and each hop's configured delay."""
    topo = net.scenario.topology
    by_vehicle: dict[str, PduSession] = {}
    for s in net.core.sessions if net.core is not None else []:
        by_vehicle.setdefault(s.vehicle, s)  # its first cell's; the others are prepared
    out = []
    for v in topo.vehicles:
        cell = topo.cell_of_gnb(v.gnb)
        hops = []
        for name in [f"{v.name}-{v.gnb}", *cell.path()]:
            link = net.links[name]
            spec = link.spec
            hops.append({
                "link": name,
                "kind": link.kind,
                "uplink_delay_ms": None if spec is None else spec.uplink.fixed_delay_s * 1e3,
                "downlink_delay_ms": None if spec is None else spec.downlink.fixed_delay_s * 1e3,
            })  # fmt: skip
        session = by_vehicle.get(v.name)
        out.append({
            "vehicle": v.name,
            "address": str(net.vehicle_address(v.name)),
            "gnb": v.gnb,
            "upf": cell.upf,
            "edge": cell.server,
            "edge_address": str(net.server_address(cell)),
            "placement": cell.placement if cell.tunnelled else "core (plain backhaul)",
            "tunnel": None if session is None else {
                "ul_teid": f"0x{session.ul_teid:08x}", "dl_teid": f"0x{session.dl_teid:08x}",
                "gnb_n3": str(session.gnb_n3), "upf_n3": str(session.upf_n3),
            },
            "hops": hops,
        })  # fmt: skip
    return out
