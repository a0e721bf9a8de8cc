"""A handover for real (`channel.handover`): the vehicle's traffic moves from one gNB to the
other inside the namespaces, its N3 tunnel with it, and the user plane stops for the
configured interruption.

Oracles we did not write: `ip route` inside the namespaces for the routes, tshark on the two
gNBs' N3 devices for which tunnel carries the UE (G-PDUs with its TEIDs and inner address),
and the arrival times of numbered datagrams at the edge server for the interruption.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import threading
import time
from pathlib import Path

import pytest

from netem.netns import list_netns
from testbed.connectivity import echo_rtts
from testbed.scenario import load
from testbed.scenario.model import HandoverEvent, Scenario
from testbed.timeline import TimelinePlayer
from testbed.topology import Net, build
from tests.tshark import TSHARK, Capture

pytestmark = [pytest.mark.root, pytest.mark.alone]

SCENARIO = """
version: 1
name: handover
seed: 3
duration: 20s
topology:
  cells:
    - {{gnb: gnb1, upf: upf1, edge: edge1, site: auto}}
    - {{gnb: gnb2, upf: upf1, edge: edge1, site: auto}}
  vehicles:
    - {{name: av1, gnb: gnb1}}
links:
  backend: userspace
  air: {{radio: oai-tdd-30k}}
  n3: {{uplink: {{delay: 1ms}}, downlink: {{delay: 1ms}}}}
  n6: {{uplink: {{delay: 1ms}}, downlink: {{delay: 1ms}}}}
channel:
  model: uma
  handover: {{interruption: {gap_ms}ms, lossless: {lossless}}}
"""
UE = "10.45.0.2"  # the pool's first UE address
SLOT_MS = 0.5  # oai-tdd-30k: 30 kHz subcarriers
#: How much shorter or longer than the interruption the silence at the edge may be (beyond a
#: slot, and the stream's own spacing for longer). Before the gap, the
#: last datagram leaves the source's air link and crosses gnb1's N3 relay and the N6 relay;
#: after it, the first crosses gnb2's N3 relay and N6: separate relay processes that share the
#: host's cores with the others and the test's threads, so one late wake-up on the first path
#: shortens the silence by as much, and one on the second path lengthens it by as much.
#: Measured on a 2-core host: 38.9-39.5 ms in 4 of 26 lossy runs, 39.5-46.0 ms in the others;
#: in the short ones the edge's kernel receive timestamps (SO_TIMESTAMPNS) gave the same
#: silence to 0.06 ms, so it is not the test thread's lateness. Long ones, later: 46.43 ms
#: (lossy) and 46.68 ms (lossless) with the stream's spacing at 5.22 and 5.32 ms, 0.7 and
#: 0.9 ms past interruption + slot + spacing, 1 in ~10 runs of each.
DOWNSTREAM_JITTER_MS = 2.0
GAP_MS = 40.0
SEND_EVERY_S = 0.001
PORT = 7411


def _scenario(tmp_path: Path, lossless: bool = True, gap_ms: float = GAP_MS) -> Scenario:
    path = tmp_path / "handover.yaml"
    path.write_text(SCENARIO.format(lossless=str(lossless).lower(), gap_ms=gap_ms))
    return load(path)


def _ip_json(netns: str, *args: str) -> list[dict]:  # type: ignore[type-arg]
    out = subprocess.run(
        ["ip", "-n", netns, "-j", *args], capture_output=True, text=True, check=True, timeout=10
    ).stdout
    return json.loads(out)


def _stream(net: Net, event: HandoverEvent, seconds: float, at_s: float) -> tuple[
    dict[int, float], dict[int, float], float
]:  # fmt: skip
    """Send a numbered datagram from av1 to the edge every `SEND_EVERY_S` for `seconds`,
    handing over at `at_s`: (seq -> sent, seq -> arrived, when the handover was called), on
    one perf_counter clock."""
    edge_addr = str(net.server_address(net.scenario.topology.cells[0]))
    server, client = net["edge1"].socket(), net["av1"].socket()
    sent: dict[int, float] = {}
    arrived: dict[int, float] = {}
    done = threading.Event()
    try:
        server.bind((edge_addr, PORT))
        server.settimeout(0.2)

        def receive() -> None:
            while not done.is_set():
                try:
                    data = server.recv(2048)
                except TimeoutError:
                    continue
                arrived[int.from_bytes(data[:4], "big")] = time.perf_counter()

        rx = threading.Thread(target=receive)
        rx.start()
        # A first datagram, unnumbered in the result, wakes the UE's uplink (SR, grants).
        client.sendto(b"\xff" * 4 + b"w" * 200, (edge_addr, PORT))
        time.sleep(0.1)
        t0 = time.perf_counter()
        called = None
        seq = 0
        assert net.control is not None
        while (now := time.perf_counter()) - t0 < seconds:
            if called is None and now - t0 >= at_s:
                called = time.perf_counter()
                net.control.handover(event)
                continue
            client.sendto(seq.to_bytes(4, "big") + b"x" * 200, (edge_addr, PORT))
            sent[seq] = now
            seq += 1
            time.sleep(max(0.0, t0 + seq * SEND_EVERY_S - time.perf_counter()))
        # Until the stream has drained: no arrival for 0.3 s (at most 3 s). A fixed 0.3 s
        # once counted the stream's tail as lost on a loaded CI host (the first try of a
        # rerun listed seqs up to the last as lost in a lossless handover).
        quiet_until = time.perf_counter() + 3.0
        while time.perf_counter() < quiet_until:
            heard = len(arrived)
            time.sleep(0.3)
            if len(arrived) == heard:
                break
    finally:
        done.set()
        rx.join()
        server.close()
        client.close()
    arrived.pop(0xFFFFFFFF, None)
    assert called is not None
    return sent, arrived, called


def _gaps(arrived: dict[int, float]) -> list[tuple[float, int]]:
    """(gap in ms before each arrival, its seq), arrivals in time order."""
    order = sorted(arrived, key=arrived.__getitem__)
    return [((arrived[b] - arrived[a]) * 1000, b) for a, b in itertools.pairwise(order)]


@pytest.mark.skipif(TSHARK is None, reason="tshark is not installed (make test installs it)")
def test_after_a_handover_the_routes_and_the_n3_tunnel_are_the_target_s(
    state_dir: Path, tmp_path: Path
) -> None:
    scenario = _scenario(tmp_path)
    assert [link.name for link in scenario.links.links if link.kind == "air"] == [
        "av1-gnb1",
        "av1-gnb2",
    ]
    with build(scenario, mode="run") as net:
        assert net.control is not None and net.core is not None
        edge = str(net.server_address(scenario.topology.cells[0]))
        # Before: the first cell's. The second has the session prepared (its route to the UE).
        assert _ip_json(net["av1"].netns, "route", "get", edge)[0]["dev"] == "gnb1"
        assert _ip_json(net["upf1"].netns, "route", "get", UE)[0]["dev"] == "gtp-gnb1"
        prepared = _ip_json(net["gnb2"].netns, "route", "show", f"{UE}/32")
        assert prepared and prepared[0]["dev"] == "av1"
        assert len(echo_rtts(net["av1"], net["edge1"], edge, count=5)) == 5
        # Through the timeline player, as a run plays it: in a thread of its own.
        player = TimelinePlayer(
            [HandoverEvent(0.0, "av1", "gnb1", "gnb2", 0.04, True)], net.control
        ).start()
        assert player.wait(5) and player.failure is None, player.failure
        assert [a.kind for a in player.applied] == ["handover"]
        time.sleep(0.1)
        route = _ip_json(net["av1"].netns, "route", "get", edge)[0]
        assert (route["dev"], route["prefsrc"]) == ("gnb2", UE)
        assert route["gateway"] == str(net.links["av1-gnb2"].addresses.upper.ip)
        assert _ip_json(net["upf1"].netns, "route", "get", UE)[0]["dev"] == "gtp-gnb2"
        old = Capture(net["gnb1"].netns, "upf1", tmp_path / "n3-gnb1.pcapng")
        new = Capture(net["gnb2"].netns, "upf1", tmp_path / "n3-gnb2.pcapng")
        try:
            rtts = echo_rtts(net["av1"], net["edge1"], edge, count=20)
        finally:
            old.stop()
            new.stop()
        run_id = net.run_id
    assert len(rtts) == 20
    fields = ("gtp.teid", "gtp.ext_hdr.pdu_ses_con.pdu_type", "ip.src", "ip.dst")
    rows = new.fields("gtp.message == 0xff", *fields)
    up = [r for r in rows if r[1] == "1"]
    down = [r for r in rows if r[1] == "0"]
    # The echo requests up the target's N3 in the vehicle's session, the replies down it.
    assert len(up) >= 20 and len(down) >= 20, (len(up), len(down))
    assert {(r[0], r[2].split(",")[1]) for r in up} == {("0x00001001", UE)}
    assert {(r[0], r[3].split(",")[1]) for r in down} == {("0x00002001", UE)}
    # Nothing of the UE's on the source's N3 any more (its path checks still run).
    assert old.fields("gtp.message == 0xff", "frame.number") == []
    assert not [n for n in list_netns() if n.startswith(f"el-{run_id}-")]


@pytest.mark.parametrize("lossless", [True, False], ids=["lossless", "lossy"])
def test_the_user_plane_stops_for_the_interruption_then_resumes(
    state_dir: Path, tmp_path: Path, lossless: bool
) -> None:
    """Lossless: nothing reaches the edge for the interruption (± one slot, beyond the
    stream's own spacing, and either way by at most the relays' jitter after the air link),
    then every datagram, in order. Lossy: exactly the datagrams in flight on the source link
    are lost (the relay's "handover" drops), one run of them."""
    scenario = _scenario(tmp_path, lossless)
    event = HandoverEvent(0.0, "av1", "gnb1", "gnb2", GAP_MS / 1000, lossless)
    with build(scenario, mode="run") as net:
        sent, arrived, called = _stream(net, event, seconds=0.6, at_s=0.3)
        assert net.control is not None
        source = net.control.counters("av1-gnb1")
        assert source is not None
    gaps = _gaps(arrived)
    during = [(g, s) for g, s in gaps if arrived[s] > called]
    longest, after = max(during)
    # The stream's own spacing at the edge (the TDD pattern bunches the uplink) away from
    # the handover: what the gap may exceed the interruption by besides one slot.
    spacing = max(g for g, s in gaps if abs(arrived[s] - called) > 0.1)
    lost = sorted(set(sent) - set(arrived))
    print(
        f"\n{'lossless' if lossless else 'lossy'}: longest silence {longest:.2f} ms "
        f"(interruption {GAP_MS:g} ms, normal spacing up to {spacing:.2f} ms), "
        f"first after it {(arrived[after] - called) * 1000:.2f} ms after the call, lost {lost}"
    )
    jitter = DOWNSTREAM_JITTER_MS
    assert GAP_MS - SLOT_MS - jitter <= longest <= GAP_MS + SLOT_MS + spacing + jitter
    order = sorted(arrived, key=arrived.__getitem__)
    assert order == sorted(order), "delivered out of order"
    drops = source["uplink"]["total"]["dropped_packets"]
    if lossless:
        assert lost == [] and not drops
        return
    # Lossy: the ones in flight when the gap began (sent within the link's few ms before the
    # call), one contiguous run, each counted by the relay.
    assert lost and lost == list(range(lost[0], lost[-1] + 1))
    assert all(called - 0.02 <= sent[s] <= called + 0.005 for s in lost), [
        round((sent[s] - called) * 1000, 2) for s in lost
    ]
    assert drops == {"handover": len(lost)}
    assert len(arrived) == len(sent) - len(lost)
