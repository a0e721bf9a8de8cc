"""GTP-U encoding (TS 29.281 / TS 38.415) and the pcapng writer, checked against tshark.

tshark is the oracle: our G-PDUs, echoes and capture files must read back in Wireshark's own
dissector with the TEID, PDU type, QFI and sequence numbers we meant. Without tshark (not root,
so `make test` could not install it) those tests skip and say why.
"""

from __future__ import annotations

import ipaddress
import re
import struct
from pathlib import Path

import pytest

from netem.gso import checksum
from netem.gtpu import wire as gtpu
from netem.gtpu.endpoint import Endpoint, EndpointConfig, QosRule, Session
from netem.gtpu.wire import GtpError, decode, echo_request, echo_response, encode_gpdu
from netem.pcap import PcapngWriter
from tests.tshark import TSHARK
from tests.tshark import fields as tshark_fields

needs_tshark = pytest.mark.skipif(
    TSHARK is None, reason="tshark is not installed (`sudo make test` installs Debian's)"
)


def ipv4_udp(src: str, dst: str, sport: int, dport: int, payload: bytes, tos: int = 0) -> bytes:
    """An IPv4/UDP packet (UDP checksum 0: none, allowed over IPv4)."""
    udp = struct.pack("!HHHH", sport, dport, 8 + len(payload), 0) + payload
    head = struct.pack(
        "!BBHHHBBH4s4s", 0x45, tos, 20 + len(udp), 0x1234, 0x4000, 64, 17, 0,
        ipaddress.IPv4Address(src).packed, ipaddress.IPv4Address(dst).packed,
    )  # fmt: skip
    head = head[:10] + struct.pack("!H", checksum(head)) + head[12:]
    return head + udp


def test_gpdu_layout_is_the_specs() -> None:
    inner = ipv4_udp("10.45.0.2", "10.46.0.2", 5000, 6000, b"hello")
    g = encode_gpdu(0x01020304, inner, qfi=9, uplink=True, sequence=7)
    assert len(g) == gtpu.GPDU_HEADER_LEN + len(inner)
    # flags: version 1, PT 1, E 1; type 255; length counts everything after 8 octets
    assert g[:8] == bytes((0x34, 0xFF)) + struct.pack("!HI", 8 + len(inner), 0x01020304)
    # seq 7, N-PDU 0, next extension 0x85; container: 1 unit, PDU type 1 (UL), QFI 9, no next
    assert g[8:16] == bytes((0, 7, 0, 0x85, 1, 0x10, 9, 0))
    m = decode(g)
    assert (m.message_type, m.teid, m.payload, m.pdu_type, m.qfi, m.uplink) == (
        gtpu.G_PDU, 0x01020304, inner, gtpu.PDU_TYPE_UL, 9, True,
    )  # fmt: skip
    assert decode(encode_gpdu(5, inner, qfi=1, uplink=False)).uplink is False
    assert gtpu.N3_OVERHEAD == 44  # so a 1500-byte N3 leaves 1456 for the UE


def test_echo_round_trip() -> None:
    req = decode(echo_request(4242))
    assert (req.message_type, req.teid, req.sequence) == (gtpu.ECHO_REQUEST, 0, 4242)
    resp = echo_response(4242)
    assert resp[-2:] == bytes((gtpu.IE_RECOVERY, 0))
    assert decode(resp).message_type == gtpu.ECHO_RESPONSE and decode(resp).sequence == 4242


@pytest.mark.parametrize(
    ("datagram", "message"),
    [
        (b"\x34\xff", "shorter than a GTP-U header"),
        (bytes((0x54, 0xFF, 0, 0, 0, 0, 0, 1)), "not GTP-U: version 2"),
        (bytes((0x30, 0xFF, 0, 9, 0, 0, 0, 1)) + b"x", "length field says 9 bytes"),
        (bytes((0x34, 0xFF, 0, 8, 0, 0, 0, 1, 0, 0, 0, 0x85, 0, 0, 0, 0)), "bad length 0"),
        (bytes((0x30, 0x07, 0, 0, 0, 0, 0, 1)), "unknown GTP-U message type 7"),
    ],
)
def test_malformed_datagrams_are_refused_with_the_reason(datagram: bytes, message: str) -> None:
    with pytest.raises(GtpError, match=message):
        decode(datagram)


def test_bad_teid_or_qfi_is_refused() -> None:
    with pytest.raises(GtpError, match="QFI must be an integer 0-63, got 64"):
        encode_gpdu(1, b"", qfi=64, uplink=True)
    with pytest.raises(GtpError, match="TEID must fit 32 bits"):
        encode_gpdu(1 << 32, b"", qfi=1, uplink=True)


def test_an_interrupted_capture_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "pcap" / "n3.pcapng"
    with pytest.raises(RuntimeError), PcapngWriter(path) as cap:
        cap.packet(cap.interface("n3"), b"\x45" + bytes(19), 0)
        raise RuntimeError("Ctrl-C")
    assert list((tmp_path / "pcap").iterdir()) == []


@needs_tshark
def test_tshark_dissects_our_gpdus_echoes_and_capture_file(tmp_path: Path) -> None:
    ue, edge, gnb, upf = "10.45.0.2", "10.46.0.2", "10.100.3.1", "10.100.3.2"
    inner_up = ipv4_udp(ue, edge, 40000, 7400, b"x" * 100)
    inner_down = ipv4_udp(edge, ue, 7400, 40000, b"y" * 50)
    path = tmp_path / "n3.pcapng"
    t = 1_700_000_000_000_000_000
    with PcapngWriter(path) as cap:
        n3 = cap.interface("gnb1-upf1")
        up = encode_gpdu(0x11, inner_up, qfi=9, uplink=True, sequence=1)
        down = encode_gpdu(0x22, inner_down, qfi=5, uplink=False)
        cap.packet(n3, ipv4_udp(gnb, upf, 2152, 2152, up), t, direction="outbound")
        cap.packet(n3, ipv4_udp(upf, gnb, 2152, 2152, down), t + 1500, direction="inbound")
        cap.packet(n3, ipv4_udp(gnb, upf, 2152, 2152, echo_request(77)), t + 3000)
        cap.packet(n3, ipv4_udp(upf, gnb, 2152, 2152, echo_response(77)), t + 4000, comment="echo")
    fields = [
        "gtp.message", "gtp.teid", "gtp.ext_hdr.pdu_ses_con.pdu_type",
        "gtp.ext_hdr.pdu_ses_con.qos_flow_id", "ip.src", "gtp.seq_number", "frame.time_epoch",
    ]  # fmt: skip
    rows = tshark_fields(path, "gtp", *fields)
    # ip.src lists the outer, then the inner source: the inner packet is dissected too.
    assert [r[:4] for r in rows] == [
        ["0xff", "0x00000011", "1", "9"],
        ["0xff", "0x00000022", "0", "5"],
        ["0x01", "0x00000000", "", ""],
        ["0x02", "0x00000000", "", ""],
    ]
    assert rows[0][4] == f"{gnb},{ue}" and rows[1][4] == f"{upf},{edge}"
    assert rows[2][5] == rows[3][5] == "0x004d"  # 77
    assert rows[1][6] == "1700000000.000001500"  # nanosecond timestamps
    flags = tshark_fields(path, "frame", "frame.comment", "frame.packet_flags_direction")
    assert [f[1] for f in flags] == ["0x00000002", "0x00000001", "", ""]  # outbound, inbound
    assert [f[0] for f in flags] == ["", "", "", "echo"]


# ---- the endpoint's pure parts: QoS classification and its configuration ----------------------


def test_qos_rules_pick_the_flow_by_dscp_or_port_first_match_wins() -> None:
    from netem.gtpu.endpoint import QosRule, classify

    rules = (QosRule(qfi=5, ports=(7400,)), QosRule(qfi=7, dscp=46), QosRule(qfi=8, ports=(53,)))
    assert classify(ipv4_udp("10.45.0.2", "10.46.0.2", 40000, 7400, b""), rules, 1) == 5
    assert classify(ipv4_udp("10.46.0.2", "10.45.0.2", 7400, 40000, b""), rules, 1) == 5
    assert classify(ipv4_udp("10.45.0.2", "10.46.0.2", 1, 2, b"", tos=46 << 2), rules, 1) == 7
    assert classify(ipv4_udp("10.45.0.2", "10.46.0.2", 1, 2, b""), rules, 1) == 1
    assert classify(ipv4_udp("10.45.0.2", "10.46.0.2", 1, 2, b""), (), 9) == 9


def test_a_datagrams_later_fragments_follow_its_first_into_its_flow() -> None:
    from netem.gtpu.endpoint import Classifier, QosRule

    def fragment(packet: bytes, ident: int, offset_8: int, more: bool) -> bytes:
        flags = (0x2000 if more else 0) | offset_8
        return packet[:4] + struct.pack("!HH", ident, flags) + packet[8:]

    classify = Classifier((QosRule(qfi=2, ports=(7410,)),), default_qfi=1, max_datagrams=2)
    first = ipv4_udp("10.45.0.2", "10.46.0.2", 40000, 7410, bytes(64))
    # A later fragment holds no UDP header (its bytes here would read as ports 0 and 0).
    later = ipv4_udp("10.45.0.2", "10.46.0.2", 0, 0, bytes(64))
    assert classify(fragment(first, 7, 0, more=True)) == 2
    assert classify(fragment(later, 7, 185, more=True)) == 2
    assert classify(fragment(later, 8, 185, more=True)) == 1  # another datagram: unknown
    assert classify(fragment(later, 7, 370, more=False)) == 2  # the last: forgotten after
    assert classify(fragment(later, 7, 370, more=False)) == 1
    assert classify(first) == 2 and classify(later) == 1  # whole datagrams as `classify`
    # At most max_datagrams remembered: the oldest goes first.
    for ident in (10, 11, 12):
        classify(fragment(first, ident, 0, more=True))
    assert [classify(fragment(later, i, 185, more=True)) for i in (10, 11, 12)] == [1, 2, 2]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda g: g.QosRule(qfi=70, ports=(1,)), "QFI must be an integer 0-63, got 70"),
        (lambda g: g.QosRule(qfi=5), "matches nothing: give dscp or ports"),
        (lambda g: g.Session("10.45.0.2", 0, 1, "1.1.1.1", "1.1.1.2"), "ul_teid must be 1..2^32-1"),
        (lambda g: g.Session("pool", 1, 1, "1.1.1.1", "1.1.1.2"), "ue_address must be an IPv4"),
        (
            lambda g: g.EndpointConfig(
                "gnb",
                "ns",
                "gtp0",
                "10.0.0.9",
                (g.Session("10.45.0.2", 1, 2, "10.0.0.1", "10.0.0.2"),),
            ),
            "its gnb_address 10.0.0.1 is not this gnb's N3 address 10.0.0.9",
        ),
        (
            lambda g: g.EndpointConfig(
                "upf",
                "ns",
                "upf0",
                "10.0.0.2",
                (
                    g.Session("10.45.0.2", 1, 2, "10.0.0.1", "10.0.0.2"),
                    g.Session("10.45.0.3", 1, 3, "10.0.0.1", "10.0.0.2"),
                ),
            ),
            "two sessions share ul_teid 1",
        ),
    ],
)
def test_bad_endpoint_settings_are_refused_with_the_reason(make, message: str) -> None:  # type: ignore[no-untyped-def]
    from netem.gtpu import endpoint as gtp

    with pytest.raises(ValueError, match=re.escape(message)):
        make(gtp)


def test_endpoint_config_survives_its_json() -> None:
    from netem.gtpu.endpoint import EndpointConfig, QosRule, Session

    cfg = EndpointConfig(
        "upf", "ns", "upf0", "10.0.0.2", (Session("10.45.0.2", 1, 2, "10.0.0.1", "10.0.0.2"),),
        (QosRule(5, ports=(7400, 7401)), QosRule(7, dscp=46)), default_qfi=9,
    )  # fmt: skip
    assert EndpointConfig.from_json(cfg.to_json()) == cfg


def _ends() -> tuple[Endpoint, Endpoint]:
    session = Session("10.45.0.2", 0x1001, 0x2001, "10.100.3.1", "10.100.3.2")
    rules = (QosRule(5, ports=(7400,)),)
    gnb = EndpointConfig("gnb", "ns", "gtp0", "10.100.3.1", (session,), rules, default_qfi=9)
    upf = EndpointConfig("upf", "ns", "upf0", "10.100.3.2", (session,), rules, default_qfi=9)
    # No TUN or socket: these tests call the per-packet parts of the data plane directly.
    return Endpoint(gnb, -1, None), Endpoint(upf, -1, None)  # type: ignore[arg-type]


@pytest.mark.parametrize("size", [0, 1, 100, 1428])
def test_an_ends_g_pdu_is_encode_gpdus_for_its_session_and_flow(size: int) -> None:
    gnb, upf = _ends()
    up = ipv4_udp("10.45.0.2", "10.100.6.2", 40000, 7400, bytes(size))
    down = ipv4_udp("10.100.6.2", "10.45.0.2", 5000, 6000, bytes(size))
    assert gnb._encapsulate(up) == ("10.100.3.2", encode_gpdu(0x1001, up, 5, uplink=True))
    assert upf._encapsulate(down) == ("10.100.3.1", encode_gpdu(0x2001, down, 9, uplink=False))


def test_a_gro_receive_is_unwrapped_packet_by_packet_and_a_spoofed_one_dropped() -> None:
    _, upf = _ends()
    packets = [ipv4_udp("10.45.0.2", "10.100.6.2", 40000, 7400, bytes([i]) * 500) for i in range(5)]
    packets[2] = ipv4_udp("10.45.0.3", "10.100.6.2", 40000, 7400, bytes(500))  # not this UE's
    last = ipv4_udp("10.45.0.2", "10.100.6.2", 40000, 7400, b"end")
    datagrams = [encode_gpdu(0x1001, p, 5, uplink=True) for p in (*packets, last)]
    inner: list[bytes] = []
    upf._untunnel_run(b"".join(datagrams), len(datagrams[0]), ("10.100.3.1", 2152), inner)
    assert inner == [packets[0], packets[1], packets[3], packets[4], last]
    got = upf.counters.to_dict()
    assert got["received"]["packets"] == 5 and got["drops"] == {"spoofed_source": 1}
    assert got["received"]["inner_bytes"] == sum(map(len, inner))
    # A run whose first G-PDU is not of the tunnel's form goes one by one, and still unwraps.
    inner.clear()
    upf._untunnel_run(b"".join(datagrams[3:5]), len(datagrams[3]) - 1, ("x", 1), inner)
    assert upf.counters.drops["malformed"] >= 1
