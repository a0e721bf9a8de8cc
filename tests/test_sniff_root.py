"""Captures of a tc-backend link (`netem.tc.sniff`) on a real veth pair, read back by tshark.

Two namespaces (`els-<hex>-a|b`) joined by a veth pair, as the tc backend joins two nodes
(no qdisc is needed to test what a capture sees: netem sits on the sending side, the capture
on the receiving one). tshark is the oracle: the file must hold each UDP datagram once, in
the direction it went, TCP's super-packets that crossed the veth whole as MTU-sized packets
whose checksums tshark verifies, and nothing an end sent itself twice.
"""

from __future__ import annotations

import contextlib
import secrets
import socket
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from netem.netns import in_netns
from netem.tc.sniff import LinkSniffer, SniffConfig, SniffError
from tests.realrun import processes_mentioning
from tests.tshark import TSHARK
from tests.tshark import fields as tshark_fields

pytestmark = [
    pytest.mark.root,
    pytest.mark.skipif(TSHARK is None, reason="tshark is not installed (`sudo make test`)"),
]

A, B = "10.77.0.1", "10.77.0.2"


def sh(*args: str) -> None:
    subprocess.run(args, check=True, capture_output=True, timeout=10)


@contextlib.contextmanager
def veth_pair() -> Iterator[tuple[str, str]]:
    tag = secrets.token_hex(3)
    a, b = f"els-{tag}-a", f"els-{tag}-b"
    try:
        for ns in (a, b):
            sh("ip", "netns", "add", ns)
        sh("ip", "link", "add", f"s{tag}a", "netns", a, "type", "veth",
           "peer", "name", f"s{tag}b", "netns", b)  # fmt: skip
        for ns, dev, addr in ((a, f"s{tag}a", A), (b, f"s{tag}b", B)):
            sh("ip", "-n", ns, "link", "set", dev, "name", "e0")
            sh("ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", "e0")
            sh("ip", "-n", ns, "link", "set", "e0", "up")
        yield a, b
    finally:
        for ns in (a, b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_a_capture_holds_each_packet_once_as_a_wire_carries_it(tmp_path: Path) -> None:
    path = tmp_path / "a-b.pcapng"
    with veth_pair() as (a, b):
        config = SniffConfig("a-b", str(path), a, "e0", b, "e0")
        with LinkSniffer(config) as sniffer:
            with in_netns(b):
                server = socket.create_server((B, 5001))
                udp_b = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                udp_b.bind((B, 5002))
            received = bytearray()

            def sink() -> None:
                conn, _ = server.accept()
                with conn:
                    while chunk := conn.recv(65536):
                        received.extend(chunk)

            t = threading.Thread(target=sink, daemon=True)
            t.start()
            with in_netns(a):
                client = socket.create_connection((B, 5001), timeout=10)
                udp_a = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                udp_a.bind((A, 5003))
            payload = bytes(range(256)) * 4096  # 1 MiB up
            with client:
                client.sendall(payload)
            t.join(20)
            for i in range(7):  # up: 7 datagrams, down: 3
                udp_a.sendto(bytes([i]) * 300, (B, 5002))
            for i in range(3):
                udp_b.sendto(bytes([i]) * 200, (A, 5003))
            for s in (server, udp_a, udp_b):
                s.close()
            pid = sniffer.pid
            result = sniffer.close()
        assert pid is not None and not Path(f"/proc/{pid}").exists()
    assert bytes(received) == payload
    assert result["path"] == str(path) and path.is_file()
    assert not Path(f"{path}.part").exists()

    rows = tshark_fields(path, "udp", "frame.interface_name", "udp.dstport", "udp.length")
    up = [r for r in rows if r[0] == "a-b uplink"]
    down = [r for r in rows if r[0] == "a-b downlink"]
    assert [(r[1], r[2]) for r in up] == [("5002", "308")] * 7
    assert [(r[1], r[2]) for r in down] == [("5003", "208")] * 3
    # TCP: each data packet within the veth's MTU, every checksum right, all bytes there.
    tcp = subprocess.run(
        [TSHARK, "-r", str(path), "-o", "tcp.check_checksum:TRUE", "-o", "ip.check_checksum:TRUE",
         "-Y", "tcp && frame.interface_name == \"a-b uplink\"", "-T", "fields",
         "-e", "frame.len", "-e", "tcp.checksum.status", "-e", "ip.checksum.status",
         "-e", "tcp.len"],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout.split("\n")  # fmt: skip
    tcp_rows = [r.split("\t") for r in tcp if r]
    assert max(int(r[0]) for r in tcp_rows) <= 1500
    assert {r[1] for r in tcp_rows} == {"1"} and {r[2] for r in tcp_rows} == {"1"}  # good
    assert sum(int(r[3]) for r in tcp_rows) == len(payload)
    assert result["packets"]["uplink"] == len(up) + len(tcp_rows)
    assert result["dropped"] is None


def test_a_capture_on_a_missing_interface_says_which_and_leaves_nothing(tmp_path: Path) -> None:
    with veth_pair() as (a, b):
        config = SniffConfig("a-b", str(tmp_path / "x.pcapng"), a, "e0", b, "nope0")
        sniffer = LinkSniffer(config)
        with pytest.raises(SniffError, match="nope0"):
            sniffer.start()
    assert list(tmp_path.iterdir()) == []
    # no capture process, and its own working folder (config, log) is gone too
    assert sniffer.proc is None and not Path(sniffer._dir).exists()
    assert processes_mentioning(sniffer._dir) == []
