"""Topologies across hosts, without root: `topology.hosts` in the scenario, which links cross
hosts, their VNIs, each host's tunnels and transit namespaces, and what `testbed up --dry-run
--host` prints. The real two-host build is `tests/test_multihost_root.py`.
"""

from __future__ import annotations

import os
import subprocess
import sys
from ipaddress import IPv4Address, IPv4Network
from pathlib import Path

import pytest
from typer.testing import CliRunner

from testbed import links
from testbed import state as st
from testbed.cli import app
from testbed.errors import BadInput
from testbed.namespaces import VethEnds
from testbed.scenario import load
from testbed.scenario.model import Scenario
from testbed.topology import plan, vxlan
from testbed.topology.corepath import CorePath

POOL = IPv4Network("10.77.0.0/24")
RUN = "abc123"


def two_host_yaml(
    backend: str = "userspace",
    delay: str = "5ms",
    address_a: str = "10.250.0.1",
    address_b: str = "10.250.0.2",
    pool: str = "10.77.0.0/24",
) -> str:
    """One vehicle and its gNB on host a, the core (the edge server) on host b: the backhaul
    gnb1-core1 crosses the hosts and carries `delay` each way."""
    return (
        "name: mh\nseed: 1\nduration: 30s\n"
        "topology:\n"
        f"  address_pool: {pool}\n"
        "  cells: [{gnb: gnb1, core: core1}]\n"
        "  vehicles: [{name: av1, gnb: gnb1}]\n"
        "  hosts:\n"
        f"    a: {{address: {address_a}, nodes: [av1, gnb1]}}\n"
        f"    b: {{address: {address_b}, nodes: [core1]}}\n"
        f"links:\n  backend: {backend}\n"
        f"  backhaul: {{uplink: {{delay: {delay}}}, downlink: {{delay: {delay}}}}}\n"
    )


@pytest.fixture(autouse=True)
def state_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    d = tmp_path / "state"
    monkeypatch.setenv(st.STATE_DIR_ENV, str(d))
    return d


def _scenario(tmp_path: Path, **kw: str) -> tuple[Path, Scenario]:
    path = tmp_path / "mh.yaml"
    path.write_text(two_host_yaml(**kw))
    return path, load(path)


def _userspace(scenario: Scenario) -> links.TunRelayEnds:
    return links.TunRelayEnds(scenario.links, die_with_parent=False)


# ---- the scenario ----------------------------------------------------------------------------


def test_hosts_place_listed_nodes_and_the_rest_on_the_first(tmp_path: Path) -> None:
    path = tmp_path / "s.yaml"
    path.write_text(two_host_yaml().replace("nodes: [av1, gnb1]", "nodes: [gnb1]"))
    topo = load(path).topology
    assert [(h.name, h.address, h.nodes) for h in topo.hosts] == [
        ("a", IPv4Address("10.250.0.1"), ("gnb1",)),
        ("b", IPv4Address("10.250.0.2"), ("core1",)),
    ]
    assert {n: topo.host_of(n) for n in ("av1", "gnb1", "core1")} == {
        "av1": "a",  # listed nowhere: the first host
        "gnb1": "a",
        "core1": "b",
    }


def test_without_hosts_every_node_is_on_this_one(tmp_path: Path) -> None:
    path = tmp_path / "s.yaml"
    text = two_host_yaml()
    path.write_text(text[: text.index("  hosts:")] + text[text.index("links:") :])
    topo = load(path).topology
    assert topo.hosts == ()
    assert topo.host_of("core1") is None


# ---- the plan --------------------------------------------------------------------------------


def test_vnis_are_24_bit_the_same_everywhere_and_apart_per_link_and_run() -> None:
    one = vxlan.vnis(RUN, ["gnb1-core1", "av1-gnb1"])
    # What the other host derives: another interpreter, another string-hash seed
    probe = (
        "from testbed.topology import vxlan; "
        f"print(vxlan.vnis({RUN!r}, ['gnb1-core1', 'av1-gnb1']))"
    )
    for seed in ("1", "2"):
        out = subprocess.run(
            [sys.executable, "-c", probe], capture_output=True, text=True, check=True,
            cwd=Path(__file__).resolve().parents[1], env={**os.environ, "PYTHONHASHSEED": seed},
        )  # fmt: skip
        assert out.stdout.strip() == str(one), (seed, out.stdout, one)
    assert all(1 <= v < 2**24 for v in one.values())
    assert len(set(one.values())) == 2
    assert vxlan.vnis("def456", ["gnb1-core1"])["gnb1-core1"] != one["gnb1-core1"]


def test_two_links_on_one_vni_draw_again_the_same_way_everywhere(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    draws = iter([7, 7, 9])  # the second link's first draw collides with the first's
    monkeypatch.setattr(vxlan, "vni", lambda run, link, attempt=0: next(draws))
    assert vxlan.vnis(RUN, ["x-y", "y-z"]) == {"x-y": 7, "y-z": 9}


def test_each_host_plans_its_nodes_and_its_end_of_the_link_across(tmp_path: Path) -> None:
    _, scenario = _scenario(tmp_path)
    a = plan(scenario, RUN, POOL, backend=_userspace(scenario), host="a")
    b = plan(scenario, RUN, POOL, backend=_userspace(scenario), host="b")
    # The plan is the whole topology on both: the same addresses and routes everywhere.
    assert a["core1"].interfaces == b["core1"].interfaces
    assert [n.name for n in a.local_nodes()] == ["av1", "gnb1"]
    assert [n.name for n in b.local_nodes()] == ["core1"]
    assert [ln.name for ln in a.local_links()] == ["av1-gnb1"]
    assert b.local_links() == []
    (ta,) = a.tunnels.values()
    (tb,) = b.tunnels.values()
    assert ta.link == tb.link == "gnb1-core1"
    assert ta.vni == tb.vni == vxlan.vnis(RUN, ["gnb1-core1"])["gnb1-core1"]
    assert (ta.local, ta.remote, ta.peer_host) == (
        IPv4Address("10.250.0.1"),
        IPv4Address("10.250.0.2"),
        "b",
    )
    assert (tb.local, tb.remote, tb.peer_host) == (ta.remote, ta.local, "a")
    # Host a has the lower node (gnb1): the link's relay runs there, to a transit namespace
    # that holds the tunnel; host b's tunnel is core1's interface itself, named after gnb1.
    assert ta.transit is not None
    assert ta.transit.netns == ta.netns == "el-abc123-vx-gnb1-core1"
    assert (ta.ifname, ta.transit.relay_end) == ("core1", "gnb1")
    assert ta.transit.peer == a["core1"].address_towards("gnb1")
    assert (tb.netns, tb.ifname, tb.transit) == ("el-abc123-core1", "gnb1", None)
    assert a.emulates("gnb1-core1") and a.emulates("av1-gnb1")
    assert not b.emulates("gnb1-core1")


def test_on_tc_both_ends_are_tunnels_and_the_shaping_end_emulates(tmp_path: Path) -> None:
    _, scenario = _scenario(tmp_path, backend="tc")
    a = plan(scenario, RUN, POOL, backend=VethEnds(), host="a")
    b = plan(scenario, RUN, POOL, backend=VethEnds(), host="b")
    assert (a.tunnels["gnb1-core1"].netns, a.tunnels["gnb1-core1"].transit) == (
        "el-abc123-gnb1",
        None,
    )
    assert b.tunnels["gnb1-core1"].netns == "el-abc123-core1"
    # A backhaul is shaped at the gNB's end (netem.tc.link.shaping_end): host a's.
    assert a.emulates("gnb1-core1") and not b.emulates("gnb1-core1")


def test_without_host_the_whole_topology_is_built_here_with_no_tunnels(tmp_path: Path) -> None:
    _, scenario = _scenario(tmp_path)
    net = plan(scenario, RUN, POOL, backend=_userspace(scenario))
    assert net.tunnels == {}
    assert len(net.local_nodes()) == 3 and len(net.local_links()) == 2


def test_a_host_the_topology_does_not_name_is_refused(tmp_path: Path) -> None:
    _, scenario = _scenario(tmp_path)
    with pytest.raises(BadInput, match=r"topology\.hosts has a, b, not c"):
        plan(scenario, RUN, POOL, host="c")


def test_the_core_path_starts_each_end_on_its_own_host(tmp_path: Path) -> None:
    path = tmp_path / "core.yaml"
    path.write_text(
        "name: mh\nduration: 30s\ntopology:\n  address_pool: 10.77.0.0/24\n"
        "  cells: [{gnb: gnb1, upf: upf1, edge: edge1}]\n"
        "  vehicles: [{name: av1, gnb: gnb1}]\n"
        "  hosts:\n    a: {address: 10.250.0.1}\n"
        "    b: {address: 10.250.0.2, nodes: [upf1, edge1]}\n"
        "links:\n  backend: userspace\n"
    )
    scenario = load(path)
    a = plan(scenario, RUN, POOL, backend=_userspace(scenario), host="a")
    b = plan(scenario, RUN, POOL, backend=_userspace(scenario), host="b")
    assert list(a.tunnels) == list(b.tunnels) == ["gnb1-upf1"]  # N3 crosses; N6 is on b
    text_a = "\n".join(CorePath(a, die_with_parent=False).commands())
    text_b = "\n".join(CorePath(b, die_with_parent=False).commands())
    assert "GTP-U gNB gnb1" in text_a and "GTP-U UPF" not in text_a
    assert "GTP-U UPF upf1" in text_b and "GTP-U gNB" not in text_b
    assert "el-abc123-upf1" not in text_a and "el-abc123-gnb1" not in text_b


# ---- the command line ------------------------------------------------------------------------


def test_dry_run_of_each_host_prints_its_part_and_the_vxlan_commands(tmp_path: Path) -> None:
    path, _ = _scenario(tmp_path)
    vni = vxlan.vnis(RUN, ["gnb1-core1"])["gnb1-core1"]
    out_a = CliRunner().invoke(app, ["up", str(path), "--dry-run", "--host", "a", "--run-id", RUN])
    assert out_a.exit_code == 0, out_a.output
    lines = out_a.output.splitlines()
    assert "ip netns add el-abc123-core1" not in lines
    assert "ip netns add el-abc123-vx-gnb1-core1" in lines
    assert (
        f"ip link add core1 mtu 1500 netns el-abc123-vx-gnb1-core1 type vxlan id {vni} "
        "local 10.250.0.1 remote 10.250.0.2 dstport 4789"
    ) in lines
    relay = next(ln for ln in lines if "--netns-b el-abc123-vx-gnb1-core1" in ln)
    assert "--netns-a el-abc123-gnb1 --dev-a core1" in relay and '"delay_s": 0.005' in relay
    assert (
        "ip -n el-abc123-vx-gnb1-core1 route add default via 10.77.0.2 dev core1 onlink table 201"
    ) in lines
    out_b = CliRunner().invoke(app, ["up", str(path), "--dry-run", "--host", "b", "--run-id", RUN])
    assert out_b.exit_code == 0, out_b.output
    assert out_b.output.splitlines() == [
        "ip netns add el-abc123-core1",
        "ip -n el-abc123-core1 link set lo up",
        f"ip link add gnb1 mtu 1500 netns el-abc123-core1 type vxlan id {vni} "
        "local 10.250.0.2 remote 10.250.0.1 dstport 4789",
        "ip -n el-abc123-core1 addr add 10.77.0.2/30 dev gnb1",
        "ip -n el-abc123-core1 link set gnb1 up",
        "ip -n el-abc123-core1 route add 10.77.0.0/24 via 10.77.0.1 dev gnb1",
    ]


def test_up_without_host_on_a_scenario_across_hosts_says_it_builds_all_here(
    tmp_path: Path,
) -> None:
    path, _ = _scenario(tmp_path)
    out = CliRunner().invoke(app, ["up", str(path), "--dry-run"])
    assert out.exit_code == 0, out.output
    assert "note: topology.hosts names a, b; building every node here" in out.output
    assert "type vxlan" not in out.output
    assert "ip netns add el-" in out.output and "-core1" in out.output


def test_up_host_on_a_scenario_without_hosts_is_bad_input(tmp_path: Path) -> None:
    path = tmp_path / "one.yaml"
    path.write_text(
        "name: one\nduration: 30s\ntopology:\n  cells: [{gnb: gnb1, core: core1}]\n"
        "  vehicles: [{name: av1, gnb: gnb1}]\n"
    )
    out = CliRunner().invoke(app, ["up", str(path), "--dry-run", "--host", "a"])
    assert out.exit_code == 2
    assert "the scenario has no topology.hosts" in out.output


def test_up_with_a_bad_run_id_is_bad_input(tmp_path: Path) -> None:
    path, _ = _scenario(tmp_path)
    out = CliRunner().invoke(app, ["up", str(path), "--dry-run", "--host", "a", "--run-id", "X1"])
    assert out.exit_code == 2
    assert "must be 6 lowercase hex characters" in out.output
