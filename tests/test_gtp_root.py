"""The N3 path for real: UE -> gNB -> GTP-U over N3 -> UPF -> N6 -> edge, in four namespaces.

Each link is a userspace link (TUN ends, the relay); the gNB and the UPF run `netem.gtpu.endpoint`
endpoints. tshark, capturing on the gNB's N3 device, is the oracle for what crosses N3: every
UDP/2152 packet must dissect as GTP-U with the session's TEID per direction, the PDU type of
its direction and the QFI its rule gives, no outer fragment, and an inner source in the UE
pool. Namespaces (`elg-<hex>-*`), relays and endpoints are removed even when a test fails.
"""

from __future__ import annotations

import contextlib
import ipaddress
import secrets
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from netem.gtpu.endpoint import EndpointConfig, GtpEndpoint, QosRule, Session
from netem.netns import in_netns
from netem.relay.client import UserspaceLink
from tests.tshark import TSHARK, Capture

pytestmark = [pytest.mark.root, pytest.mark.alone]

UE, GNB_AIR = "10.45.0.2", "10.201.0.1"
GNB_N3, UPF_N3 = "10.100.3.1", "10.100.3.2"
UPF_N6, EDGE = "10.100.6.1", "10.100.6.2"
POOL = "10.45.0.0/16"
UL_TEID, DL_TEID = 0x1001, 0x2001
EDGE_PORT = 7400


def ip(ns: str, *args: str) -> None:
    subprocess.run(["ip", "-n", ns, *args], check=True, capture_output=True, timeout=10)


def sysctl(ns: str, key: str, value: str) -> None:
    subprocess.run(["ip", "netns", "exec", ns, "sysctl", "-qw", f"{key}={value}"], check=True,
                   capture_output=True, timeout=10)  # fmt: skip


@dataclass
class CorePath:
    ns: dict[str, str]
    gnb: GtpEndpoint
    upf: GtpEndpoint


@contextlib.contextmanager
def core_path(rules: tuple[QosRule, ...] = ()) -> Iterator[CorePath]:
    from pyroute2 import netns

    tag = secrets.token_hex(3)
    ns = {role: f"elg-{tag}-{role}" for role in ("ue", "gnb", "upf", "edge")}
    with contextlib.ExitStack() as stack:
        for name in ns.values():
            netns.create(name)
            stack.callback(lambda n=name: n in netns.listnetns() and netns.remove(n))
        air = UserspaceLink(
            ns["ue"], ns["gnb"], dev_a="pdu0", dev_b="air0",
            addr_a=f"{UE}/32", addr_b=f"{GNB_AIR}/32", mtu=1456, offload=False,
        )  # fmt: skip
        n3 = UserspaceLink(ns["gnb"], ns["upf"], dev_a="n3", dev_b="n3",
                           addr_a=f"{GNB_N3}/30", addr_b=f"{UPF_N3}/30", offload=False)  # fmt: skip
        n6 = UserspaceLink(ns["upf"], ns["edge"], dev_a="n6", dev_b="n6",
                           addr_a=f"{UPF_N6}/30", addr_b=f"{EDGE}/30")  # fmt: skip
        for link in (air, n3, n6):
            stack.enter_context(link)
        session = Session(UE, UL_TEID, DL_TEID, GNB_N3, UPF_N3)
        gnb = stack.enter_context(GtpEndpoint(
            EndpointConfig("gnb", ns["gnb"], "gtp0", GNB_N3, (session,), rules), echo_interval_s=0.2
        ))  # fmt: skip
        upf = stack.enter_context(
            GtpEndpoint(EndpointConfig("upf", ns["upf"], "upf0", UPF_N3, (session,), rules))
        )
        # UE: its pool address on the PDU device, the default route through it.
        ip(ns["ue"], "route", "add", "default", "dev", "pdu0")
        # gNB: what arrives from the air goes into the tunnel; the UE is behind the air device.
        ip(ns["gnb"], "route", "add", f"{UE}/32", "dev", "air0")
        ip(ns["gnb"], "rule", "add", "iif", "air0", "lookup", "100")
        ip(ns["gnb"], "route", "add", "default", "dev", "gtp0", "table", "100")
        # UPF: the UE pool is behind the tunnel, the data network behind N6.
        ip(ns["upf"], "route", "add", POOL, "dev", "upf0")
        ip(ns["edge"], "route", "add", POOL, "via", UPF_N6)
        for role in ("gnb", "upf"):
            sysctl(ns[role], "net.ipv4.ip_forward", "1")
            sysctl(ns[role], "net.ipv4.conf.all.rp_filter", "0")
            for dev in ("gtp0", "upf0", "air0", "n3", "n6"):
                with contextlib.suppress(subprocess.CalledProcessError):
                    sysctl(ns[role], f"net.ipv4.conf.{dev}.rp_filter", "0")
        yield CorePath(ns, gnb, upf)


def udp_exchange(path: CorePath, sizes: list[int], tos: int = 0) -> list[int]:
    """UE sends UDP datagrams of `sizes` to the edge, which echoes them; the sizes it got back."""
    with in_netns(path.ns["edge"]):
        server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        server.bind((EDGE, EDGE_PORT))
    server.settimeout(2)

    def echo() -> None:
        with contextlib.suppress(OSError):
            for _ in sizes:
                data, peer = server.recvfrom(65535)
                server.sendto(data, peer)

    t = threading.Thread(target=echo, daemon=True)
    t.start()
    with in_netns(path.ns["ue"]):
        client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, tos)
    client.settimeout(2)
    got = []
    try:
        for n in sizes:
            client.sendto(bytes(n), (EDGE, EDGE_PORT))
            with contextlib.suppress(TimeoutError):
                got.append(len(client.recvfrom(65535)[0]))
    finally:
        client.close()
        server.close()
        t.join(3)
    return got


def test_ue_traffic_crosses_n3_in_gtpu_and_tshark_agrees(tmp_path: Path) -> None:
    if TSHARK is None:
        pytest.skip("tshark is not installed (`sudo make test` installs Debian's)")
    rules = (QosRule(qfi=5, ports=(EDGE_PORT,)),)
    with core_path(rules) as path:
        cap = Capture(path.ns["gnb"], "n3", tmp_path / "n3.pcapng")
        try:
            sizes = [64, 500, 1400, 1428]  # 1428 + 28 = 1456: the UE's whole MTU
            got = udp_exchange(path, sizes)
            time.sleep(0.5)  # an echo round or two
        finally:
            cap.stop()
        gnb, upf = path.gnb.close(), path.upf.close()
    assert got == sizes
    rows = cap.fields(
        "udp.port == 2152", "gtp.message", "gtp.teid", "gtp.ext_hdr.pdu_ses_con.pdu_type",
        "gtp.ext_hdr.pdu_ses_con.qos_flow_id", "ip.src", "ip.dst", "udp.dstport", "frame.len",
    )  # fmt: skip
    gpdus = [r for r in rows if r[0] == "0xff"]
    inner = [r for r in gpdus if r[6].endswith(f",{EDGE_PORT}") or r[6].startswith(f"{EDGE_PORT}")]
    up = [r for r in gpdus if r[4].split(",")[0] == GNB_N3]
    down = [r for r in gpdus if r[4].split(",")[0] == UPF_N3]
    assert len(up) == len(down) == len(sizes), rows
    # Every 2152 datagram is GTP-U (tshark found a message type in each).
    assert all(r[0] for r in rows)
    for r in up:
        inner_src = r[4].split(",")[1]
        assert (r[1], r[2], r[3]) == (f"0x{UL_TEID:08x}", "1", "5")
        assert ipaddress.ip_address(inner_src) in ipaddress.ip_network(POOL)
    for r in down:
        assert (r[1], r[2], r[3]) == (f"0x{DL_TEID:08x}", "0", "5")
        assert r[5].split(",")[1] == UE
    assert inner and max(int(r[7]) for r in gpdus) == 1456 + 44  # the largest fills N3's 1500
    frags = cap.fields("ip.flags.mf == 1 || ip.frag_offset > 0", "frame.number")
    assert frags == []
    echoes = cap.fields("gtp.message == 1 || gtp.message == 2", "gtp.message")
    assert {"0x01", "0x02"} <= {e[0] for e in echoes}
    assert gnb["sent"]["packets"] == upf["received"]["packets"] == len(sizes)
    assert upf["sent"]["packets"] == gnb["received"]["packets"] == len(sizes)
    assert gnb["qfi_sent"] == {"5": len(sizes)} and gnb["echo"]["responses_received"] >= 1
    assert 0 < gnb["overhead_share"] < 0.5 and not gnb["drops"] and not upf["drops"]


def test_ue_mtu_route_and_a_1_mib_tcp_transfer_each_way() -> None:
    with core_path() as path:
        out = subprocess.run(["ip", "-n", path.ns["ue"], "-o", "link", "show", "pdu0"],
                             capture_output=True, text=True, check=True).stdout  # fmt: skip
        assert " mtu 1456 " in out
        route = subprocess.run(["ip", "-n", path.ns["ue"], "route", "get", EDGE],
                               capture_output=True, text=True, check=True).stdout  # fmt: skip
        assert f"dev pdu0 src {UE}" in route
        with in_netns(path.ns["edge"]):
            server = socket.create_server((EDGE, EDGE_PORT))
        received = bytearray()
        answer = bytes(reversed(range(256))) * 4096  # 1 MiB back down

        def sink() -> None:
            conn, _ = server.accept()
            with conn:
                while chunk := conn.recv(65536):
                    received.extend(chunk)
                conn.sendall(answer)

        t = threading.Thread(target=sink, daemon=True)
        t.start()
        payload = bytes(range(256)) * 4096  # 1 MiB
        back = bytearray()
        with in_netns(path.ns["ue"]):
            client = socket.create_connection((EDGE, EDGE_PORT), timeout=10)
        with client:
            client.sendall(payload)
            client.shutdown(socket.SHUT_WR)
            while chunk := client.recv(65536):
                back.extend(chunk)
        t.join(20)
        server.close()
        gnb, upf = path.gnb.close(), path.upf.close()
    assert bytes(received) == payload and bytes(back) == answer
    assert not gnb["drops"] and not upf["drops"], (gnb["drops"], upf["drops"])
    assert gnb["sent"]["inner_bytes"] > len(payload) and upf["sent"]["inner_bytes"] > len(answer)
    # Each end hands the UE's TCP segments on coalesced (software GRO into its TUN), and the
    # bytes above arrived intact through them. How many of a MiB's ~750 segments meet in one
    # read depends on the host's speed (this one: ~710; a CI VM: 495), so the bound asks for
    # a quarter of them in super-packets of 3 or more on average; without GRO both are 0.
    segments = len(payload) // 1416
    for end in (upf, gnb):
        got = end["received"]
        assert got["gro_packets"] > segments // 4, got
        assert got["gro_frames"] * 3 < got["gro_packets"], got


def test_an_unknown_ue_is_not_tunnelled() -> None:
    with core_path() as path:
        # A second address on the UE that has no PDU session: the gNB must not tunnel it.
        ip(path.ns["ue"], "addr", "add", "10.45.9.9/32", "dev", "pdu0")
        with in_netns(path.ns["ue"]):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("10.45.9.9", 0))
        with s:
            s.sendto(b"x" * 10, (EDGE, EDGE_PORT))
        time.sleep(0.5)
        gnb = path.gnb.close()
        path.upf.close()
    assert gnb["drops"] == {"no_session": 1} and gnb["sent"].get("packets", 0) == 0
