"""Real namespaces: build, send packets through the gNB, tear down, crash and clean.

Every test uses its own state directory (EDGELOC_STATE_DIR in tmp_path), so `clean` here only
sees runs these tests made; the `guard` fixture removes whatever a failing test left behind,
and only namespaces of runs recorded in that directory.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
from ipaddress import IPv4Network
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from netem.errors import NetlinkError
from netem.netns import delete_netns, list_netns
from netem.relay.client import UserspaceLink
from testbed import state as st
from testbed.cli import app
from testbed.errors import BadInput, TestbedError
from testbed.links.relay_ends import TunRelayEnds
from testbed.namespaces import EndNames, Netns, VethEnds
from testbed.topology import Link, Net, build, clean, example_scenario, teardown_run

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[1]


def _run_namespaces(run_id: str) -> list[str]:
    return [n for n in list_netns() if n.startswith(f"el-{run_id}-")]


def _udp_round_trip(net: Net, vehicle: str, core: str, gnb: str) -> tuple[str, str]:
    """Send a datagram vehicle -> core and back; returns (what core saw, what vehicle saw)."""
    srv = net[core].socket()
    cli = net[vehicle].socket()
    try:
        srv.bind(("0.0.0.0", 0))
        srv.settimeout(2)
        cli.settimeout(2)
        core_ip = str(net[core].address_towards(gnb))
        cli.sendto(f"hello from {vehicle}".encode(), (core_ip, srv.getsockname()[1]))
        data, peer = srv.recvfrom(100)
        srv.sendto(b"hello back", peer)
        back, _ = cli.recvfrom(100)
        assert peer[0] == str(net[vehicle].address_towards(gnb))
        return data.decode(), back.decode()
    finally:
        srv.close()
        cli.close()


def _checksum(data: bytes) -> int:
    if len(data) % 2:
        data += b"\0"
    total = sum(struct.unpack(f"!{len(data) // 2}H", data))
    total = (total >> 16) + (total & 0xFFFF)
    total += total >> 16
    return ~total & 0xFFFF


def _icmp_echo(net: Net, src: str, dst_ip: str) -> int:
    """One ICMP echo from `src`'s namespace (a raw socket opened in it); returns the reply TTL."""
    sock = net[src].socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_ICMP)
    try:
        sock.settimeout(2)
        ident, payload = os.getpid() & 0xFFFF, b"edgeloc"
        header = struct.pack("!BBHHH", 8, 0, 0, ident, 1)
        header = struct.pack("!BBHHH", 8, 0, _checksum(header + payload), ident, 1)
        sock.sendto(header + payload, (dst_ip, 0))
        while True:
            packet, addr = sock.recvfrom(1500)
            ihl = (packet[0] & 0x0F) * 4
            kind, _, _, rid, _ = struct.unpack("!BBHHH", packet[ihl : ihl + 8])
            if kind == 0 and rid == ident and addr[0] == dst_ip:
                return packet[8]
    finally:
        sock.close()


def _rx_packets(net: Net, node: str, ifname: str) -> int:
    (msg,) = net[node].ipr.get_links(net[node].ipr.link_lookup(ifname=ifname)[0])
    return int(msg.get_attr("IFLA_STATS64")["rx_packets"])


def _host_ifnames() -> set[str]:
    return {
        line.split(":")[0].strip() for line in Path("/proc/net/dev").read_text().splitlines()[2:]
    }


def _host_forwarding() -> str:
    return Path("/proc/sys/net/ipv4/ip_forward").read_text().strip()


# ---- one cell ------------------------------------------------------------------------------


def test_three_namespaces_carry_real_packets_through_the_gnb(state_dir: Path) -> None:
    host_before, host_forwarding = _host_ifnames(), _host_forwarding()
    with build(example_scenario(1, 1), mode="run") as net:
        run_id = net.run_id
        assert sorted(_run_namespaces(run_id)) == sorted(n.netns for n in net.nodes.values())
        assert _host_ifnames() == host_before, "nothing may appear in the host namespace"
        state = st.load_run(run_id)
        assert state is not None and state.phase == "up" and state.liveness() == "live"
        assert state.pool == str(net.pool)

        rx_before = _rx_packets(net, "gnb1", "av1")
        assert _udp_round_trip(net, "av1", "core1", "gnb1") == ("hello from av1", "hello back")
        assert _rx_packets(net, "gnb1", "av1") > rx_before, "the packet went through the gNB"
        # ICMP: the reply from the core crossed one router (TTL 64 -> 63)
        assert _icmp_echo(net, "av1", str(net["core1"].address_towards("gnb1"))) == 63
        assert _icmp_echo(net, "core1", str(net["av1"].address_towards("gnb1"))) == 63

        assert {n: net[n].read_sysctl("net.ipv4.ip_forward") for n in net.nodes} == {
            "av1": "0",
            "gnb1": "1",
            "core1": "0",
        }
        assert _host_forwarding() == host_forwarding, "the host's sysctl is untouched"
        # users can `ip netns exec` into it
        out = subprocess.run(
            ["ip", "-n", net["av1"].netns, "addr", "show", "gnb1"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        # the UP flag (a TUN end of the userspace backend reports operstate UNKNOWN)
        assert "10." in out and re.search(r"<[^>]*\bUP\b[^>]*>", out)
    assert _run_namespaces(run_id) == []
    assert st.load_run(run_id) is None and st.list_runs() == []
    assert _host_ifnames() == host_before


def test_popen_runs_inside_the_namespace_and_teardown_stops_it(state_dir: Path) -> None:
    with build(example_scenario(1, 1), mode="run") as net:
        server = net["core1"].popen(
            [
                sys.executable,
                "-c",
                "import socket; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM);"
                "s.bind(('0.0.0.0', 7001)); print('ready', flush=True);"
                "d, a = s.recvfrom(64); s.sendto(d.upper(), a); import time; time.sleep(60)",
            ],
            what="udp echo",
            stdout=subprocess.PIPE,
            text=True,
        )
        assert server.stdout is not None and server.stdout.readline().strip() == "ready"
        run = st.load_run(net.run_id)
        assert run is not None
        # after the link relays (userspace backend), which are on file too
        ref = next(p for p in run.pids if p.what == "udp echo")
        assert ref.pid == server.pid and ref.what == "udp echo" and ref.alive()
        cli = net["av1"].socket()
        cli.settimeout(2)
        cli.sendto(b"ping", (str(net["core1"].address_towards("gnb1")), 7001))
        assert cli.recvfrom(64)[0] == b"PING"
        cli.close()
        removed = net.teardown()
    assert removed.processes == 1 and server.poll() is not None
    server.stdout.close()


def test_detached_up_then_down(state_dir: Path) -> None:
    net = build(example_scenario(1, 1), mode="up")
    runs = st.list_runs()
    assert [(r.run_id, r.liveness()) for r in runs] == [(net.run_id, "detached")]
    with pytest.raises(BadInput, match=rf"no run 'abcdef'; live runs: {net.run_id} \(detached"):
        teardown_run("abcdef")
    for node in net.nodes.values():
        node.ns.close()  # type: ignore[union-attr]  # like the `up` process exiting
    removed = teardown_run(None)
    assert removed.run_id == net.run_id and removed.namespaces == 3
    assert "3 namespace(s)" in removed.summary()
    assert _run_namespaces(net.run_id) == [] and st.list_runs() == []
    with pytest.raises(BadInput, match="no live run"):
        teardown_run(None)


def test_cli_status_and_down(state_dir: Path) -> None:
    net = build(example_scenario(1, 1), mode="up")
    runner = CliRunner()
    res = runner.invoke(app, ["status", "--json"])
    assert res.exit_code == 0, res.output
    (described,) = json.loads(res.output)
    assert described["run_id"] == net.run_id and described["liveness"] == "detached"
    assert len(described["namespaces"]) == 3
    res = runner.invoke(app, ["down", "ffffff"])
    assert res.exit_code == 2 and "no run 'ffffff'" in res.output
    res = runner.invoke(app, ["down"])
    assert res.exit_code == 0 and f"run {net.run_id} is down" in res.output
    assert _run_namespaces(net.run_id) == []
    assert runner.invoke(app, ["status"]).output.strip() == "no runs"


def test_two_runs_get_different_pools_and_a_clashing_pool_is_refused(state_dir: Path) -> None:
    with build(example_scenario(1, 1), mode="run") as first:
        with build(example_scenario(1, 1), mode="run") as second:
            assert not first.pool.overlaps(second.pool)
        clash = example_scenario(1, 1, pool=IPv4Network(first.pool))
        with pytest.raises(BadInput, match=f"overlaps {first.pool} of live run {first.run_id}"):
            build(clash, mode="run")
    assert st.list_runs() == []


class _FailingEnds(VethEnds):
    """Creates two links, then fails (or is interrupted) on the third."""

    def __init__(self, exc: BaseException) -> None:
        self.exc, self.count, self.run_id = exc, 0, ""

    def create(self, link: Link, net: Net) -> None:
        self.run_id = net.run_id
        self.count += 1
        if self.count == 3:
            raise self.exc
        super().create(link, net)


@pytest.mark.parametrize(
    "exc", [NetlinkError("link refused"), KeyboardInterrupt()], ids=["error", "ctrl-c"]
)
def test_a_failed_build_removes_everything(state_dir: Path, exc: BaseException) -> None:
    ends = _FailingEnds(exc)
    with pytest.raises(type(exc)):
        build(example_scenario(4, 1), mode="run", backend=ends)
    # its own namespaces: the tests beside it (`make test` runs two at a time) have theirs
    assert ends.run_id and not [n for n in list_netns() if f"-{ends.run_id}-" in n]
    assert st.list_runs() == []


class _DeadRelayEnds(TunRelayEnds):
    """Relays launched together; the third one's program exits at once instead of coming up."""

    def _relay(self, ends: EndNames, control: str | None = None,
               log_dir: Path | None = None, **cell: Any) -> UserspaceLink:  # fmt: skip
        relay = super()._relay(ends, control, log_dir, **cell)
        if len(self.relays) == 2:
            relay.python = "/bin/false"
        return relay


def test_a_relay_that_never_comes_up_fails_the_build_and_leaves_nothing(
    state_dir: Path,
) -> None:
    scenario = example_scenario(2, 1)
    ends = _DeadRelayEnds(scenario.links)
    with pytest.raises(TestbedError, match=r"link \S+: relay for .* exited with code 1"):
        build(scenario, mode="run", backend=ends)
    [run_id] = {Path(r.control_path or "").parent.name for r in ends.relays.values()}
    assert not [n for n in list_netns() if f"-{run_id}-" in n]
    assert st.list_runs() == []
    # the relays launched beside it were stopped too
    assert not [p for p in os.listdir("/proc") if p.isdigit() and _relay_of(p, state_dir)]


def _relay_of(pid: str, state_dir: Path) -> bool:
    """Whether `pid` is a relay of a run in `state_dir` (its control socket is there)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return b"netem.relay" in argv and any(bytes(state_dir) in a for a in argv)


def test_cgroups_recorded_by_a_run_are_removed(state_dir: Path) -> None:
    base = Path("/sys/fs/cgroup/cpu")
    if not base.is_dir():
        pytest.skip("no cgroup v1 cpu controller here")
    with build(example_scenario(1, 1), mode="run") as net:
        cg = base / f"el-{net.run_id}-av1"
        net.record_cgroup(cg)
        cg.mkdir()
        assert str(cg) in st.load_run(net.run_id).cgroups  # type: ignore[union-attr]
    assert not cg.exists()


# ---- crash and clean -----------------------------------------------------------------------

_CRASHER = """
import subprocess, sys, time
from testbed.namespaces import VethEnds
from testbed.topology import build, example_scenario

class SlowVeth(VethEnds):
    count = 0
    def create(self, link, net):
        super().create(link, net)
        SlowVeth.count += 1
        if SlowVeth.count == 2:
            recorded = link.lower.popen(["sleep", "600"], what="recorded sleeper")
            stray = subprocess.Popen(link.upper.nsenter_argv(["sleep", "600"]))  # not recorded
            print(recorded.pid, stray.pid, flush=True)
        time.sleep(0.05)

build(example_scenario(20, 4), mode="up", backend=SlowVeth())
print("finished", flush=True)
"""


def test_sigkill_midway_then_clean_leaves_nothing(state_dir: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", _CRASHER],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env={**os.environ, st.STATE_DIR_ENV: str(state_dir)},
    )
    try:
        assert proc.stdout is not None
        pids = [int(p) for p in proc.stdout.readline().split()]
        assert len(pids) == 2, "the builder died before starting its processes"
        (run,) = st.list_runs()
        assert len(run.namespaces) == 28 and run.phase == "building"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()  # type: ignore[union-attr]
    run_id = run.run_id
    assert len(_run_namespaces(run_id)) == 28
    last = Netns.open(f"el-{run_id}-av20")
    try:
        assert last.ipr.link_lookup(ifname="gnb4") == [], "killed midway: the last link is missing"
    finally:
        last.close()
    sleepers = [st.ProcessRef.of(p) for p in pids]
    assert all(s.alive() for s in sleepers)
    assert [(r.run_id, r.liveness()) for r in st.list_runs()] == [(run_id, "dead")]

    report = clean(include_detached=False)

    assert report.startswith("cleaned 1 run(s)")
    assert _run_namespaces(run_id) == []
    assert st.list_runs() == [] and not (state_dir / f"{run_id}.json").exists()
    assert not any(s.alive() for s in sleepers), "processes inside the namespaces must die"


def test_clean_removes_orphans_but_not_namespaces_owned_elsewhere(
    state_dir: Path, tmp_path: Path
) -> None:
    taken = {n.split("-")[1] for n in list_netns() if n.startswith("el-")}
    orphan_id = st.fresh_run_id(taken)
    owned_id = st.fresh_run_id(taken | {orphan_id})
    # an owned namespace: tagged with a state file that exists in another state directory
    other = tmp_path / "elsewhere.json"
    other.write_text("{}")
    made = []
    try:
        for name, tag in ((f"el-{orphan_id}-av1", None), (f"el-{owned_id}-av1", str(other))):
            ns = Netns.create(name)
            made.append(name)
            if tag:
                ns.ipr.link("set", index=1, ifalias=f"edgeloc-testbed state={tag}")
            ns.close()
        with build(example_scenario(1, 1), mode="up") as detached:
            report = clean(include_detached=False)
            assert "1 orphan namespace(s)" in report and "1 detached run(s) left up" in report
            assert f"el-{orphan_id}-av1" not in list_netns()
            assert f"el-{owned_id}-av1" in list_netns()
            assert len(_run_namespaces(detached.run_id)) == 3, "detached runs stay without --all"
            for node in detached.nodes.values():
                node.ns.close()  # type: ignore[union-attr]
            report = clean(include_detached=True)
            assert report.startswith("cleaned 1 run(s)") and _run_namespaces(detached.run_id) == []
    finally:
        for name in made:
            delete_netns(name)


# ---- many vehicles -------------------------------------------------------------------------


def test_twenty_vehicles_four_cells(state_dir: Path) -> None:
    scenario = example_scenario(20, 4)
    with build(scenario, mode="run") as net:
        assert len(_run_namespaces(net.run_id)) == 28 and len(net.links) == 24
        for vehicle in ("av1", "av6", "av20"):
            gnb = scenario.topology.vehicles[int(vehicle[2:]) - 1].gnb
            core = scenario.topology.cell_of_gnb(gnb).core
            assert _udp_round_trip(net, vehicle, core, gnb)[1] == "hello back"
        # two vehicles of one cell reach each other through their gNB
        assert _icmp_echo(net, "av1", str(net["av5"].address_towards("gnb1"))) == 63
        forwarding = {n for n in net.nodes if net[n].read_sysctl("net.ipv4.ip_forward") == "1"}
        assert forwarding == {"gnb1", "gnb2", "gnb3", "gnb4"}
    assert _run_namespaces(net.run_id) == [] and st.list_runs() == []
