"""Real emulated links: the userspace backend (TUN relays) end to end, caps with HTB/IFB on TUN
devices, outages, relay death, `up`/`down` of relays, the timeline on live links, and the tc
backend (HTB here; its netem paths skip with the kernel's reason where sch_netem is missing).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from testbed import links
from testbed import state as st
from testbed.errors import HostError
from testbed.scenario import load
from testbed.timeline import TimelinePlayer
from testbed.topology import Net, build, teardown_run

pytestmark = pytest.mark.root

NETEM_OK, NETEM_DETAIL = (False, "not probed")
if os.geteuid() == 0:
    from testbed.check import netem_status

    NETEM_OK, NETEM_DETAIL = netem_status()


def _scenario(tmp_path: Path, backend: str, air_up: str, timeline: str = "") -> Path:
    path = tmp_path / "s.yaml"
    path.write_text(
        "name: t\nseed: 3\nduration: 10s\n"
        "topology:\n  cells:\n    - {gnb: gnb1, core: core1}\n  vehicles:\n"
        "    - {name: av1, gnb: gnb1}\n"
        f"links:\n  backend: {backend}\n  air:\n    uplink: {air_up}\n"
        "    downlink: {rate: 100mbit}\n"
        "  backhaul:\n    uplink: {rate: 1gbit}\n    downlink: {rate: 1gbit}\n" + timeline
    )
    return path


def _rtt_ms(net: Net, count: int = 5) -> float:
    """Median RTT av1 -> gnb1 over the air link, one datagram at a time."""
    addr = str(net["gnb1"].address_towards("av1"))
    server, client = net["gnb1"].socket(), net["av1"].socket()
    rtts = []
    try:
        server.bind((addr, 0))
        server.settimeout(1)
        client.settimeout(1)
        for _ in range(count):
            t0 = time.perf_counter()
            client.sendto(b"x", (addr, server.getsockname()[1]))
            try:
                data, peer = server.recvfrom(16)
                server.sendto(data, peer)
                client.recvfrom(16)
            except TimeoutError:
                continue
            rtts.append((time.perf_counter() - t0) * 1000)
    finally:
        server.close()
        client.close()
    return sorted(rtts)[len(rtts) // 2] if rtts else float("inf")


def _qdisc_kinds(net: Net, node: str) -> set[str]:
    return {q.get_attr("TCA_KIND") for q in net[node].ipr.get_qdiscs()}


def test_userspace_links_carry_the_profiles_and_change_live(
    state_dir: Path, tmp_path: Path
) -> None:
    scenario = load(_scenario(tmp_path, "userspace", "{rate: 20mbit, delay: 5ms}"))
    with build(scenario, mode="run") as net:
        assert net.link_backend is not None and net.link_backend.name == "userspace"
        control = net.control
        assert isinstance(control, links.UserspaceController)
        relay = control.relays["av1-gnb1"]
        assert relay.profiles["uplink"].delay_s == 0.005
        assert relay.profiles["uplink"].rate_bps == 20e6
        # Every relay is on file, and its control socket is in the run's state folder.
        pids = sorted(r.pid for r in control.relays.values())
        assert sorted(p.pid for p in st.load_run(net.run_id).pids) == pids
        assert sorted(links.relay_pids(net.state.namespaces)) == pids
        assert Path(relay.control_path).parent == state_dir / net.run_id
        assert 5 <= _rtt_ms(net) < 9
        control.set("av1-gnb1", "both", {"delay_s": 0.010})
        assert control.profile("av1-gnb1", "downlink").delay_s == 0.010
        assert control.profile("av1-gnb1", "uplink").rate_bps == 20e6  # untouched field
        assert 20 <= _rtt_ms(net) < 24
    assert links.relay_pids(net.state.namespaces) == []
    assert not (state_dir / net.run_id).exists()


def test_shape_caps_a_tun_interface_with_htb_and_ifb(state_dir: Path, tmp_path: Path) -> None:
    scenario = load(_scenario(tmp_path, "userspace", "{delay: 1ms}"))
    with build(scenario, mode="run") as net:
        assert net.control is not None
        net.control.shape("av1", 5e6, 3e6)
        kinds = _qdisc_kinds(net, "av1")
        assert {"htb", "ingress"} <= kinds
        assert net["av1"].ipr.link_lookup(ifname="ifb-gnb1")
        net.control.shape("av1", 8e6, None)  # in place
        net.control.clear("av1")
        assert "htb" not in _qdisc_kinds(net, "av1")
        assert not net["av1"].ipr.link_lookup(ifname="ifb-gnb1")
        # A gNB is capped towards its core.
        assert links.shaped_interface(net, "gnb1")[1] == "core1"


def _uplink_probes(net: Net, until_s: float, every_s: float = 0.01) -> tuple[list[float], set[int]]:
    """Datagram k from av1 to gnb1 every `every_s` until `until_s` (monotonic): each one's
    send time, and the numbers that arrived."""
    addr = str(net["gnb1"].address_towards("av1"))
    server, client = net["gnb1"].socket(), net["av1"].socket()
    sent: list[float] = []
    got: set[int] = set()
    try:
        server.bind((addr, 0))
        server.setblocking(False)
        while time.monotonic() < until_s:
            client.sendto(len(sent).to_bytes(4, "big"), (addr, server.getsockname()[1]))
            sent.append(time.monotonic())
            time.sleep(every_s)
        time.sleep(0.05)  # the last ones' 1 ms of delay, and then some
        while True:
            try:
                got.add(int.from_bytes(server.recv(16), "big"))
            except BlockingIOError:
                break
    finally:
        server.close()
        client.close()
    return sent, got


def test_outage_drops_everything_for_its_duration(state_dir: Path, tmp_path: Path) -> None:
    """A probe every 10 ms across a 0.5 s outage: every one sent inside it is lost, every one
    sent once it is over arrives (20 ms of margin each side for the command's delivery and
    the relay's wake-ups)."""
    scenario = load(_scenario(tmp_path, "userspace", "{delay: 1ms}"))
    with build(scenario, mode="run") as net:
        assert net.control is not None
        t0 = time.monotonic()
        net.control.outage("av1-gnb1", 0.5)
        applied = time.monotonic()
        sent, got = _uplink_probes(net, until_s=t0 + 0.9)
    inside = [k for k, s in enumerate(sent) if applied + 0.02 <= s <= t0 + 0.48]
    after = [k for k, s in enumerate(sent) if s >= applied + 0.52]
    print(f"outage applied in {(applied - t0) * 1e3:.1f} ms; {len(sent)} probes, {len(got)} in")
    assert len(inside) >= 30 and len(after) >= 20, (len(inside), len(after))
    assert not got & set(inside), sorted(got & set(inside))
    assert set(after) <= got, sorted(set(after) - got)


def test_a_dead_relay_is_reported_within_a_second(state_dir: Path, tmp_path: Path) -> None:
    scenario = load(_scenario(tmp_path, "userspace", "{delay: 1ms}"))
    with build(scenario, mode="run") as net:
        control = net.control
        assert isinstance(control, links.UserspaceController)
        control.watch()
        os.kill(control.relays["av1-gnb1"].pid, signal.SIGKILL)
        t0 = time.monotonic()
        assert control.died.wait(1.0)
        assert time.monotonic() - t0 < 1.0
        assert "died" in (control.failure() or "")


def test_up_leaves_relays_running_and_down_stops_them(state_dir: Path, tmp_path: Path) -> None:
    scenario = load(_scenario(tmp_path, "userspace", "{delay: 1ms}"))
    net = build(scenario, mode="up")
    control = net.control
    assert isinstance(control, links.UserspaceController)
    log_dirs = [Path(r._tmpdir) for r in control.relays.values() if r._tmpdir]
    pids = links.relay_pids(net.state.namespaces)
    assert len(pids) == 2 and all(d.is_dir() for d in log_dirs)
    assert (state_dir / net.run_id / "link-backend.json").is_file()
    removed = teardown_run(net.run_id)
    assert removed.processes >= 2 and not removed.problems
    assert links.relay_pids(net.state.namespaces) == []
    assert not any(d.exists() for d in log_dirs)
    assert not (state_dir / net.run_id).exists()


def test_timeline_plays_on_real_links(state_dir: Path, tmp_path: Path) -> None:
    (tmp_path / "up.csv").write_text("time_s,mbit\n0,4\n0.2,8\n")
    timeline = (
        "timeline:\n"
        "  - {at: 0s, set: av1-gnb1, delay: 3ms}\n"
        "  - {at: 100ms, shape: av1, uplink: 10mbit}\n"
        "  - {at: 200ms, trace: av1-gnb1, direction: uplink, file: up.csv}\n"
        "  - {at: 300ms, clear: av1}\n"
    )
    scenario = load(_scenario(tmp_path, "userspace", "{delay: 1ms}", timeline))
    with build(scenario, mode="run") as net:
        assert net.control is not None
        log = tmp_path / "events.jsonl"
        player = TimelinePlayer(scenario.timeline, net.control, log_path=log)
        player.start()
        assert player.wait(5)
        assert player.failure is None
        assert [a.kind for a in player.applied] == ["set", "shape", "trace", "clear"]
        assert all(a.lateness_s >= 0 for a in player.applied)
        assert len(log.read_text().splitlines()) == 4
        assert net.control.profile("av1-gnb1", "uplink").delay_s == 0.003
        assert "htb" not in _qdisc_kinds(net, "av1")


def test_tc_backend_shapes_rates_with_htb_at_the_gnb(state_dir: Path, tmp_path: Path) -> None:
    scenario = load(_scenario(tmp_path, "tc", "{rate: 20mbit}"))
    with build(scenario, mode="run") as net:
        assert net.link_backend is not None and net.link_backend.name == "tc"
        assert isinstance(net.control, links.TcController)
        assert {"htb", "ingress"} <= _qdisc_kinds(net, "gnb1")
        assert "htb" not in _qdisc_kinds(net, "av1")  # the gNB end carries both directions
        net.control.set("av1-gnb1", "uplink", {"rate_bps": 5e6})
        tree = net.control.shapers["av1-gnb1"].side("uplink").state()
        assert tree is not None and tree.profile_rate * 8 == 5e6
        assert _rtt_ms(net) < 5


def test_tc_backend_captures_a_link_with_its_packets_after_the_shaper(
    state_dir: Path, tmp_path: Path
) -> None:
    from tests.tshark import TSHARK
    from tests.tshark import fields as tshark_fields

    if TSHARK is None:
        pytest.skip("tshark is not installed (`sudo make test`)")
    scenario = load(_scenario(tmp_path, "tc", "{rate: 20mbit}"))
    path = tmp_path / "pcap" / "av1-gnb1.pcapng"
    with build(scenario, mode="run") as net:
        assert isinstance(net.control, links.TcController)
        net.control.capture("av1-gnb1", path)
        state = st.load_run(net.run_id)
        assert state is not None
        (ref,) = [p for p in state.pids if p.what == "capture av1-gnb1"]
        assert _rtt_ms(net, count=9) < 5  # 9 datagrams up (av1 -> gnb1), 9 answers down
        info = net.control.stop_capture("av1-gnb1")
        assert not Path(f"/proc/{ref.pid}").exists()
        net.control.capture("av1-gnb1", tmp_path / "second.pcapng")  # closed with the run
    assert info["packets"] == {"uplink": 9, "downlink": 9} and info["dropped"] is None
    rows = tshark_fields(path, "udp", "frame.interface_name", "ip.src", "udp.length")
    av1, gnb1 = str(net["av1"].address_towards("gnb1")), str(net["gnb1"].address_towards("av1"))
    assert [tuple(r) for r in rows] == [("av1-gnb1 uplink", av1, "9"),
                                        ("av1-gnb1 downlink", gnb1, "9")] * 9  # fmt: skip
    assert (tmp_path / "second.pcapng").is_file()  # finished when the run was torn down


@pytest.mark.skipif(NETEM_OK, reason="this kernel has sch_netem: tc takes delay here")
def test_tc_with_delay_on_a_kernel_without_netem_is_a_host_error(
    state_dir: Path, tmp_path: Path
) -> None:
    scenario = load(_scenario(tmp_path, "tc", "{rate: 20mbit, delay: 5ms}"))
    with pytest.raises(HostError, match="backend: userspace"):
        build(scenario, mode="run")
    assert st.list_runs() == []


@pytest.mark.skipif(not NETEM_OK, reason=f"tc netem path: {NETEM_DETAIL}")
def test_tc_backend_applies_netem_delay(state_dir: Path, tmp_path: Path) -> None:
    scenario = load(_scenario(tmp_path, "tc", "{rate: 20mbit, delay: 5ms}"))
    with build(scenario, mode="run") as net:
        assert "netem" in _qdisc_kinds(net, "gnb1")
        assert 5 <= _rtt_ms(net) < 9
        assert net.control is not None
        net.control.outage("av1-gnb1", 0.3)
        assert _rtt_ms(net, count=1) == float("inf")


def test_the_air_links_of_one_gnb_with_a_radio_share_one_relay_and_its_cell(
    state_dir: Path, tmp_path: Path
) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(
        "name: t\nseed: 3\nduration: 10s\n"
        "topology:\n  cells:\n    - {gnb: gnb1, core: core1, scheduler: pf}\n"
        "    - {gnb: gnb2, core: core2}\n  vehicles:\n"
        "    - {name: av1, gnb: gnb1}\n    - {name: av2, gnb: gnb1}\n"
        "    - {name: av3, gnb: gnb2}\n"
        "links:\n  air:\n    uplink: {radio: oai-tdd-30k}\n    downlink: {radio: oai-tdd-30k}\n"
    )
    scenario = load(path)
    with build(scenario, mode="run") as net:
        control = net.control
        assert isinstance(control, links.UserspaceController)
        relays = control.relays
        # One process per cell: av1's and av2's air links in gnb1's, av3's alone.
        assert relays["av1-gnb1"].pid == relays["av2-gnb1"].pid
        assert relays["av3-gnb2"].pid != relays["av1-gnb1"].pid
        assert relays["gnb1-core1"].pid not in {relays["av1-gnb1"].pid, relays["av3-gnb2"].pid}
        assert "--scheduler" in relays["av1-gnb1"].command()
        assert control.counters("av2-gnb1")["cell"] == "gnb1"  # type: ignore[index]
        assert control.counters("gnb1-core1")["cell"] is None  # type: ignore[index]
        # Both UEs reach their gNB through the shared relay, and a live change reaches the
        # attached link (not the host's).
        assert _rtt_ms(net) > 1.0  # over the radio: slots, not a wire
        control.set("av2-gnb1", "uplink", {"radio": {"mcs": 5}})
        assert control.profile("av2-gnb1", "uplink").radio.mcs == 5  # type: ignore[union-attr]
        assert control.profile("av1-gnb1", "uplink").radio.mcs == 20  # type: ignore[union-attr]
        pids = links.relay_pids(net.state.namespaces)
    assert pids and links.relay_pids(net.state.namespaces) == []


@pytest.mark.alone  # times the first packet after a quiet spell: nothing else on the CPUs
def test_rrc_states_from_the_scenario_hold_the_first_packet_after_a_quiet_spell(
    state_dir: Path, tmp_path: Path
) -> None:
    # links.air.rrc reaches the relay: after 1.2 s of quiet (inactivity 1 s) the first
    # datagram waits the 30 ms resume, the next one does not; av2 (rrc: null) never waits.
    path = tmp_path / "rrc.yaml"
    path.write_text(
        "name: t\nseed: 3\nduration: 10s\n"
        "topology:\n  cells:\n    - {gnb: gnb1, core: core1}\n  vehicles:\n"
        "    - {name: av1, gnb: gnb1}\n    - {name: av2, gnb: gnb1}\n"
        "links:\n  backend: auto\n  air:\n    uplink: {delay: 2ms}\n    downlink: {delay: 2ms}\n"
        "    rrc: {inactivity: 1s, resume: 30ms, idle_after: null}\n"
        "  overrides:\n    - {link: av2-gnb1, rrc: null}\n"
    )
    scenario = load(path)
    assert links.choose_backend(scenario).name == "userspace"

    def one_way_ms(net: Net, vehicle: str, gaps_s: list[float]) -> list[float]:
        addr = str(net["gnb1"].address_towards(vehicle))
        server, client = net["gnb1"].socket(), net[vehicle].socket()
        out = []
        try:
            server.bind((addr, 0))
            server.settimeout(2)
            for gap in gaps_s:
                time.sleep(gap)
                t0 = time.perf_counter()
                client.sendto(b"x", (addr, server.getsockname()[1]))
                server.recv(16)
                out.append((time.perf_counter() - t0) * 1000)
        finally:
            server.close()
            client.close()
        return out

    with build(scenario, mode="run") as net:
        first, second = one_way_ms(net, "av1", [1.2, 0.05])
        plain = one_way_ms(net, "av2", [1.2, 0.05])
    assert 2.0 + 30.0 - 1.0 < first < 2.0 + 30.0 + 8.0, first
    assert second < 8.0 and all(p < 8.0 for p in plain), (second, plain)
