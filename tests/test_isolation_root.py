"""Isolation (issue #8): two runs at once do not see each other, the host namespace is never
configured, a run's namespaces route nowhere but to their own run, and no scenario value
reaches a shell.

Routes are checked with `ip route get`-style lookups (RTM_GETROUTE): the kernel answers from
its tables without sending a packet, so proving "no route to anything else" sends nothing.
"""

from __future__ import annotations

import ast
import os
from ipaddress import IPv4Address
from pathlib import Path

import pytest
from pyroute2 import IPRoute
from pyroute2.netlink.exceptions import NetlinkError

from netem.netns import list_netns
from nodes.ros.env import domain_id_for
from testbed import state as st
from testbed.topology import Net, build, example_scenario

REPO = Path(__file__).resolve().parents[1]
#: Documentation addresses (RFC 5737): stand-ins for "anything outside the run".
ELSEWHERE = ("192.0.2.1", "198.51.100.7", "203.0.113.9")


def _host_snapshot() -> dict[str, object]:
    """What a run could change in the host namespace: links, addresses, routes, qdiscs."""
    with IPRoute() as ipr:
        links = sorted(
            (link.get_attr("IFLA_IFNAME"), link["index"], str(link.get_attr("IFLA_OPERSTATE")))
            for link in ipr.get_links()
        )
        addrs = sorted(
            (a["index"], a.get_attr("IFA_ADDRESS"), a["prefixlen"]) for a in ipr.get_addr()
        )
        routes = sorted(
            (r["table"], r.get_attr("RTA_DST") or "default", r["dst_len"], r.get_attr("RTA_OIF"))
            for r in ipr.get_routes()
        )
        qdiscs = sorted((q["index"], q["handle"], q.get_attr("TCA_KIND")) for q in ipr.get_qdiscs())
    with open("/proc/sys/net/ipv4/ip_forward") as f:
        forward = f.read().strip()
    return {"links": links, "addrs": addrs, "routes": routes, "qdiscs": qdiscs, "fwd": forward}


def _route_oif(netns: str, dst: str) -> str | None:
    """The interface the namespace would send `dst` out of, or None: unreachable."""
    with IPRoute(netns=netns) as ipr:
        try:
            route = ipr.route("get", dst=dst)[0]
        except NetlinkError as err:
            assert err.code in (101, 113), err  # ENETUNREACH / EHOSTUNREACH: no route at all
            return None
        oif = route.get_attr("RTA_OIF")
        return ipr.get_links(oif)[0].get_attr("IFLA_IFNAME")


def _hops(net: Net, start: str, dst: str) -> list[str]:
    """The nodes a packet for `dst` would visit from `start`, following each node's routes,
    until one has no route: the packet is dropped there."""
    hops, node = [start], start
    while (oif := _route_oif(net[node].netns, dst)) is not None:
        assert oif in net.nodes and len(hops) <= len(net.nodes), (hops, oif)
        hops.append(node := oif)
    return hops


def _addresses(net: Net) -> list[IPv4Address]:
    return [
        net[name].address_towards(peer)
        for name, node in net.nodes.items()
        for peer in node.interfaces
    ]


@pytest.mark.root
def test_two_runs_at_once_share_nothing_and_leave_the_host_alone(state_dir: Path) -> None:
    before = _host_snapshot()
    with (
        build(example_scenario(1, 1), mode="run") as a,
        build(example_scenario(1, 1), mode="run") as b,
    ):
        assert _host_snapshot() == before, "a run configured something in the host namespace"
        assert a.run_id != b.run_id
        assert domain_id_for(a.run_id) != domain_id_for(b.run_id), "one ROS domain for two runs"
        assert not a.pool.overlaps(b.pool)
        ns_a = {n.netns for n in a.nodes.values()}
        ns_b = {n.netns for n in b.nodes.values()}
        assert not ns_a & ns_b and ns_a | ns_b <= set(list_netns())
        for mine, other in ((a, b), (b, a)):
            theirs = [*map(str, _addresses(other)), *ELSEWHERE]
            for name, node in mine.nodes.items():
                # Its only interfaces are its links to its own run's nodes ...
                with IPRoute(netns=node.netns) as ipr:
                    ifnames = {link.get_attr("IFLA_IFNAME") for link in ipr.get_links()}
                assert ifnames - {"lo"} == set(node.interfaces) <= set(mine.nodes), ifnames
                # ... its run's addresses are reachable over them ...
                for peer in node.interfaces:
                    target = str(mine[peer].address_towards(name))
                    assert _route_oif(node.netns, target) == peer, (name, peer)
                # ... and a packet for anything else dies inside the run.
                for dst in theirs:
                    hops = _hops(mine, name, dst)
                    assert set(hops) <= set(mine.nodes), (mine.run_id, dst, hops)
    assert _host_snapshot() == before, "teardown left something in the host namespace"
    assert st.list_runs() == []


def test_run_ids_avoid_the_ros_domains_of_live_runs(state_dir: Path) -> None:
    # 99 taken domains leave one free: every fresh id must land on it.
    taken = {f"{i:06x}" for i in range(99)}  # domain ids 1..99 (value % 100 + 1)
    for _ in range(20):
        run_id = st.fresh_run_id(taken, key=domain_id_for)
        assert run_id not in taken and domain_id_for(run_id) == 100
    # The same through `build`, where the taken ids are the live runs' state files (a dry run:
    # it reads them as a real build does, and creates nothing).
    me = st.ProcessRef.of(os.getpid(), "test")
    for run_id in taken:
        st.RunState(run_id, "smoke", None, me, "run", "up", None, 0.0).save()
    assert {r.run_id for r in st.list_runs()} == taken
    for _ in range(5):
        net = build(example_scenario(1, 1), dry_run=True, echo=lambda _line: None)
        assert domain_id_for(net.run_id) == 100, net.run_id
    assert {r.run_id for r in st.list_runs()} == taken  # the dry runs recorded nothing


# ---- no scenario value reaches a shell ---------------------------------------------------------

SHELL_CALLS = {("os", "system"), ("os", "popen"), ("subprocess", "getoutput"),
               ("subprocess", "getstatusoutput")}  # fmt: skip
SPAWNERS = {"run", "Popen", "call", "check_call", "check_output"}


def _shell_uses(tree: ast.AST) -> list[tuple[int, str]]:
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name):
            if (func.value.id, func.attr) in SHELL_CALLS:
                found.append((node.lineno, f"{func.value.id}.{func.attr}"))
            if (
                func.value.id == "subprocess"
                and func.attr in SPAWNERS
                and node.args
                and isinstance(node.args[0], (ast.Constant, ast.JoinedStr, ast.BinOp))
            ):
                found.append((node.lineno, f"subprocess.{func.attr} with a command string"))
        for kw in node.keywords:
            if kw.arg == "shell" and not (
                isinstance(kw.value, ast.Constant) and kw.value.value is False
            ):
                found.append((node.lineno, "shell=..."))
    return found


def test_no_code_path_hands_a_string_to_a_shell() -> None:
    sources = [
        p for d in ("testbed", "netem", "nodes", "reports") for p in (REPO / d).rglob("*.py")
    ]
    assert len(sources) > 30
    offenders = [
        f"{p.relative_to(REPO)}:{line}: {what}"
        for p in sources
        for line, what in _shell_uses(ast.parse(p.read_text(), str(p)))
    ]
    assert offenders == [], "commands must be argv lists, never shell strings"


def test_the_shell_scan_finds_what_it_looks_for() -> None:
    code = (
        "import os, subprocess\n"
        "os.system('x')\n"
        "subprocess.run(f'ip {name}', shell=True)\n"
        "subprocess.Popen(['ip', name])\n"
        "subprocess.check_output('tc qdisc')\n"
    )
    assert _shell_uses(ast.parse(code)) == [
        (2, "os.system"),
        (3, "subprocess.run with a command string"),
        (3, "shell=..."),
        (5, "subprocess.check_output with a command string"),
    ]
