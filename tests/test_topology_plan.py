"""Topology plan and addressing: names, /30s, routes, forwarding, pool choice, dry run.

None of these need root: they check the plan that `build` realises, and that a dry run prints
it without creating anything.
"""

from __future__ import annotations

import dataclasses
import os
from ipaddress import IPv4Interface, IPv4Network
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from netem.netns import list_netns
from testbed import state as st
from testbed.addressing import CANDIDATE_POOLS, assign, choose_pool
from testbed.errors import BadInput, HostError
from testbed.scenario.model import Cell, Topology, Vehicle
from testbed.topology import Net, build, clean, example_scenario, plan, teardown_run

POOL = IPv4Network("10.200.0.0/16")


@pytest.fixture(autouse=True)
def state_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    d = tmp_path / "state"
    monkeypatch.setenv(st.STATE_DIR_ENV, str(d))
    return d


def _plan(vehicles: int = 1, cells: int = 1) -> Net:
    return plan(example_scenario(vehicles, cells), "abc123", POOL)


def test_one_cell_plan_names_and_addresses() -> None:
    net = _plan()
    assert {n: (x.role, x.netns) for n, x in net.nodes.items()} == {
        "av1": ("vehicle", "el-abc123-av1"),
        "gnb1": ("gnb", "el-abc123-gnb1"),
        "core1": ("core", "el-abc123-core1"),
    }
    # backhaul first, then air; one /30 each; interfaces named after the peer node
    assert list(net.links) == ["gnb1-core1", "av1-gnb1"]
    assert net["gnb1"].interfaces == {
        "core1": IPv4Interface("10.200.0.1/30"),
        "av1": IPv4Interface("10.200.0.6/30"),
    }
    assert net["core1"].interfaces == {"gnb1": IPv4Interface("10.200.0.2/30")}
    assert net["av1"].interfaces == {"gnb1": IPv4Interface("10.200.0.5/30")}
    assert net["av1"].addresses() == "gnb1 10.200.0.5/30"


def test_routes_and_forwarding() -> None:
    net = _plan()
    (av_route,) = net["av1"].routes
    assert (av_route.dst, str(av_route.via), av_route.dev) == ("default", "10.200.0.6", "gnb1")
    (core_route,) = net["core1"].routes
    assert (core_route.dst, str(core_route.via), core_route.dev) == (
        "10.200.0.0/16",
        "10.200.0.1",
        "gnb1",
    )
    assert net["gnb1"].routes == []
    assert {n: x.forwarding for n, x in net.nodes.items()} == {
        "av1": False,
        "gnb1": True,
        "core1": False,
    }


def test_link_ends_sit_in_the_right_namespaces() -> None:
    link = _plan().links["av1-gnb1"]
    assert link.kind == "air" and link.spec is not None and link.spec.name == "av1-gnb1"
    ends = link.ends
    assert (ends.lower_netns, ends.lower_ifname) == ("el-abc123-av1", "gnb1")
    assert (ends.upper_netns, ends.upper_ifname) == ("el-abc123-gnb1", "av1")


def test_commands_are_the_equivalent_ip_calls() -> None:
    cmds = _plan().commands()
    assert cmds[:3] == [f"ip netns add el-abc123-{n}" for n in ("av1", "gnb1", "core1")]
    assert (
        "ip -n el-abc123-gnb1 link add core1 type veth peer name gnb1 netns el-abc123-core1"
    ) in cmds
    assert "ip -n el-abc123-av1 link add gnb1 type veth peer name av1 netns el-abc123-gnb1" in cmds
    assert "ip -n el-abc123-av1 addr add 10.200.0.5/30 dev gnb1" in cmds
    assert "ip -n el-abc123-av1 route add default via 10.200.0.6 dev gnb1" in cmds
    assert "ip -n el-abc123-core1 route add 10.200.0.0/16 via 10.200.0.1 dev gnb1" in cmds
    assert cmds[-1] == "ip netns exec el-abc123-gnb1 sysctl -w net.ipv4.ip_forward=1"
    # namespaces exist before anything is put into them; links exist before addresses
    first_link = min(i for i, c in enumerate(cmds) if "type veth" in c)
    assert all("netns add" in c for c in cmds[:3])
    assert all("addr add" not in c for c in cmds[:first_link])
    assert not any(c.startswith("ip link") or c.startswith("ip addr") for c in cmds), (
        "nothing may be configured in the host namespace"
    )


@settings(max_examples=40, deadline=None)
@given(vehicles=hs.integers(1, 40), cells=hs.integers(1, 8))
def test_any_size_gets_disjoint_subnets_and_reachable_gateways(vehicles: int, cells: int) -> None:
    net = _plan(vehicles, cells)
    subnets = [link.addresses.subnet for link in net.links.values()]
    assert len(subnets) == vehicles + cells
    assert all(s.subnet_of(POOL) for s in subnets)
    assert len(set(subnets)) == len(subnets)
    for link in net.links.values():
        a = link.addresses
        assert a.lower.ip in a.subnet and a.upper.ip in a.subnet and a.lower != a.upper
    for node in net.nodes.values():
        for route in node.routes:
            # every gateway is on a connected /30 of the interface the route names
            assert route.via in node.interfaces[route.dev].network
            peer = net.nodes[route.dev]
            assert peer.role == "gnb" and route.via in [i.ip for i in peer.interfaces.values()]
    assert len(net.nodes) == vehicles + 2 * cells
    assert len({n.netns for n in net.nodes.values()}) == len(net.nodes)


def test_vehicles_spread_over_cells() -> None:
    net = _plan(20, 4)
    assert len(net.nodes) == 28 and len(net.links) == 24
    assert sorted(net["gnb3"].interfaces) == ["av11", "av15", "av19", "av3", "av7", "core3"]


# ---- pool choice ---------------------------------------------------------------------------


def test_default_pool_is_the_first_free_candidate() -> None:
    host = [IPv4Network("192.168.1.0/24"), IPv4Network("10.200.3.0/24")]
    others = {"aaaaaa": IPv4Network("10.201.0.0/16")}
    assert choose_pool(None, 24, host, others) == IPv4Network("10.202.0.0/16")
    assert choose_pool(None, 24, [], {}) == CANDIDATE_POOLS[0]


def test_requested_pool_overlapping_host_is_bad_input() -> None:
    with pytest.raises(BadInput, match=r"overlaps the host network 10\.77\.3\.0/24"):
        choose_pool(IPv4Network("10.77.0.0/16"), 2, [IPv4Network("10.77.3.0/24")], {})


def test_requested_pool_overlapping_live_run_is_bad_input() -> None:
    with pytest.raises(BadInput, match="live run beef01"):
        choose_pool(IPv4Network("10.77.0.0/16"), 2, [], {"beef01": IPv4Network("10.77.8.0/22")})


def test_requested_pool_too_small_says_how_big() -> None:
    with pytest.raises(BadInput, match=r"too small: 24 links .* /25 or larger"):
        choose_pool(IPv4Network("10.77.0.0/26"), 24, [], {})
    assert choose_pool(IPv4Network("10.77.0.0/25"), 24, [], {}) == IPv4Network("10.77.0.0/25")


def test_public_pool_is_bad_input() -> None:
    with pytest.raises(BadInput, match="not a private network"):
        choose_pool(IPv4Network("8.8.0.0/16"), 2, [], {})


def test_no_free_candidate_is_bad_input() -> None:
    everything = [IPv4Network("10.0.0.0/8"), IPv4Network("172.16.0.0/12")]
    with pytest.raises(BadInput, match="no free address pool"):
        choose_pool(None, 2, everything, {})


def test_assign_refuses_a_full_pool() -> None:
    with pytest.raises(BadInput, match="no room"):
        assign(IPv4Network("10.77.0.0/30"), ["a-b", "b-c"])


# ---- bad topologies ------------------------------------------------------------------------


def _with_topology(topo: Topology) -> object:
    return dataclasses.replace(example_scenario(), topology=topo)


@pytest.mark.parametrize(
    ("topo", "message"),
    [
        (Topology((Vehicle("Av1", "gnb1"),), (Cell("gnb1", "core1"),)), "must match"),
        (Topology((Vehicle("av1", "gnb1"),), (Cell("gnb1", "av1"),)), "repeated: av1"),
        (Topology((Vehicle("av1", "gnb9"),), (Cell("gnb1", "core1"),)), "unknown gNB 'gnb9'"),
        (Topology((Vehicle("averyverylongname", "gnb1"),), (Cell("gnb1", "core1"),)), "must"),
    ],
)
def test_bad_names_are_bad_input(topo: Topology, message: str) -> None:
    with pytest.raises(BadInput, match=message):
        plan(_with_topology(topo), "abc123", POOL)  # type: ignore[arg-type]


def test_bad_run_id_is_bad_input() -> None:
    with pytest.raises(BadInput, match="6 lowercase hex"):
        build(example_scenario(), dry_run=True, run_id="XYZ")


# ---- dry run -------------------------------------------------------------------------------


def test_dry_run_prints_the_commands_and_creates_nothing(state_dir: Path) -> None:
    before = list_netns()
    lines: list[str] = []
    net = build(example_scenario(2, 1), dry_run=True, echo=lines.append, run_id="d0d0d0")
    assert lines == net.commands()
    assert "ip netns add el-d0d0d0-av2" in lines
    assert list_netns() == before
    assert not state_dir.exists(), "a dry run must not write state"
    assert all(n.ns is None for n in net.nodes.values())
    assert net.teardown().summary().startswith("0 namespace(s)")


def test_without_root_building_and_removing_say_so(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    for call in (lambda: build(example_scenario()), lambda: teardown_run(None), clean):
        with pytest.raises(HostError, match="needs root"):
            call()
    assert build(example_scenario(), dry_run=True).commands(), "a dry run needs no root"


# ---- the 5G core path: UPF, edge, N3/N6, UE pool ----------------------------------------------

CORE5G = """
version: 1
name: core5g
duration: 20s
topology:
  cells:
    - {gnb: gnb1, upf: upf1, edge: edge1}
    - {gnb: gnb2, upf: upf1, edge: {name: rsu2, placement: cell}}
  vehicles:
    - {name: av1, gnb: gnb1}
    - {name: av2, gnb: gnb2}
    - {name: av3, gnb: gnb1}
links:
  n3: {uplink: {delay: 1ms}, downlink: {delay: 1ms}}
  n6: {uplink: {delay: 3ms}, downlink: {delay: 3ms}}
  overrides:
    - {link: gnb2-rsu2, uplink: {delay: 0ms}, downlink: {delay: 0ms}}
"""


def _core5g(tmp_path: Path) -> Net:
    from testbed.scenario import load

    (tmp_path / "core5g.yaml").write_text(CORE5G)
    return plan(load(tmp_path / "core5g.yaml"), "abc123", POOL)


def test_cells_with_a_upf_get_n3_n6_and_a_shared_upf(tmp_path: Path) -> None:
    net = _core5g(tmp_path)
    kinds = {name: link.kind for name, link in net.links.items()}
    assert kinds == {
        "gnb1-upf1": "n3", "upf1-edge1": "n6", "gnb2-upf1": "n3", "gnb2-rsu2": "n6",
        "av1-gnb1": "air", "av2-gnb2": "air", "av3-gnb1": "air",
    }  # fmt: skip
    assert [n.role for n in net.nodes.values()].count("upf") == 1  # gnb1 and gnb2 share it
    assert net.links["gnb1-upf1"].spec.uplink.delay_s == 0.001  # links.n3
    assert net.links["gnb2-rsu2"].spec.uplink.delay_s == 0.0  # the override
    topo = net.scenario.topology
    assert [topo.cell_of_gnb(g).path() for g in ("gnb1", "gnb2")] == [
        ["gnb1-upf1", "upf1-edge1"], ["gnb2-rsu2"]
    ]  # fmt: skip


def test_vehicles_behind_a_upf_use_the_ue_pool_with_room_for_the_tunnel(tmp_path: Path) -> None:
    from ipaddress import IPv4Address

    net = _core5g(tmp_path)
    # Open5GS's pool; .1 is the UPF's own, so the UEs start at .2, in the order written.
    assert [str(net[v].ue_address) for v in ("av1", "av2", "av3")] == [
        "10.45.0.2", "10.45.0.3", "10.45.0.4"
    ]  # fmt: skip
    av1 = net["av1"]
    assert av1.mtus == {"gnb1": 1456}
    (default,) = av1.routes
    assert default.dst == "default" and default.src == IPv4Address("10.45.0.2")
    assert default.via == net.links["av1-gnb1"].addresses.upper.ip
    # The applications' addresses: the UE's, and the edge's on its N6 (towards the UPF, or
    # towards the gNB for the edge at the cell).
    assert net.vehicle_address("av1") == IPv4Address("10.45.0.2")
    cells = net.scenario.topology.cells
    assert net.server_address(cells[0]) == net.links["upf1-edge1"].addresses.upper.ip
    assert net.server_address(cells[1]) == net.links["gnb2-rsu2"].addresses.upper.ip
    # The edges route the pool back the way their traffic came; the UPF forwards.
    assert [r.dst for r in net["edge1"].routes] == ["10.45.0.0/16"]
    assert net["edge1"].routes[0].via == net.links["upf1-edge1"].addresses.lower.ip
    assert net["rsu2"].routes[0].via == net.links["gnb2-rsu2"].addresses.lower.ip
    assert net["upf1"].forwarding and net["gnb1"].forwarding


def test_sessions_number_teids_and_the_dry_run_shows_the_tunnels(tmp_path: Path) -> None:
    from testbed.topology.corepath import CorePath, sessions

    net = _core5g(tmp_path)
    got = [(s.vehicle, s.gnb, s.upf, hex(s.ul_teid), hex(s.dl_teid)) for s in sessions(net)]
    assert got == [
        ("av1", "gnb1", "upf1", "0x1001", "0x2001"),
        ("av2", "gnb2", "upf1", "0x1002", "0x2002"),
        ("av3", "gnb1", "upf1", "0x1003", "0x2003"),
    ]
    s = sessions(net)[0]
    n3 = net.links["gnb1-upf1"].addresses
    assert (s.gnb_n3, s.upf_n3) == (n3.lower.ip, n3.upper.ip)
    lines = CorePath(net, die_with_parent=False).commands()
    text = "\n".join(lines)
    assert "rule add from 10.45.0.0/16 lookup 100" in text
    assert "route add 10.45.0.3/32 dev gtp-gnb2" in text  # the UPF: each UE into its tunnel
    # The edge at the cell is reached before the tunnel: its N6 comes first in the UE table.
    breakout = net.links["gnb2-rsu2"].addresses.subnet
    assert text.index(f"route add {breakout} dev rsu2 table 100") < text.index(
        "route add default dev gtp0 table 100", text.index("gnb2 on")
    )
    assert net.state is None  # nothing created


def test_the_old_core_form_keeps_its_plain_backhaul() -> None:
    net = _plan()
    assert {link.kind for link in net.links.values()} == {"air", "backhaul"}
    assert net["av1"].ue_address is None and net["av1"].mtus == {}
    assert net.vehicle_address("av1") == net["av1"].address_towards("gnb1")


def test_each_vehicles_path_names_its_hops_and_delays(tmp_path: Path) -> None:
    from testbed.topology.corepath import CorePath, vehicle_paths

    net = _core5g(tmp_path)
    net.core = CorePath(net, die_with_parent=False)  # planned, not started: its sessions
    paths = {p["vehicle"]: p for p in vehicle_paths(net)}
    av1, av2 = paths["av1"], paths["av2"]
    assert (av1["address"], av1["upf"], av1["edge"], av1["placement"]) == (
        "10.45.0.2", "upf1", "edge1", "core"
    )  # fmt: skip
    assert av1["tunnel"]["ul_teid"] == "0x00001001"
    assert [(h["link"], h["uplink_delay_ms"]) for h in av1["hops"]] == [
        ("av1-gnb1", 0.0), ("gnb1-upf1", 1.0), ("upf1-edge1", 3.0)
    ]  # fmt: skip
    assert [h["link"] for h in av2["hops"]] == ["av2-gnb2", "gnb2-rsu2"]  # not over N3
    assert av2["placement"] == "cell"


def test_the_ue_mtu_and_the_qos_flows_reach_the_plan_and_the_gtp_u_ends(tmp_path: Path) -> None:
    """A scenario's `ue_mtu` is the UEs' air interface MTU; its QoS rules are what the GTP-U
    ends match, a DDS rule as the RTPS ports of the run's domain (DDSI-RTPS's formula: domain
    d, participant p: discovery 7400 + 250 d (multicast) and 7410 + 250 d + 2 p, data one
    port above each)."""
    from testbed.scenario import load
    from testbed.topology.corepath import CorePath

    text = CORE5G.replace(
        "  vehicles:\n",
        "  ue_mtu: 1400\n  qos:\n    flows: [1, 2, 9]\n    default_qfi: 9\n    rules:\n"
        "      - {qfi: 2, dds: discovery}\n      - {qfi: 1, dds: data, dscp: 46}\n  vehicles:\n",
        1,
    )
    (tmp_path / "qos.yaml").write_text(text)
    net = plan(load(tmp_path / "qos.yaml"), "abc123", POOL)  # domain 1 + 0xabc123 % 100 = 100
    assert net["av1"].mtus == {"gnb1": 1400}
    rules = CorePath(net, die_with_parent=True).qos_rules()
    assert [(r.qfi, r.dscp, len(r.ports)) for r in rules] == [(2, None, 121), (1, 46, 121)]
    base = 7400 + 250 * 100
    assert rules[0].ports[:3] == (base, base + 10, base + 12)
    assert rules[1].ports[:3] == (base + 1, base + 11, base + 13)
    assert max(rules[1].ports) < base + 250  # never the next domain's ports
    assert not set(rules[0].ports) & set(rules[1].ports)
    assert net.scenario.topology.qos.default_qfi == 9
    assert (
        "# QoS flows: QFI 2 for DDS discovery; QFI 1 for DDS data + DSCP 46; QFI 9 for the rest"
        in (CorePath(net, die_with_parent=True).commands())
    )


def test_qos_defaults_put_dds_discovery_in_its_own_flow(tmp_path: Path) -> None:
    from netem.gtpu.endpoint import classify
    from testbed.scenario import load
    from testbed.topology.corepath import CorePath

    net = _core5g(tmp_path)
    qos = net.scenario.topology.qos
    assert (qos.flows, qos.default_qfi) == ((1, 2), 1)
    rules = CorePath(net, die_with_parent=True).qos_rules()

    def udp(dport: int) -> bytes:  # an IPv4 header (IHL 5, proto UDP) and the UDP ports
        return (
            bytes([0x45, 0, 0, 36])
            + bytes(5)
            + bytes([17])
            + bytes(10)
            + ((40000).to_bytes(2, "big") + dport.to_bytes(2, "big") + bytes(4))
        )

    base = 7400 + 250 * 100
    assert [classify(udp(p), rules, 1) for p in (base, base + 10, base + 11, 5201)] == [2, 2, 1, 1]
    # Flows written without 2: the default rule goes, nothing is put in a flow the
    # sessions lack.
    (tmp_path / "one.yaml").write_text(
        CORE5G.replace("  vehicles:\n", "  qos: {flows: [5], default_qfi: 5}\n  vehicles:\n", 1)
    )
    assert load(tmp_path / "one.yaml").topology.qos.rules == ()


def test_links_backhaul_stands_in_for_n3_where_n3_is_not_written(tmp_path: Path) -> None:
    from testbed.scenario import load

    text = CORE5G.replace("  n3: {uplink: {delay: 1ms}, downlink: {delay: 1ms}}\n", "")
    alias = text.replace("links:\n", "links:\n  backhaul: {uplink: {delay: 2ms, rate: 1gbit}}\n")
    (tmp_path / "alias.yaml").write_text(alias)
    net = plan(load(tmp_path / "alias.yaml"), "abc123", POOL)
    for name in ("gnb1-upf1", "gnb2-upf1"):
        spec = net.links[name].spec
        assert (spec.uplink.delay_s, spec.uplink.rate_bps) == (0.002, 1e9)
        assert spec.downlink.delay_s == 0.0
    # Written n3 wins over the alias.
    both = alias.replace("links:\n", "links:\n  n3: {uplink: {delay: 4ms}}\n")
    (tmp_path / "both.yaml").write_text(both)
    net = plan(load(tmp_path / "both.yaml"), "abc123", POOL)
    assert net.links["gnb1-upf1"].spec.uplink.delay_s == 0.004


def test_a_ue_pool_overlapping_the_links_or_a_host_network_is_bad_input() -> None:
    from testbed.topology.build import check_ue_pool

    ue, links = IPv4Network("10.45.0.0/16"), IPv4Network("10.200.0.0/16")
    check_ue_pool(ue, links, [IPv4Network("192.168.1.0/24")])  # apart: fine
    with pytest.raises(BadInput, match=r"^s\.yaml: topology\.ue_pool 10\.45\.0\.0/16 overlaps "
                       r"the host network 10\.45\.3\.0/24"):  # fmt: skip
        check_ue_pool(ue, links, [IPv4Network("10.45.3.0/24")], Path("s.yaml"))
    with pytest.raises(BadInput, match=r"overlaps the link address pool 10\.45\.0\.0/24"):
        check_ue_pool(ue, IPv4Network("10.45.0.0/24"), [])
