"""GTP-U tunnel endpoints in user space: the gNB's and the UPF's end of N3.

The kernel here has no GTP module, so each end is a process, as in UERANSIM and the Open5GS
UPF: a TUN device that the namespace's routes send the UE traffic into, and a UDP socket on
the node's N3 address, port 2152.

- `Session`: one UE's PDU session, the pair of tunnels that carry it: its address in the UE
  pool, the uplink TEID (allocated by the UPF, used by the gNB) and the downlink TEID
  (allocated by the gNB, used by the UPF), and the two N3 addresses.
- `QosRule`: which QoS flow (QFI) a packet belongs to, by DSCP or by port; the first rule that
  matches wins, else the default QFI.
- `EndpointConfig`: one end: its role (`gnb` or `upf`), namespace, TUN device, N3 address,
  sessions and rules.
- `Endpoint`: the data plane of one end. The gNB reads uplink packets from its TUN (the routes
  send there what arrives from the air), finds the session by the packet's source and sends
  a G-PDU (PDU type UL) to the UPF; a G-PDU from the UPF (PDU type DL) goes into the TUN, and
  the routes take it to the UE. The UPF mirrors it: a downlink packet from its TUN (routes for
  the UE pool point there) is found by destination and sent to that session's gNB; an uplink
  G-PDU is checked (known TEID, inner source = the session's UE) and goes into the TUN, and
  the routes take it over N6. Echo Requests are answered. Outer packets are sent with the
  don't-fragment bit (IP_PMTUDISC_DO): a packet that would need fragmenting on N3 is dropped
  and counted, never fragmented.
- `GtpEndpoint`: the process (`python -m netem.gtpu.endpoint CONFIG.json`), started and stopped
  by a context manager; it writes its counters to a JSON file twice a second and on exit.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import errno
import functools
import ipaddress
import json
import os
import selectors
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from netem.errors import NetemError
from netem.gso import VNET_LEN, coalesce, ip_packets
from netem.gtpu.wire import (
    ECHO_REQUEST,
    ECHO_RESPONSE,
    G_PDU,
    GTPU_PORT,
    GtpError,
    check_qfi,
    decode,
    echo_request,
    echo_response,
    encode_gpdu,
)
from netem.netns import in_netns
from netem.proc import die_with_parent, remove_dir, renice, spawn, stop, wait_ready
from netem.tun import TunConfig, open_tun

Role = Literal["gnb", "upf"]
#: Outer IPv4 + UDP bytes of each datagram on N3 (the GTP-U header is GPDU_HEADER_LEN more).
OUTER_IP_UDP = 28
IP_MTU_DISCOVER, IP_PMTUDISC_DO = 10, 2
STATS_INTERVAL_S = 0.5
_BATCH = 64  # packets read from one fd before the other gets its turn
SOL_UDP, UDP_SEGMENT, UDP_GRO = 17, 103, 104  # linux/udp.h
#: UDP GSO sends at most 64 segments in one call; 44 of 1472 bytes stay under 64 kB.
GSO_MAX_SEGMENTS = 44
_GRO_CMSG_SPACE = socket.CMSG_SPACE(4)
#: The first two bytes of a G-PDU as these ends send it (version 1, PT, E; type 255), and
#: its bytes 11-12: one PDU Session Container (0x85) of one 4-byte unit.
_GPDU_FLAGS_TYPE, _ONE_CONTAINER = bytes((0x34, G_PDU)), bytes((0x85, 1))


class GtpEndpointError(NetemError, RuntimeError):
    """A GTP-U endpoint could not start, or died; the message says which and why."""


@dataclass(frozen=True)
class Session:
    """One UE's PDU session on N3 (see the module doc)."""

    ue_address: str
    ul_teid: int
    dl_teid: int
    gnb_address: str
    upf_address: str

    @functools.cached_property
    def ue_packed(self) -> bytes:
        """The UE's address as the 4 bytes of an IPv4 header (read per uplink packet)."""
        return ipaddress.IPv4Address(self.ue_address).packed

    def __post_init__(self) -> None:
        for name in ("ue_address", "gnb_address", "upf_address"):
            try:
                ipaddress.IPv4Address(getattr(self, name))
            except ValueError:
                raise ValueError(
                    f"session {name} must be an IPv4 address, got {getattr(self, name)!r}"
                ) from None
        for name in ("ul_teid", "dl_teid"):
            teid = getattr(self, name)
            if not isinstance(teid, int) or not 1 <= teid <= 0xFFFFFFFF:
                # TEID 0 is reserved for signalling (echo, error indication).
                raise ValueError(f"session {name} must be 1..2^32-1, got {teid!r}")


@dataclass(frozen=True)
class QosRule:
    """Packets with this DSCP, or to or from one of these ports (TCP/UDP), are in flow `qfi`."""

    qfi: int
    dscp: int | None = None
    ports: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        try:
            check_qfi(self.qfi)
        except GtpError as exc:
            raise ValueError(str(exc)) from None
        if self.dscp is not None and not 0 <= self.dscp <= 63:
            raise ValueError(f"DSCP must be 0-63, got {self.dscp!r}")
        if any(not 0 < p < 65536 for p in self.ports):
            raise ValueError(f"ports must be 1-65535, got {list(self.ports)}")
        if self.dscp is None and not self.ports:
            raise ValueError(f"QoS rule for QFI {self.qfi} matches nothing: give dscp or ports")
        # Looked up per packet: a set, as a rule for DDS lists a port per participant.
        object.__setattr__(self, "_port_set", frozenset(self.ports))

    def matches(self, dscp: int, sport: int | None, dport: int | None) -> bool:
        if self.dscp is not None and dscp != self.dscp:
            return False
        ports: frozenset[int] = self._port_set  # type: ignore[attr-defined]
        return not ports or sport in ports or dport in ports


def classify(packet: bytes, rules: tuple[QosRule, ...], default_qfi: int) -> int:
    """The QFI of an IPv4 packet: the first rule it matches, else `default_qfi`."""
    if not rules or len(packet) < 20:
        return default_qfi
    dscp = packet[1] >> 2
    ihl = (packet[0] & 0x0F) * 4
    sport = dport = None
    # Ports only in the first fragment of TCP (6) or UDP (17).
    first_fragment = not struct.unpack_from("!H", packet, 6)[0] & 0x1FFF
    if packet[9] in (6, 17) and first_fragment and len(packet) >= ihl + 4:
        sport, dport = struct.unpack_from("!HH", packet, ihl)
    for rule in rules:
        if rule.matches(dscp, sport, dport):
            return rule.qfi
    return default_qfi


class Classifier:
    """`classify` over a stream of packets, IP fragments included: a datagram's later
    fragments carry no ports, so each gets the flow its first fragment got (kept by source,
    destination, IP ID and protocol, as a reassembler keys them, until the last fragment; at
    most `max_datagrams` at once, the oldest forgotten first). Without this, a DDS message
    larger than the UE's MTU would cross N3 partly in its own flow and partly in the default
    one."""

    def __init__(
        self, rules: tuple[QosRule, ...], default_qfi: int, max_datagrams: int = 1024
    ) -> None:
        self.rules, self.default_qfi, self.max_datagrams = rules, default_qfi, max_datagrams
        self._first: dict[bytes, int] = {}  # datagram key -> the QFI of its first fragment

    def __call__(self, packet: bytes) -> int:
        if not self.rules or len(packet) < 20:
            return self.default_qfi
        frag = struct.unpack_from("!H", packet, 6)[0]
        offset, more = frag & 0x1FFF, frag & 0x2000
        if not offset and not more:  # not a fragment: the common case
            return classify(packet, self.rules, self.default_qfi)
        key = packet[12:20] + packet[4:6] + packet[9:10]
        if not offset:
            qfi = classify(packet, self.rules, self.default_qfi)
            self._first[key] = qfi
            if len(self._first) > self.max_datagrams:
                del self._first[next(iter(self._first))]
            return qfi
        if more:
            return self._first.get(key, self.default_qfi)
        return self._first.pop(key, self.default_qfi)


@dataclass(frozen=True)
class EndpointConfig:
    """One N3 end (see the module doc). `tun_mtu` is the largest UE packet it carries: 1456
    on a 1500-byte N3. `stats_path` is where the process writes its counters."""

    role: Role
    netns: str
    tun: str
    address: str  # this node's N3 address
    sessions: tuple[Session, ...]
    rules: tuple[QosRule, ...] = ()
    default_qfi: int = 1
    tun_mtu: int = 1456
    stats_path: str | None = None
    #: The TUN with TSO/USO offloads (`netem.tun`): super-packets in, segmented here into the
    #: UE's packets before they are tunnelled; coalesced (GRO) on the way out. False: one
    #: packet per read and write (what the bench compares against).
    offload: bool = True

    def __post_init__(self) -> None:
        if self.role not in ("gnb", "upf"):
            raise ValueError(f"GTP-U endpoint role must be gnb or upf, got {self.role!r}")
        check_qfi(self.default_qfi)
        own = "gnb_address" if self.role == "gnb" else "upf_address"
        for s in self.sessions:
            if getattr(s, own) != self.address:
                raise ValueError(
                    f"session of UE {s.ue_address}: its {own} {getattr(s, own)} is not this "
                    f"{self.role}'s N3 address {self.address}"
                )
        for attr in ("ue_address", "ul_teid", "dl_teid"):
            seen = Counter(getattr(s, attr) for s in self.sessions)
            dup = sorted(str(k) for k, n in seen.items() if n > 1)
            if dup:
                raise ValueError(f"two sessions share {attr} {', '.join(dup)}")

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> EndpointConfig:
        d = json.loads(text)
        d["sessions"] = tuple(Session(**s) for s in d["sessions"])
        d["rules"] = tuple(
            QosRule(r["qfi"], r.get("dscp"), tuple(r.get("ports", ()))) for r in d["rules"]
        )
        return cls(**d)


@dataclass
class Counters:
    """What one end moved: per direction packets and bytes (inner and on N3), per QFI, drops."""

    sent: Counter[str] = field(default_factory=Counter)  # into N3: packets, inner, n3 bytes
    received: Counter[str] = field(default_factory=Counter)  # from N3
    qfi_sent: Counter[int] = field(default_factory=Counter)
    drops: Counter[str] = field(default_factory=Counter)
    echo: Counter[str] = field(default_factory=Counter)

    def to_dict(self) -> dict[str, Any]:
        n3 = self.sent["n3_bytes"] + self.received["n3_bytes"]
        inner = self.sent["inner_bytes"] + self.received["inner_bytes"]
        return {
            "sent": dict(self.sent),
            "received": dict(self.received),
            "qfi_sent": {str(k): v for k, v in sorted(self.qfi_sent.items())},
            "drops": dict(self.drops),
            "echo": dict(self.echo),
            # GTP-U + outer IP/UDP bytes, and their share of everything this end put on or
            # took off N3.
            "overhead_bytes": n3 - inner,
            "overhead_share": (n3 - inner) / n3 if n3 else None,
        }


class Endpoint:
    """The data plane of one N3 end over an open TUN fd and UDP socket (see the module doc)."""

    def __init__(self, config: EndpointConfig, tun_fd: int, sock: socket.socket) -> None:
        self.cfg, self.tun, self.sock = config, tun_fd, sock
        self.uplink_sender = config.role == "gnb"
        self._by_ue = {s.ue_packed: s for s in config.sessions}
        # The TEID this end receives on: the gNB is addressed with DL TEIDs, the UPF with UL.
        # Keyed by the TEID's 4 bytes as they stand in a G-PDU (no int per packet).
        self._by_teid = {
            (s.dl_teid if self.uplink_sender else s.ul_teid).to_bytes(4, "big"): s
            for s in config.sessions
        }
        self._spoof_check = config.role == "upf"
        # (session, QFI) -> (peer, the G-PDU header for an empty packet): per packet only
        # the length field changes (`_encapsulate`).
        self._heads: dict[tuple[Session, int], tuple[str, bytes]] = {}
        self.counters = Counters()
        self._classify = Classifier(config.rules, config.default_qfi)
        self._seq = 0
        self._gso = True  # until the kernel refuses UDP_SEGMENT
        self._read_size = VNET_LEN + 65535 if config.offload else 65535

    # ---- TUN -> N3 -------------------------------------------------------------------------

    def from_tun(self) -> int:
        """Tunnel what the TUN holds (up to a batch); returns how many packets were read.

        With offloads one read may be a TCP super-packet: it is cut into the UE's packets
        (`netem.gso.ip_packets`, complete checksums), each its own G-PDU, as a real gNB gets
        them from the air. Datagrams to one peer leave in runs of equal size through UDP GSO
        (one sendmsg for up to `GSO_MAX_SEGMENTS`), as a bulk TCP flow gives them: the kernel
        still puts one datagram per UE packet on N3, only the system calls are fewer."""
        n = 0
        run: list[bytes] = []
        run_peer, run_size = "", 0
        offload = self.cfg.offload
        while n < _BATCH:
            try:
                data = os.read(self.tun, self._read_size)
            except BlockingIOError:
                break
            n += 1
            for packet in ip_packets(data) if offload else (data,):
                out = self._encapsulate(packet)
                if out is None:
                    continue
                peer, datagram = out
                if run and (
                    peer != run_peer or len(datagram) > run_size or len(run) >= GSO_MAX_SEGMENTS
                ):
                    self._send_run(run, run_peer, run_size)
                    run = []
                if not run:
                    run_peer, run_size = peer, len(datagram)
                run.append(datagram)
                if len(datagram) < run_size:  # a shorter one may only end a GSO run
                    self._send_run(run, run_peer, run_size)
                    run = []
            if n == 1 and run:
                # What the first read gave leaves before the next read is tried: a lone
                # packet (a ping, a DDS heartbeat) does not wait for the read that finds
                # the TUN empty; a burst goes on in GSO runs.
                self._send_run(run, run_peer, run_size)
                run = []
        if run:
            self._send_run(run, run_peer, run_size)
        return n

    def _encapsulate(self, packet: bytes) -> tuple[str, bytes] | None:
        c = self.counters
        if len(packet) < 20 or packet[0] >> 4 != 4:
            c.drops["not_ipv4"] += 1
            return None
        # The gNB knows the UE by the source of its uplink, the UPF by the destination.
        session = self._by_ue.get(packet[12:16] if self.uplink_sender else packet[16:20])
        if session is None:
            c.drops["no_session"] += 1
            return None
        qfi = self._classify(packet)
        cached = self._heads.get((session, qfi))
        if cached is None:
            cached = self._heads[session, qfi] = self._head(session, qfi)
        peer, head = cached
        c.qfi_sent[qfi] += 1
        c.sent["inner_bytes"] += len(packet)
        if len(packet) > 0xFFFF - 8:
            c.drops["too_big_for_n3"] += 1
            return None
        return peer, b"".join((head[:2], (8 + len(packet)).to_bytes(2, "big"), head[4:], packet))

    def _head(self, session: Session, qfi: int) -> tuple[str, bytes]:
        if self.uplink_sender:
            teid, peer = session.ul_teid, session.upf_address
        else:
            teid, peer = session.dl_teid, session.gnb_address
        # Sequence numbers are not signalled (S flag off): 0, so equal-sized G-PDUs of one
        # run differ only in their inner packet.
        return peer, encode_gpdu(teid, b"", qfi, uplink=self.uplink_sender)

    def _send_run(self, run: list[bytes], peer: str, size: int) -> None:
        c = self.counters
        sent = 0
        try:
            if len(run) == 1 or not self._gso:
                for datagram in run:
                    self.sock.sendto(datagram, (peer, GTPU_PORT))
                    sent += 1
            else:
                segment = struct.pack("=H", size)
                self.sock.sendmsg([b"".join(run)], [(SOL_UDP, UDP_SEGMENT, segment)], 0,
                                  (peer, GTPU_PORT))  # fmt: skip
                sent = len(run)
        except OSError as exc:
            if (
                exc.errno in (errno.EINVAL, errno.EIO, errno.ENOPROTOOPT)
                and self._gso
                and sent == 0
            ):
                self._gso = False  # no UDP GSO on this kernel or device: one at a time
                self._send_run(run, peer, size)
                return
            lost = len(run) - sent
            if exc.errno == errno.EMSGSIZE:
                c.drops["too_big_for_n3"] += lost  # DF is set: never fragmented
            elif exc.errno in (errno.EAGAIN, errno.ENOBUFS):
                c.drops["n3_busy"] += lost
            else:
                c.drops[f"send_{errno.errorcode.get(exc.errno or 0, 'error')}"] += lost
            run = run[:sent]
        c.sent["packets"] += len(run)
        c.sent["n3_bytes"] += sum(map(len, run)) + OUTER_IP_UDP * len(run)

    # ---- N3 -> TUN -------------------------------------------------------------------------

    def from_n3(self) -> int:
        """Unwrap what N3 delivered (up to a batch of receives; with UDP GRO one receive may
        hold many datagrams of one size, `gso` says how long each is). The inner packets go
        into the TUN together at the end: with offloads a run of one TCP flow's segments as
        one super-packet (`netem.gso.coalesce`, as a NIC's GRO would), so the stack behind
        handles one packet where it would have handled dozens."""
        n = 0
        inner: list[bytes] = []
        while n < _BATCH:
            try:
                data, anc, _flags, peer = self.sock.recvmsg(65535, _GRO_CMSG_SPACE)
            except BlockingIOError:
                break
            n += 1
            size = len(data)
            for level, kind, value in anc:
                if level == SOL_UDP and kind == UDP_GRO and len(value) >= 2:
                    size = struct.unpack("=H", value[:2])[0] or size
            if size >= len(data):
                self._untunnel(data, peer, inner)
            else:
                self._untunnel_run(data, size, peer, inner)
            if n == 1 and inner:  # as in `from_tun`: the first receive goes on at once
                self._to_tun(inner)
                inner = []
        if inner:
            self._to_tun(inner)
        return n

    def _untunnel_run(
        self, data: bytes, size: int, peer: tuple[str, int], inner_out: list[bytes]
    ) -> None:
        """The datagrams of one UDP GRO receive: `size` bytes each (the last may be
        shorter), one peer. G-PDUs of one tunnel and flow with no sequence number are alike
        to the byte in their 16-byte header, so the first one's is checked in full and the
        others are compared with it (and their inner source with the UE's); any that differs
        goes through `_untunnel` alone."""
        head = data[:16]
        session = self._by_teid.get(head[4:8])
        if (
            session is None
            or head[:2] != _GPDU_FLAGS_TYPE
            or head[11:13] != _ONE_CONTAINER
            or head[15] != 0
            or int.from_bytes(head[2:4], "big") + 8 != size
            or size < 16 + 20
        ):
            for off in range(0, len(data), size):
                self._untunnel(data[off : off + size], peer, inner_out)
            return
        # The UPF lets only the session's own UE send in its tunnel; the gNB checks nothing.
        ue = session.ue_packed if self._spoof_check else None
        alike = 0
        whole = len(data) - len(data) % size
        for off in range(0, whole, size):
            if data[off : off + 16] == head and (ue is None or data[off + 28 : off + 32] == ue):
                inner_out.append(data[off + 16 : off + size])
                alike += 1
            else:
                self._untunnel(data[off : off + size], peer, inner_out)
        if whole < len(data):
            self._untunnel(data[whole:], peer, inner_out)
        c = self.counters
        c.received["packets"] += alike
        c.received["inner_bytes"] += alike * (size - 16)
        c.received["n3_bytes"] += alike * (size + OUTER_IP_UDP)

    def _to_tun(self, packets: list[bytes]) -> None:
        c = self.counters
        frames = coalesce(packets) if self.cfg.offload else [(p, 1) for p in packets]
        for frame, count in frames:
            try:
                os.write(self.tun, frame)
            except OSError:
                c.drops["tun_write"] += count
                c.received["packets"] -= count
        c.received["tun_writes"] += len(frames)
        merged = [count for _, count in frames if count > 1]
        if merged:  # how much GRO did: packets handed on inside super-packets, and those
            c.received["gro_packets"] += sum(merged)
            c.received["gro_frames"] += len(merged)

    def _untunnel(self, datagram: bytes, peer: tuple[str, int], inner_out: list[bytes]) -> None:
        c = self.counters
        # The G-PDU as this testbed's ends send it (flags 0x34, one PDU Session Container),
        # read in place; anything else through the general decoder.
        if (
            datagram[:2] == _GPDU_FLAGS_TYPE
            and datagram[11:13] == _ONE_CONTAINER
            and len(datagram) >= 16
            and datagram[15] == 0
        ):
            teid = datagram[4:8]
            inner = datagram[16 : 8 + int.from_bytes(datagram[2:4], "big")]
        else:
            try:
                msg = decode(datagram)
            except GtpError:
                c.drops["malformed"] += 1
                return
            if msg.message_type == ECHO_REQUEST:
                c.echo["requests_received"] += 1
                with contextlib.suppress(OSError):
                    self.sock.sendto(echo_response(msg.sequence or 0), peer)
                    c.echo["responses_sent"] += 1
                return
            if msg.message_type == ECHO_RESPONSE:
                c.echo["responses_received"] += 1
                return
            if msg.message_type != G_PDU:
                c.drops[f"message_type_{msg.message_type}"] += 1
                return
            teid, inner = msg.teid.to_bytes(4, "big"), msg.payload
        session = self._by_teid.get(teid)
        if session is None:
            c.drops["unknown_teid"] += 1
            return
        # Only the session's own UE may send in its tunnel (no spoofed sources onto N6).
        if self._spoof_check and (len(inner) < 20 or inner[12:16] != session.ue_packed):
            c.drops["spoofed_source"] += 1
            return
        inner_out.append(inner)
        c.received["packets"] += 1
        c.received["inner_bytes"] += len(inner)
        c.received["n3_bytes"] += len(datagram) + OUTER_IP_UDP

    def send_echo(self, peer: str) -> None:
        self._seq = (self._seq + 1) & 0xFFFF
        with contextlib.suppress(OSError):
            self.sock.sendto(echo_request(self._seq), (peer, GTPU_PORT))
            self.counters.echo["requests_sent"] += 1


def open_endpoint(config: EndpointConfig) -> tuple[int, socket.socket]:
    """The TUN device and the N3 socket of `config`, made inside its namespace."""
    with in_netns(config.netns):
        # Reads one packet at a time: the kernel segments TCP faster than Python could.
        tun = TunConfig(config.tun, mtu=config.tun_mtu, offload=config.offload, tso=False)
        fd = open_tun(tun)
        try:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.IPPROTO_IP, IP_MTU_DISCOVER, IP_PMTUDISC_DO)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
            # Coalesced receives of equal-sized datagrams (fewer system calls); none is fine.
            with contextlib.suppress(OSError):
                sock.setsockopt(SOL_UDP, UDP_GRO, 1)
            sock.bind((config.address, GTPU_PORT))
            sock.setblocking(False)
        except OSError as exc:
            os.close(fd)
            raise GtpEndpointError(
                f"{config.role} in {config.netns}: cannot bind GTP-U on "
                f"{config.address}:{GTPU_PORT}: {exc.strerror}"
            ) from None
    return fd, sock


def _write_stats(path: str | None, endpoint: Endpoint) -> None:
    if not path:
        return
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(
            {"role": endpoint.cfg.role, "time": time.time(), **endpoint.counters.to_dict()}, f
        )
    os.replace(tmp, path)


def serve(
    config: EndpointConfig, echo_peers: tuple[str, ...] = (), echo_interval_s: float = 0
) -> int:
    """Run one end until SIGTERM/SIGINT (the process's main)."""
    fd, sock = open_endpoint(config)
    endpoint = Endpoint(config, fd, sock)
    stop = False

    def on_signal(*_: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    # A signal wakes the select at once (its byte on this pipe) rather than at its timeout:
    # a run's teardown waits for every endpoint to have written its last counters.
    wake_r, wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
    signal.set_wakeup_fd(wake_w)
    sel = selectors.DefaultSelector()
    sel.register(fd, selectors.EVENT_READ, endpoint.from_tun)
    sel.register(sock, selectors.EVENT_READ, endpoint.from_n3)
    sel.register(wake_r, selectors.EVENT_READ, lambda: os.read(wake_r, 64))
    print(json.dumps({"event": "ready", "pid": os.getpid(), "role": config.role}), flush=True)
    next_stats = next_echo = time.monotonic()
    try:
        while not stop:
            now = time.monotonic()
            if now >= next_stats:
                _write_stats(config.stats_path, endpoint)
                next_stats = now + STATS_INTERVAL_S
            if echo_interval_s > 0 and now >= next_echo:
                for peer in echo_peers:
                    endpoint.send_echo(peer)
                next_echo = now + echo_interval_s
            for key, _ in sel.select(timeout=STATS_INTERVAL_S / 2):
                key.data()
    finally:
        _write_stats(config.stats_path, endpoint)
        signal.set_wakeup_fd(-1)
        sel.close()
        sock.close()
        for end in (fd, wake_r, wake_w):
            os.close(end)
    return 0


class GtpEndpoint:
    """One end as a process; a context manager (`stats()` reads its latest counters)."""

    def __init__(
        self,
        config: EndpointConfig,
        echo_interval_s: float = 0.0,
        die_with_parent: bool = True,
        nice: int = -10,
        workdir: str | os.PathLike[str] | None = None,
    ) -> None:
        self.config = config
        self.nice = nice
        self.echo_interval_s = echo_interval_s
        self.die_with_parent = die_with_parent
        # Its config, counters and log: in `workdir` (a run's state folder, which outlives a
        # detached `testbed up`), else in a temporary folder of its own, removed on close.
        self._own_dir = workdir is None
        if workdir is None:
            self._dir = tempfile.mkdtemp(prefix=f"gtp-{config.role}-")
        else:
            self._dir = str(workdir)
            os.makedirs(self._dir, exist_ok=True)
        stats = config.stats_path or os.path.join(self._dir, "stats.json")
        self.config = dataclasses.replace(config, stats_path=stats)
        self.proc: subprocess.Popen[str] | None = None

    def start(self, timeout_s: float = 10.0) -> GtpEndpoint:
        return self.launch().wait_ready(timeout_s)

    def launch(self) -> GtpEndpoint:
        """Start the process without waiting for it to be ready (`wait_ready` does)."""
        if self.proc is not None:
            raise GtpEndpointError(f"GTP-U {self.config.role} is already started")
        path = Path(self._dir) / "config.json"
        path.write_text(self.config.to_json())
        cmd = [sys.executable, "-m", "netem.gtpu.endpoint", str(path)]
        if self.echo_interval_s > 0:
            cmd += ["--echo-interval", str(self.echo_interval_s)]
        if self.die_with_parent:
            cmd.append("--die-with-parent")
        if self.nice and os.geteuid() == 0:
            # Like the relays: on a busy 2-core host an endpoint waiting for a CPU adds delay.
            cmd += ["--nice", str(self.nice)]
        self.proc = spawn(cmd, Path(self._dir) / "gtp.log")
        return self

    def wait_ready(self, timeout_s: float = 10.0) -> GtpEndpoint:
        """Wait for the launched process's ready line; on failure it is gone and closed."""
        if self.proc is None:
            raise GtpEndpointError(f"GTP-U {self.config.role} was not launched")
        self.proc, why = wait_ready(self.proc, Path(self._dir) / "gtp.log", timeout_s)
        if self.proc is None:
            self.close()
            raise GtpEndpointError(f"GTP-U {self.config.role} failed to start: {why}")
        return self

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def stats(self) -> dict[str, Any]:
        try:
            return json.loads(Path(self.config.stats_path or "").read_text())
        except (OSError, ValueError):
            return {}

    def close(self, timeout_s: float = 3.0) -> dict[str, Any]:
        """Stop the process; returns its last counters."""
        stop(self.proc, timeout_s)
        self.proc = None
        stats = self.stats()
        if self._own_dir:
            remove_dir(self._dir)
        return stats

    def __enter__(self) -> GtpEndpoint:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m netem.gtpu.endpoint", description=__doc__.splitlines()[0]
    )
    p.add_argument("config", help="the endpoint's EndpointConfig as JSON (a file)")
    p.add_argument("--echo-interval", type=float, default=0.0, help="s between Echo Requests")
    p.add_argument("--die-with-parent", action="store_true", help="exit when the parent dies")
    p.add_argument("--nice", type=int, default=0, help="priority change (-10: as the relays)")
    args = p.parse_args(argv)
    renice("gtp", args.nice)
    if args.die_with_parent and not die_with_parent():
        return 1
    try:
        config = EndpointConfig.from_json(Path(args.config).read_text())
        peers = tuple(sorted({s.upf_address if config.role == "gnb" else s.gnb_address
                              for s in config.sessions}))  # fmt: skip
        return serve(config, peers, args.echo_interval)
    except (OSError, ValueError, NetemError) as exc:
        print(f"gtp: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
