"""A topology across two hosts on one machine: two "host" namespaces joined by a veth underlay,
each running its half with `testbed up --host` (the real CLI, in a process that lives in that
host namespace, as it would on a machine of its own), the backhaul gnb1-core1 carried by a
VXLAN tunnel between them and emulated at host a's end.

What must hold: av1 on host a reaches core1 on host b through the emulated link, with the
configured delay within 0.5 ms each way; `testbed down` (or `clean --all`) on each host leaves
nothing: no run namespace, no VXLAN device or VXLAN socket in either host namespace, no relay.
Also: the tc backend's two tunnel ends (HTB at the shaping end's host), the 5G core path with
N3 across the hosts, and `up` on a machine that is not the host it names.
"""

from __future__ import annotations

import json
import os
import secrets
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from netem.netns import delete_netns, in_netns, list_netns
from testbed import links
from testbed.namespaces import Netns
from testbed.topology import vxlan
from tests.test_multihost import two_host_yaml

pytestmark = [pytest.mark.root, pytest.mark.alone]

ROOT = Path(__file__).resolve().parent.parent
UNDERLAY_A, UNDERLAY_B = "10.250.0.1", "10.250.0.2"
#: The configured one-way delay of the link across the hosts, and the tolerance on it.
DELAY_MS, TOLERANCE_MS = 5.0, 0.5


@dataclass(frozen=True)
class Host:
    """One "host": its namespace (the underlay side) and the state dir its testbed uses."""

    name: str
    netns: str
    state: Path

    def testbed(self, *args: str) -> subprocess.CompletedProcess[str]:
        """The testbed CLI run inside this host's namespace (nsenter switches only the network
        namespace: /run/netns stays shared, as it is on one machine)."""
        return subprocess.run(
            ["nsenter", f"--net=/run/netns/{self.netns}", "--",
             sys.executable, "-m", "testbed.cli", *args],
            cwd=ROOT,
            env={**os.environ, "EDGELOC_STATE_DIR": str(self.state)},
            capture_output=True,
            text=True,
            timeout=120,
        )  # fmt: skip


@pytest.fixture
def hosts(tmp_path: Path) -> Iterator[tuple[Host, Host]]:
    """Hosts a and b: two namespaces of their own joined by a veth pair with private underlay
    addresses. Removed afterwards, whatever the test left in them."""
    tag = f"{os.getpid()}-{secrets.token_hex(2)}"
    a = Host("a", f"mh-a-{tag}", tmp_path / "state-a")
    b = Host("b", f"mh-b-{tag}", tmp_path / "state-b")
    made: list[Netns] = []
    try:
        for host in (a, b):
            made.append(Netns.create(host.netns))
        ns_a, ns_b = made
        fd = os.open(ns_b.path, os.O_RDONLY)
        try:
            ns_a.ipr.link("add", ifname="u0", kind="veth", peer={"ifname": "u0", "net_ns_fd": fd})
        finally:
            os.close(fd)
        for ns, address in ((ns_a, UNDERLAY_A), (ns_b, UNDERLAY_B)):
            idx = ns.ifindex("u0")
            ns.ipr.addr("add", index=idx, address=address, prefixlen=30)
            ns.ipr.link("set", index=idx, state="up")
            ns.ipr.link("set", index=1, state="up")
        yield a, b
    finally:
        for ns in made:
            ns.close()
        for host in (a, b):
            if host.state.is_dir():
                host.testbed("clean", "--all")
        for name in list_netns():
            if name in (a.netns, b.netns):
                delete_netns(name)


def _scenario(tmp_path: Path, delay_ms: float) -> Path:
    path = tmp_path / f"mh-{delay_ms:g}.yaml"
    path.write_text(two_host_yaml(delay=f"{delay_ms:g}ms", address_a=UNDERLAY_A,
                                  address_b=UNDERLAY_B, pool="10.251.0.0/24"))  # fmt: skip
    return path


def _up(hosts: tuple[Host, Host], path: Path, run_id: str) -> None:
    for host in hosts:
        out = host.testbed("up", str(path), "--host", host.name, "--run-id", run_id)
        assert out.returncode == 0, f"up on host {host.name}:\n{out.stdout}{out.stderr}"


def _rtts_ms(
    run_id: str, count: int, node: str = "core1", address: str = "10.251.0.2"
) -> list[float]:
    """UDP echo av1 -> `address` of `node` (default: core1 on gnb1-core1, the pool's
    first /30, across the hosts), one datagram at a time, after a warm-up that resolves the
    neighbours on the way."""
    with Netns.open(f"el-{run_id}-{node}") as server_ns, Netns.open(f"el-{run_id}-av1") as av1:
        server, client = server_ns.socket(), av1.socket()
        try:
            server.bind((address, 0))
            port = server.getsockname()[1]
            server.settimeout(2)
            client.settimeout(2)
            rtts = []
            for i in range(count + 3):
                t0 = time.perf_counter()
                client.sendto(b"x", (address, port))
                data, peer = server.recvfrom(16)
                server.sendto(data, peer)
                client.recvfrom(16)
                if i >= 3:
                    rtts.append((time.perf_counter() - t0) * 1000)
                time.sleep(0.01)
        finally:
            server.close()
            client.close()
    return rtts


def _median(values: list[float]) -> float:
    ordered = sorted(values)
    return ordered[len(ordered) // 2]


def _vxlan_devices(netns: str) -> list[str]:
    with Netns.open(netns) as ns:
        return [
            str(d.get_attr("IFLA_IFNAME"))
            for d in ns.ipr.get_links()
            if d.get_nested("IFLA_LINKINFO", "IFLA_INFO_KIND") == "vxlan"
        ]


def _udp_ports(netns: str) -> set[int]:
    """The local UDP ports with a socket in `netns` (where a VXLAN device keeps its own)."""
    with in_netns(f"/run/netns/{netns}"), open("/proc/thread-self/net/udp") as f:
        rows = f.read().splitlines()[1:]
    return {int(row.split()[1].split(":")[1], 16) for row in rows}


def _tunnel_of_core1(run_id: str) -> tuple[int, int]:
    """core1's interface towards gnb1: its VNI and the packets it received."""
    with Netns.open(f"el-{run_id}-core1") as ns:
        (dev,) = ns.ipr.get_links(ns.ifindex("gnb1"))
        info = dev.get_attr("IFLA_LINKINFO")
        assert info.get_attr("IFLA_INFO_KIND") == "vxlan"
        vni = info.get_attr("IFLA_INFO_DATA").get_attr("IFLA_VXLAN_ID")
        return int(vni), int(dev.get_attr("IFLA_STATS64")["rx_packets"])


def _assert_nothing_left(hosts: tuple[Host, Host], run_id: str) -> None:
    left = [n for n in list_netns() if n.startswith(f"el-{run_id}-")]
    assert left == [], f"namespaces left: {left}"
    for host in hosts:
        assert _vxlan_devices(host.netns) == [], f"VXLAN device left on host {host.name}"
        assert vxlan.VXLAN_PORT not in _udp_ports(host.netns), f"VXLAN socket on {host.name}"
        assert not list(host.state.glob("*.json")), f"state file left on host {host.name}"
        assert not (host.state / run_id).exists()
    names = [f"el-{run_id}-{n}" for n in ("av1", "gnb1", "core1", "upf1", "edge1")]
    assert links.relay_pids(names) == []


def _set_delay(host: Host, run_id: str, link: str, delay_ms: float) -> None:
    """Set both directions of `link`'s delay live, through its relay's control socket (named
    in the run's link-backend.json on the host that emulates it)."""
    relays = json.loads((host.state / run_id / links.LINK_STATE_FILE).read_text())["relays"]
    control = next(r["control"] for r in relays if r["link"] == link)
    request = {"op": "set", "direction": "both", "profile": {"delay_s": delay_ms / 1000}}
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(2)
        sock.connect(control)
        sock.sendall((json.dumps(request) + "\n").encode())
        reply = json.loads(sock.makefile().readline())
    assert reply.get("ok"), reply


def test_a_vehicle_on_host_a_reaches_its_edge_on_host_b_with_the_configured_delay(
    hosts: tuple[Host, Host], tmp_path: Path
) -> None:
    a, b = hosts
    run_id = secrets.token_hex(3)
    rtts: dict[float, list[float]] = {DELAY_MS: [], 0.0: []}
    try:
        _up(hosts, _scenario(tmp_path, DELAY_MS), run_id)
        # Nothing of the run in the host namespaces but the tunnels' sockets.
        assert _vxlan_devices(a.netns) == _vxlan_devices(b.netns) == []
        assert vxlan.VXLAN_PORT in _udp_ports(a.netns) & _udp_ports(b.netns)
        assert f"el-{run_id}-vx-gnb1-core1" in list_netns()
        vni, before = _tunnel_of_core1(run_id)
        assert vni == vxlan.vnis(run_id, ["gnb1-core1"])["gnb1-core1"]
        # The configured delay and the same path without it, in turns, so that the host's
        # load drifting during the test weighs on both alike.
        for _ in range(4):
            for delay in (DELAY_MS, 0.0):
                _set_delay(a, run_id, "gnb1-core1", delay)
                rtts[delay] += _rtts_ms(run_id, count=15)
        _set_delay(a, run_id, "gnb1-core1", DELAY_MS)
        assert _tunnel_of_core1(run_id)[1] >= before + 120  # every echo came through it
    finally:
        downs = [host.testbed("down", run_id) for host in hosts]
    for host, out in zip(hosts, downs, strict=True):
        assert out.returncode == 0, f"down on host {host.name}:\n{out.stdout}{out.stderr}"
        assert "1 VXLAN tunnel(s)" in out.stdout
    _assert_nothing_left(hosts, run_id)
    medians = {delay: _median(values) for delay, values in rtts.items()}
    for delay, values in rtts.items():
        print(
            f"\ndelay {delay:g} ms each way: RTT av1 -> core1 median {medians[delay]:.3f} ms, "
            f"min {min(values):.3f}, max {max(values):.3f} ({len(values)} echoes)"
        )
    one_way = (medians[DELAY_MS] - medians[0.0]) / 2
    print(
        f"one way, over the no-delay baseline: {one_way:.3f} ms (configured {DELAY_MS:g} ms, "
        f"tolerance {TOLERANCE_MS:g} ms)"
    )
    assert abs(one_way - DELAY_MS) <= TOLERANCE_MS
    assert medians[DELAY_MS] >= 2 * DELAY_MS


def test_clean_all_on_each_host_removes_its_part(hosts: tuple[Host, Host], tmp_path: Path) -> None:
    run_id = secrets.token_hex(3)
    _up(hosts, _scenario(tmp_path, DELAY_MS), run_id)
    for host in hosts:
        out = host.testbed("clean", "--all")
        assert out.returncode == 0, out.stdout + out.stderr
        assert "1 VXLAN tunnel(s)" in out.stdout
    _assert_nothing_left(hosts, run_id)


def test_up_on_the_wrong_host_says_so_and_builds_nothing(
    hosts: tuple[Host, Host], tmp_path: Path
) -> None:
    a, _ = hosts
    run_id = secrets.token_hex(3)
    out = a.testbed("up", str(_scenario(tmp_path, DELAY_MS)), "--host", "b", "--run-id", run_id)
    assert out.returncode == 3, out.stdout + out.stderr
    assert f"topology.hosts.b.address {UNDERLAY_B} is not an address of this machine" in (
        out.stdout + out.stderr
    )
    assert not [n for n in list_netns() if n.startswith(f"el-{run_id}-")]


def test_on_tc_the_shaping_ends_host_puts_htb_on_its_tunnel(
    hosts: tuple[Host, Host], tmp_path: Path
) -> None:
    """The air link crosses the hosts (av1 on a, gnb1 and core1 on b); tc shapes it at the
    gNB's end, on host b's tunnel (rates only: HTB works without sch_netem)."""
    path = tmp_path / "tc.yaml"
    path.write_text(
        "name: mhtc\nduration: 30s\ntopology:\n  address_pool: 10.251.0.0/24\n"
        "  cells: [{gnb: gnb1, core: core1}]\n  vehicles: [{name: av1, gnb: gnb1}]\n"
        f"  hosts:\n    a: {{address: {UNDERLAY_A}, nodes: [av1]}}\n"
        f"    b: {{address: {UNDERLAY_B}, nodes: [gnb1, core1]}}\n"
        "links:\n  backend: tc\n  air: {uplink: {rate: 20mbit}, downlink: {rate: 50mbit}}\n"
    )
    run_id = secrets.token_hex(3)
    try:
        _up(hosts, path, run_id)
        with Netns.open(f"el-{run_id}-gnb1") as gnb1, Netns.open(f"el-{run_id}-av1") as av1:
            for ns, peer in ((gnb1, "av1"), (av1, "gnb1")):
                (dev,) = ns.ipr.get_links(ns.ifindex(peer))
                assert dev.get_nested("IFLA_LINKINFO", "IFLA_INFO_KIND") == "vxlan"
            kinds = {q.get_attr("TCA_KIND") for q in gnb1.ipr.get_qdiscs(gnb1.ifindex("av1"))}
            assert "htb" in kinds
            assert "htb" not in {q.get_attr("TCA_KIND") for q in av1.ipr.get_qdiscs()}
        assert _median(_rtts_ms(run_id, count=10)) < 5  # no delay configured
    finally:
        downs = [host.testbed("down", run_id) for host in hosts]
    assert all(out.returncode == 0 for out in downs), [o.stdout + o.stderr for o in downs]
    _assert_nothing_left(hosts, run_id)


def test_the_core_path_crosses_hosts_on_n3(hosts: tuple[Host, Host], tmp_path: Path) -> None:
    """gNB on host a, UPF and edge on host b: N3 is the tunnel, GTP-U (UDP 2152) inside it,
    each host running the GTP-U end of its own node."""
    path = tmp_path / "core.yaml"
    path.write_text(
        "name: mhcore\nduration: 30s\ntopology:\n  address_pool: 10.251.0.0/24\n"
        "  cells: [{gnb: gnb1, upf: upf1, edge: edge1}]\n  vehicles: [{name: av1, gnb: gnb1}]\n"
        f"  hosts:\n    a: {{address: {UNDERLAY_A}}}\n"
        f"    b: {{address: {UNDERLAY_B}, nodes: [upf1, edge1]}}\n"
        "links:\n  backend: userspace\n  n3: {uplink: {delay: 2ms}, downlink: {delay: 2ms}}\n"
    )
    run_id = secrets.token_hex(3)
    try:
        _up(hosts, path, run_id)
        # edge1 on upf1-edge1, the pool's second /30; av1 sends from its UE address
        rtts = _rtts_ms(run_id, count=10, node="edge1", address="10.251.0.6")
        print(f"\nav1 -> edge1 over N3 across the hosts: RTT median {_median(rtts):.3f} ms")
        assert 4 <= _median(rtts) < 8
    finally:
        downs = [host.testbed("down", run_id) for host in hosts]
    assert all(out.returncode == 0 for out in downs), [o.stdout + o.stderr for o in downs]
    _assert_nothing_left(hosts, run_id)
