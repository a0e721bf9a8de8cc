"""Offloaded packets of a TUN end: the virtio-net header, super-packets and their segments.

With `IFF_VNET_HDR` and the TSO/USO offloads a TUN device behaves like a virtual NIC: the
kernel hands the relay TCP (and UDP-GSO) *super-packets* of up to 64 kB, each behind a 10-byte
`struct virtio_net_hdr`, and takes them back whole on the far end, where the receiving stack
treats them like GRO'd packets. The relay then moves one object per ~44 wire packets, which
is what lets a Python relay carry Gbit/s at MTU 1500.

Nouns:
- `Frame`: one read from an offloading TUN. `data` is written back unchanged (header
  included); `wire_len` is what the frame would weigh on a wire without offloads (the bytes of
  all its IP packets, headers repeated per segment) and `segments` how many IP packets that
  is. `len(frame)` is `wire_len`, so every stage that charges bytes (rate, trace
  opportunities, counters) is exact without knowing about offloads.
- `rejoin(frames)`: software GRO of a batch leaving together: `split`'s wire packets back
  into super-packets where they run in sequence (one write, one pass of the stack behind).
- `split(frame)`: software GSO, the IP packets a NIC would have put on the wire, each with
  complete IP and TCP/UDP checksums (so the receiving kernel verifies them). Stages whose
  effect is per wire packet (loss, a trace's delivery opportunities, a slow link's
  serialisation) get segments; every other stage moves the super-packet whole.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence

#: struct virtio_net_hdr: flags, gso_type, hdr_len, gso_size, csum_start, csum_offset. The
#: TUN uses the host's byte order unless told otherwise (TUNSETVNETLE/BE).
VNET = struct.Struct("=BBHHHH")
VNET_LEN = VNET.size
VNET_F_NEEDS_CSUM = 1
GSO_NONE, GSO_TCPV4, GSO_TCPV6, GSO_UDP_L4 = 0, 1, 4, 5
GSO_ECN = 0x80
PROTO_TCP, PROTO_UDP = 6, 17
_PLAIN_HEADER = VNET.pack(0, GSO_NONE, 0, 0, 0, 0)
_FIN_PSH, _CWR = 0x09, 0x80
_ONES = 0xFFFF
_ACK = 0x10
_GRO_FLAGS = (_ACK, _ACK | 0x08)  # ACK, and ACK+PSH to end a run
MAX_IP_LEN = 0xFFFF


class Frame:
    """One packet as an offloading TUN gives it: `data` (virtio-net header + IP packet)."""

    __slots__ = ("data", "segments", "wire_len")

    def __init__(self, data: bytes, segments: int = 0, wire_len: int = 0) -> None:
        self.data = data
        if segments:  # a segment made by `split`: already known
            self.segments, self.wire_len = segments, wire_len
            return
        _, gso_type, _, gso_size, _, _ = VNET.unpack_from(data)
        if gso_type & ~GSO_ECN == GSO_NONE or not gso_size:
            self.segments, self.wire_len = 1, len(data) - VNET_LEN
            return
        headers = _header_len(data)
        payload = len(data) - VNET_LEN - headers if headers else 0
        if payload <= 0:
            self.segments, self.wire_len = 1, len(data) - VNET_LEN
            return
        self.segments = -(-payload // gso_size)
        self.wire_len = payload + self.segments * headers

    def __len__(self) -> int:
        return self.wire_len

    def __repr__(self) -> str:
        return f"Frame({self.wire_len} B on the wire in {self.segments} packet(s))"


def _header_len(data: bytes) -> int:
    """IP + TCP/UDP header bytes of the packet behind the virtio-net header (0: unknown)."""
    ip = VNET_LEN
    version = data[ip] >> 4
    if version == 4:
        l4, proto = ip + (data[ip] & 0x0F) * 4, data[ip + 9]
    elif version == 6:
        l4, proto = ip + 40, data[ip + 6]  # the kernel segments no extension headers for us
    else:
        return 0
    if proto == PROTO_TCP:
        return l4 - ip + (data[l4 + 12] >> 4) * 4
    if proto == PROTO_UDP:
        return l4 - ip + 8
    return 0


def checksum(*parts: bytes) -> int:
    """The Internet checksum (RFC 1071) over the concatenation of `parts`.

    Each part but the last must have an even length. The one's-complement sum of 16-bit
    words is the big-endian value of the bytes modulo 0xFFFF (2^16 ≡ 1), which CPython
    computes in C; 0 comes back as 0xFFFF, the form UDP needs and IP and TCP accept.
    """
    total = 0
    for part in parts:
        if len(part) & 1:
            part = bytes(part) + b"\0"
        total += int.from_bytes(part, "big") % _ONES
    return _ONES - total % _ONES


def split(frame: Frame) -> list[Frame]:
    """The wire packets of a super-packet (itself alone if it is one already)."""
    if frame.segments <= 1:
        return [frame]
    return [Frame(p, 1, len(p) - VNET_LEN) for p in _segments(frame.data, _PLAIN_HEADER)]


def ip_packets(data: bytes) -> list[bytes]:
    """The IP packets, complete, that one read from an offloading TUN holds: a super-packet's
    segments (software GSO), a packet whose checksum the kernel left to us (NEEDS_CSUM)
    finished, any other packet as it is. For an end that must hand on real packets with
    valid checksums (a GTP-U tunnel end), not the virtio-net header's promise of them."""
    flags, gso_type, _, gso_size, csum_start, csum_offset = VNET.unpack_from(data)
    if gso_type & ~GSO_ECN != GSO_NONE and gso_size:
        return list(_segments(data, b""))
    if flags & VNET_F_NEEDS_CSUM:
        packet = bytearray(data[VNET_LEN:])
        # The field holds the pseudo-header's sum: summing over it finishes the checksum.
        at = csum_start + csum_offset
        if at + 2 <= len(packet):
            struct.pack_into("!H", packet, at, checksum(packet[csum_start:]))
        return [bytes(packet)]
    return [data[VNET_LEN:]]


def _segments(data: bytes, prefix: bytes) -> Iterator[bytes]:
    """Software GSO of the super-packet `data` (virtio-net header first): each wire packet
    with complete checksums, `prefix` in front of it."""
    gso_size = VNET.unpack_from(data)[3]
    ip = VNET_LEN
    version = data[ip] >> 4
    if version == 4:
        l4 = ip + (data[ip] & 0x0F) * 4
        proto = data[ip + 9]
        addresses = data[ip + 12 : ip + 20]
        ident = int.from_bytes(data[ip + 4 : ip + 6], "big")
    else:
        l4 = ip + 40
        proto = data[ip + 6]
        addresses = data[ip + 8 : ip + 40]
        ident = 0
    tcp = proto == PROTO_TCP
    end = l4 + ((data[l4 + 12] >> 4) * 4 if tcp else 8)
    ip_header = bytearray(data[ip:l4])
    l4_header = bytearray(data[l4:end])
    seq = int.from_bytes(l4_header[4:8], "big") if tcp else 0
    flags = l4_header[13] if tcp else 0
    view = memoryview(data)
    n_bytes = len(data) - end
    for i, offset in enumerate(range(0, n_bytes, gso_size)):
        chunk = view[end + offset : end + min(offset + gso_size, n_bytes)]
        l4_len = len(l4_header) + len(chunk)
        if version == 4:
            struct.pack_into("!H", ip_header, 2, len(ip_header) + l4_len)
            struct.pack_into("!H", ip_header, 4, (ident + i) & 0xFFFF)
            struct.pack_into("!H", ip_header, 10, 0)
            struct.pack_into("!H", ip_header, 10, checksum(ip_header))
            pseudo = addresses + struct.pack("!BBH", 0, proto, l4_len)
        else:
            struct.pack_into("!H", ip_header, 4, l4_len)
            pseudo = addresses + struct.pack("!I3xB", l4_len, proto)
        if tcp:
            struct.pack_into("!I", l4_header, 4, (seq + offset) & 0xFFFFFFFF)
            f = flags
            if offset + gso_size < n_bytes:
                f &= ~_FIN_PSH
            if i:
                f &= ~_CWR
            l4_header[13] = f
            struct.pack_into("!H", l4_header, 16, 0)
            struct.pack_into("!H", l4_header, 16, checksum(pseudo, l4_header, chunk))
        else:
            struct.pack_into("!HH", l4_header, 4, l4_len, 0)
            struct.pack_into("!H", l4_header, 6, checksum(pseudo, l4_header, chunk))
        yield b"".join((prefix, ip_header, l4_header, chunk))


def coalesce(packets: Sequence[bytes]) -> list[tuple[bytes, int]]:
    """Software GRO: `packets` (complete IP packets, in arrival order) as frames for an
    offloading TUN, each with how many packets it holds.

    A run of IPv4 TCP segments of one flow, back to back in sequence, with the same headers
    but for sequence, length, IP ID and checksums, each but the last of the first one's
    payload size, and no flag but ACK (PSH allowed on the last), becomes one super-packet
    (`GSO_TCPV4`, the first one's payload as `gso_size`, the checksum left to the kernel as
    TSO leaves it). The receiving stack then handles one packet where it would have handled
    ~44, as after a NIC's GRO; split again (by the kernel or `split`), it gives back the very
    packets it was made of. Anything else passes alone, as it came."""
    out: list[tuple[bytes, int]] = []
    i, n = 0, len(packets)
    while i < n:
        first = packets[i]
        j = i + 1
        run = _gro_head(first)
        if run is not None:
            ihl, end, size = run
            total = len(first)
            seq = (int.from_bytes(first[ihl + 4 : ihl + 8], "big") + size) & 0xFFFFFFFF
            last_flags = first[ihl + 13]
            # What every packet of the run shares with the first: version, TOS; flags, TTL,
            # protocol; addresses and ports; ACK and data offset; window; urgent pointer and
            # options (IP ID, lengths, sequence, TCP flags and checksums may differ).
            same = (first[:2], first[6:10], first[12 : ihl + 4], first[ihl + 8 : ihl + 13],
                    first[ihl + 14 : ihl + 16], first[ihl + 18 : end])  # fmt: skip
            while j < n and last_flags == _ACK:
                nxt = packets[j]
                more = len(nxt) - end
                if (
                    more <= 0
                    or more > size
                    or total + more > MAX_IP_LEN
                    or nxt[ihl + 13] not in _GRO_FLAGS
                    or int.from_bytes(nxt[ihl + 4 : ihl + 8], "big") != seq
                    or int.from_bytes(nxt[2:4], "big") != len(nxt)
                    or (
                        nxt[:2],
                        nxt[6:10],
                        nxt[12 : ihl + 4],
                        nxt[ihl + 8 : ihl + 13],
                        nxt[ihl + 14 : ihl + 16],
                        nxt[ihl + 18 : end],
                    )
                    != same
                ):
                    break
                total += more
                seq = (seq + more) & 0xFFFFFFFF
                last_flags = nxt[ihl + 13]
                j += 1
                if more < size:
                    break
        if j - i == 1:
            out.append((_PLAIN_HEADER + first, 1))
        else:
            out.append((_merge(packets[i:j], total, last_flags), j - i))
        i = j
    return out


def rejoin(frames: Sequence[Frame]) -> list[tuple[bytes, int]]:
    """What to write for `frames`, a batch that leaves a link at one instant, in order: each
    run of wire packets that `split` made (plain header, complete checksums) coalesced as
    `coalesce` does, every other frame (a super-packet moved whole, a packet whose checksum
    the kernel left partial) as it is; each with how many frames of the batch it holds.

    A stage that needs wire packets (a radio's slots, a slow link) hands out a slot's or a
    burst's worth at once: written one by one, each costs a system call and a pass through
    the receiving stack; rejoined, the stack behind gets them as a NIC's GRO would."""
    out: list[tuple[bytes, int]] = []
    run: list[bytes] = []
    for frame in frames:
        data = frame.data
        if frame.segments == 1 and data[:VNET_LEN] == _PLAIN_HEADER:
            run.append(data[VNET_LEN:])
            continue
        if run:
            out.extend(coalesce(run))
            run = []
        out.append((data, 1))
    if run:
        out.extend(coalesce(run))
    return out


def _gro_head(packet: bytes) -> tuple[int, int, int] | None:
    """(IP header length, header end, payload size) if `packet` may start a GRO run."""
    if len(packet) < 40 or packet[0] >> 4 != 4 or packet[9] != PROTO_TCP:
        return None
    ihl = (packet[0] & 0x0F) * 4
    if packet[6] & 0x3F or packet[7]:  # a fragment
        return None
    if len(packet) < ihl + 20 or packet[ihl + 13] != _ACK:
        return None
    end = ihl + (packet[ihl + 12] >> 4) * 4
    size = len(packet) - end
    if size <= 0 or int.from_bytes(packet[2:4], "big") != len(packet):
        return None
    return ihl, end, size


def _merge(run: Sequence[bytes], total: int, flags: int) -> bytes:
    first = run[0]
    ihl = (first[0] & 0x0F) * 4
    end = ihl + (first[ihl + 12] >> 4) * 4
    ip_header = bytearray(first[:ihl])
    struct.pack_into("!H", ip_header, 2, total)
    struct.pack_into("!H", ip_header, 10, 0)
    struct.pack_into("!H", ip_header, 10, checksum(ip_header))
    tcp_header = bytearray(first[ihl:end])
    tcp_header[13] = flags
    # As TSO leaves it: the pseudo-header's sum, not complemented, for the kernel to finish.
    pseudo = first[12:20] + struct.pack("!BBH", 0, PROTO_TCP, total - ihl)
    struct.pack_into("!H", tcp_header, 16, _ONES - checksum(pseudo))
    header = VNET.pack(VNET_F_NEEDS_CSUM, GSO_TCPV4, end, len(first) - end, ihl, 16)
    return b"".join((header, ip_header, tcp_header, *(p[end:] for p in run)))
