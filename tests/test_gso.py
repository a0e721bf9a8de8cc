"""Super-packets and software GSO (`netem.gso`), checked with scapy as the independent parser.

Each test builds the kind of frame an offloading TUN hands the relay (a virtio-net header in
front of a TCP or UDP super-packet), splits it, and lets scapy recompute every IP, TCP and UDP
checksum and read every header field of the segments. The stage tests check that a pipeline
splits super-packets exactly where an effect is per wire packet, and counts wire packets.
"""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

scapy_all = pytest.importorskip("scapy.all", reason="scapy (in .[test]) parses the segments")
IP, IPv6, TCP, UDP, Raw = (
    scapy_all.IP,
    scapy_all.IPv6,
    scapy_all.TCP,
    scapy_all.UDP,
    scapy_all.Raw,
)

from netem.gso import (  # noqa: E402
    GSO_ECN,
    GSO_NONE,
    GSO_TCPV4,
    GSO_TCPV6,
    GSO_UDP_L4,
    VNET,
    VNET_F_NEEDS_CSUM,
    VNET_LEN,
    Frame,
    checksum,
    coalesce,
    ip_packets,
    rejoin,
    split,
)
from netem.profile import GilbertElliott, LinkProfile  # noqa: E402
from netem.relay.direction import build_pipeline  # noqa: E402
from netem.stages import Pipeline, Rate, Segment, wire_packets  # noqa: E402

PAYLOAD = bytes(range(256)) * 20 + b"tail"  # 5124 bytes: 3 full segments of 1448 and a rest


def super_packet(layer3, gso_type: int, gso_size: int = 1448, payload: bytes = PAYLOAD) -> Frame:
    """A frame as the kernel gives it: header fields of one packet, the whole payload behind.

    The checksum field carries only the pseudo-header sum (NEEDS_CSUM), as under TSO; the
    segments must come out with full checksums regardless.
    """
    packet = bytes(layer3 / Raw(payload))
    l4 = packet.index(payload) - (20 if TCP in layer3 else 8)
    header = VNET.pack(VNET_F_NEEDS_CSUM, gso_type, 0, gso_size, l4, 16 if TCP in layer3 else 6)
    return Frame(header + packet)


def tcp4(flags: str = "PA") -> Frame:
    return super_packet(
        IP(src="10.9.0.1", dst="10.9.0.2", id=1000, flags="DF")
        / TCP(sport=40000, dport=5201, seq=4_294_967_000, ack=7, flags=flags, window=512),
        GSO_TCPV4,
    )


def parse(frame: Frame):
    assert frame.data[:VNET_LEN] == VNET.pack(0, GSO_NONE, 0, 0, 0, 0)
    return (IPv6 if frame.data[VNET_LEN] >> 4 == 6 else IP)(frame.data[VNET_LEN:])


def assert_checksums_valid(packet) -> None:
    """scapy fills in the checksums it would send; they must equal the ones we wrote."""
    fresh = packet.__class__(bytes(packet))
    for layer in (IP, TCP, UDP):
        if layer in fresh:
            del fresh[layer].chksum
    rebuilt = packet.__class__(bytes(fresh))
    for layer in (IP, TCP, UDP):
        if layer in packet:
            assert packet[layer].chksum == rebuilt[layer].chksum, layer.__name__


def test_a_tcp_super_packet_weighs_what_its_segments_weigh_on_the_wire() -> None:
    frame = tcp4()
    assert frame.segments == 4
    assert len(frame) == frame.wire_len == len(PAYLOAD) + 4 * 40
    plain = Frame(VNET.pack(0, GSO_NONE, 0, 0, 0, 0) + bytes(IP() / UDP() / Raw(b"x" * 100)))
    assert (plain.segments, len(plain)) == (1, 128)


def test_tcp_segments_are_what_a_nic_would_send() -> None:
    frame = tcp4("FPA")
    parts = split(frame)
    assert len(parts) == frame.segments == 4
    assert sum(len(p) for p in parts) == len(frame)
    packets = [parse(p) for p in parts]
    for i, pkt in enumerate(packets):
        assert_checksums_valid(pkt)
        assert pkt[IP].len == len(parts[i])
        assert pkt[IP].id == 1000 + i
        assert pkt[IP].flags == "DF"
        assert pkt[TCP].seq == (4_294_967_000 + i * 1448) % 2**32  # wraps past 2^32
        assert pkt[TCP].ack == 7 and pkt[TCP].window == 512
    assert [str(p[TCP].flags) for p in packets] == ["A", "A", "A", "FPA"]
    assert b"".join(bytes(p[TCP].payload) for p in packets) == PAYLOAD
    assert [len(p[TCP].payload) for p in packets] == [1448, 1448, 1448, 780]


def test_cwr_is_kept_on_the_first_segment_only() -> None:
    packets = [parse(p) for p in split(tcp4("CA"))]
    assert [str(p[TCP].flags) for p in packets] == ["AC", "A", "A", "A"]


def test_tcp_over_ipv6_and_ecn_marked_gso() -> None:
    frame = super_packet(
        IPv6(src="fd00::1", dst="fd00::2") / TCP(sport=1, dport=2, seq=10, flags="PA"),
        GSO_TCPV6 | GSO_ECN,
        gso_size=1000,
    )
    assert frame.segments == 6 and len(frame) == len(PAYLOAD) + 6 * 60
    packets = [parse(p) for p in split(frame)]
    for i, pkt in enumerate(packets):
        assert_checksums_valid(pkt)
        assert pkt[IPv6].plen == len(pkt[TCP])
        assert pkt[TCP].seq == 10 + 1000 * i
    assert b"".join(bytes(p[TCP].payload) for p in packets) == PAYLOAD


def test_udp_gso_gives_datagrams_of_gso_size() -> None:
    frame = super_packet(
        IP(src="10.9.0.1", dst="10.9.0.2") / UDP(sport=5000, dport=6000), GSO_UDP_L4, 1200
    )
    packets = [parse(p) for p in split(frame)]
    assert len(packets) == 5 == frame.segments
    for pkt in packets:
        assert_checksums_valid(pkt)
        assert pkt[UDP].len == 8 + len(pkt[UDP].payload)
    assert [len(p[UDP].payload) for p in packets] == [1200] * 4 + [324]
    assert b"".join(bytes(p[UDP].payload) for p in packets) == PAYLOAD


def test_a_frame_of_one_segment_is_not_copied() -> None:
    frame = tcp4()
    small = super_packet(IP() / TCP(), GSO_TCPV4, gso_size=9000)
    assert small.segments == 1 and split(small) == [small]
    assert split(frame)[0] is not frame


def test_ip_packets_are_the_segments_without_the_virtio_header() -> None:
    frame = tcp4()
    packets = ip_packets(frame.data)
    assert packets == [f.data[VNET_LEN:] for f in split(frame)]
    for packet in packets:
        assert_checksums_valid(IP(packet))


def test_ip_packets_finish_a_checksum_the_kernel_left_partial() -> None:
    # One packet with NEEDS_CSUM, as TUN_F_CSUM hands a small TCP packet: the field holds the
    # pseudo-header's sum only. scapy must find a correct checksum once it is finished.
    packet = (
        IP(src="10.45.0.2", dst="10.100.6.2") / TCP(sport=1, dport=2, flags="PA") / Raw(b"x" * 101)
    )
    raw = bytearray(bytes(packet))
    pseudo = raw[12:20] + bytes([0, 6]) + (len(raw) - 20).to_bytes(2, "big")
    raw[36:38] = (0xFFFF - checksum(pseudo)).to_bytes(2, "big")
    header = VNET.pack(VNET_F_NEEDS_CSUM, GSO_NONE, 0, 0, 20, 16)
    [finished] = ip_packets(header + bytes(raw))
    assert finished != bytes(raw)
    assert_checksums_valid(IP(finished))
    assert IP(finished)[TCP].chksum == IP(bytes(packet))[TCP].chksum


def test_coalesced_segments_split_back_into_the_same_packets() -> None:
    frame = tcp4()
    segments = ip_packets(frame.data)
    [(merged, count)] = coalesce(segments)
    assert count == len(segments) == 4
    again = Frame(merged)
    assert again.segments == 4 and len(again) == len(frame)
    assert [f.data[VNET_LEN:] for f in split(again)] == segments
    flags, gso_type, hdr_len, gso_size, start, offset = VNET.unpack_from(merged)
    assert (flags, gso_type, hdr_len, gso_size, start, offset) == (
        VNET_F_NEEDS_CSUM, GSO_TCPV4, 40, 1448, 20, 16,
    )  # fmt: skip
    head = IP(merged[VNET_LEN:])
    assert head.len == 20 + 20 + len(PAYLOAD) and bytes(head[TCP].payload) == PAYLOAD
    assert head[TCP].flags == "PA"


def test_only_a_clean_run_of_one_flow_is_coalesced() -> None:
    segments = ip_packets(tcp4().data)
    other_flow = ip_packets(
        super_packet(
            IP(src="10.9.0.1", dst="10.9.0.3", flags="DF") / TCP(sport=1, dport=2, flags="A"),
            GSO_TCPV4,
        ).data
    )
    udp = bytes(IP(src="10.9.0.1", dst="10.9.0.2") / UDP(sport=5, dport=6) / Raw(b"u" * 30))
    syn = bytes(IP(src="10.9.0.1", dst="10.9.0.2") / TCP(flags="S"))
    counts = [n for _, n in coalesce([*segments[:2], udp, *segments[2:], syn, *other_flow])]
    assert counts == [2, 1, 2, 1, 4]
    # A gap in the sequence, or a short segment in the middle, ends a run.
    assert [n for _, n in coalesce([segments[0], segments[2], segments[3]])] == [1, 2]

    def seg(seq: int, size: int) -> bytes:
        return bytes(
            IP(src="10.9.0.1", dst="10.9.0.2", flags="DF")
            / TCP(sport=7, dport=8, seq=seq, ack=1, flags="A")
            / Raw(b"s" * size)
        )

    assert [n for _, n in coalesce([seg(0, 1448), seg(1448, 100), seg(1548, 1448)])] == [2, 1]
    # Every packet that passes alone passes as it came, behind a plain header.
    alone = coalesce([udp, syn])
    assert alone == [(VNET.pack(0, GSO_NONE, 0, 0, 0, 0) + udp, 1),
                     (VNET.pack(0, GSO_NONE, 0, 0, 0, 0) + syn, 1)]  # fmt: skip


def test_a_batch_of_split_packets_is_rejoined_and_other_frames_pass_as_they_are() -> None:
    whole = tcp4()
    segments = split(whole)
    partial = tcp4("A")  # a super-packet moved whole: written as the kernel gave it
    small = bytes(IP(src="10.9.0.1", dst="10.9.0.2") / TCP(flags="A") / Raw(b"x" * 10))
    # One packet whose checksum the kernel left partial: its header must stay as it is.
    left = Frame(VNET.pack(VNET_F_NEEDS_CSUM, GSO_NONE, 0, 0, 20, 16) + small)
    batch = [*segments[:3], partial, left, segments[3]]
    out = rejoin(batch)
    assert [n for _, n in out] == [3, 1, 1, 1]
    assert sum(n for _, n in out) == len(batch)
    assert out[1][0] is partial.data and out[2][0] is left.data
    # The three rejoined segments split back into the very packets of the batch.
    assert ip_packets(out[0][0]) == [f.data[VNET_LEN:] for f in segments[:3]]
    assert out[3][0] == segments[3].data  # alone: as it came, behind the plain header
    assert rejoin(segments) == coalesce([f.data[VNET_LEN:] for f in segments])
    assert len(rejoin(segments)) == 1 and rejoin([]) == []


@given(st.binary(min_size=0, max_size=300))
def test_checksum_is_rfc_1071(data: bytes) -> None:
    # The textbook loop: 16-bit big-endian words, end-around carry, complement.
    padded = data + b"\0" * (len(data) % 2)
    total = 0
    for i in range(0, len(padded), 2):
        total += padded[i] << 8 | padded[i + 1]
        total = (total & 0xFFFF) + (total >> 16)
    want = ~total & 0xFFFF
    got = checksum(data)
    # 0 and 0xFFFF are the same number in one's complement; we always give 0xFFFF.
    assert got == (want or 0xFFFF)
    split_at = (len(data) // 2) & ~1
    assert checksum(data[:split_at], data[split_at:]) == got


# -- the pipeline with super-packets ----------------------------------------------------------


def run(pipeline: Pipeline, frames: list, until: float = 10.0) -> list:
    for f in frames:
        pipeline.push(f, 0.0)
    out = []
    while (due := pipeline.next_due()) is not None and due <= until:
        out += pipeline.pop_ready(due)
    return out


def test_a_plain_link_moves_super_packets_whole_and_counts_wire_packets() -> None:
    pipeline = build_pipeline(LinkProfile(delay_s=0.005))
    out = run(pipeline, [tcp4(), tcp4()])
    assert [type(p) for p in out] == [Frame, Frame] and all(p.segments == 4 for p in out)
    total = pipeline.snapshot()["total"]
    assert total["packets_in"] == total["packets_out"] == 8
    assert total["bytes_out"] == 2 * len(tcp4())


def test_a_slow_link_gets_wire_packets() -> None:
    # 5.3 kB take 42 ms at 1 Mbit/s: moved whole, the first segment would wait for the last.
    out = run(build_pipeline(LinkProfile(rate_bps=1e6)), [tcp4() for _ in range(5)])
    assert len(out) == 20 and all(type(p) is Frame and p.segments == 1 for p in out)


@pytest.mark.parametrize(
    "profile",
    [LinkProfile(loss=0.05), LinkProfile(gilbert_elliott=GilbertElliott(p=0.05, r=0.8))],
    ids=["random", "gilbert-elliott"],
)
def test_a_lossy_link_splits_only_the_super_packets_that_lose_packets(
    profile: LinkProfile,
) -> None:
    pipeline = build_pipeline(profile, seed=2)
    out = run(pipeline, [tcp4() for _ in range(2000)])
    whole = [p for p in out if p.segments == 4]
    lost = pipeline.snapshot()["total"]["dropped_packets"]["loss"]
    assert sum(p.segments for p in out) + lost == 8000
    assert all(p.segments in (1, 4) for p in out)
    # A frame passes whole exactly when none of its 4 packets is lost.
    share = len(whole) / 2000
    if profile.gilbert_elliott is None:
        assert share == pytest.approx(0.95**4, abs=0.03)
    assert 0 < len(out) - len(whole) < 4 * (2000 - len(whole))


def test_a_fast_rate_keeps_super_packets_whole() -> None:
    out = run(build_pipeline(LinkProfile(rate_bps=1e9)), [tcp4()])
    assert len(out) == 1 and out[0].segments == 4


def test_a_trace_gets_wire_packets_and_gives_them_back_when_it_stops() -> None:
    from netem.traces import Trace

    pipeline = build_pipeline(LinkProfile())
    segment = pipeline.stage("segment")
    assert isinstance(segment, Segment)
    trace = Trace(format="csv", duration_s=1.0, steps=((0.0, 12e6),))
    pipeline.play_trace(trace, now=0.0)
    assert segment.splits(tcp4())
    pipeline.play_trace(None, now=0.5)
    assert not segment.splits(tcp4())


def test_loss_is_drawn_per_wire_packet() -> None:
    pipeline = build_pipeline(LinkProfile(loss=0.25), seed=3)
    out = run(pipeline, [tcp4() for _ in range(500)])
    lost = pipeline.snapshot()["total"]["dropped_packets"]["loss"]
    assert lost + sum(p.segments for p in out) == 2000
    assert 0.22 < lost / 2000 < 0.28  # per packet; whole frames would lose in steps of 4


def test_the_rate_queue_limit_counts_wire_packets_and_admits_a_partial_frame() -> None:
    rate = Rate(rate_bps=1e6, queue_packets=10)
    rate.push(tcp4(), 0.0)
    rate.push(tcp4(), 0.0)  # 8 wire packets queued
    rate.push(tcp4(), 0.0)  # room for 2 of its 4
    assert sum(wire_packets(p) for p in rate._queue) == 10
    drops = rate.counters.dropped_packets
    assert drops == {"queue_full": 2}
    assert rate.counters.packets_in == 12
