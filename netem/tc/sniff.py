"""Captures of a link whose packets no relay sees: the tc backend's veth pairs.

On the userspace backend the relay writes `record.pcap`'s files itself (`netem.relay`). On
the tc backend the kernel moves the packets, so a capture listens where they leave the link:
an AF_PACKET socket on each end's interface takes what arrives there, after every qdisc of
the far end (netem's delay, loss, rate), as tcpdump would on that interface. What arrives at
the upper end is the uplink, at the lower end the downlink; what an end sends itself
(PACKET_OUTGOING) is left out, so each packet is in the file once.

- `SniffConfig`: the link's name, its two ends (namespace, interface) and the pcapng path.
- `Sniffer`: the data plane over the two open sockets: each received packet, stamped by the
  kernel on arrival (SO_TIMESTAMPNS), goes into the file as the wire packets it stands for,
  without its Ethernet header (raw-IP interfaces, as the relays' captures): the sockets read
  a virtio-net header (PACKET_VNET_HDR), so a TCP super-packet that crossed
  the veth whole is written segment by segment with its checksums done (`netem.gso`).
- `LinkSniffer`: the process (`python -m netem.tc.sniff CONFIG.json`), a context manager;
  `close()` finishes the file and returns what it holds, as a relay's capture does. The
  link's own drops are not counted here (`dropped` is None): netem's qdisc has them.
"""

from __future__ import annotations

import argparse
import contextlib
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
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from netem.directions import DIRECTIONS
from netem.errors import NetemError
from netem.gso import VNET, VNET_LEN, ip_packets
from netem.netns import in_netns
from netem.pcap import PcapngWriter
from netem.proc import die_with_parent, remove_dir, spawn_ready, stop

ETH_P_ALL, ETH_P_IP, ETH_P_IPV6 = 0x0003, 0x0800, 0x86DD
SOL_PACKET, PACKET_VNET_HDR, PACKET_STATISTICS = 263, 15, 6
ETH_HLEN, ARPHRD_ETHER = 14, 1  # a veth has an Ethernet header; a TUN none
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("=qq")
#: How long a packet waits to be written, so that both ends' packets go in in time order.
HOLD_NS = 50_000_000
_ANCILLARY = socket.CMSG_SPACE(_TIMESPEC.size)
#: Which direction arrives at which end: the uplink goes from the lower end to the upper.
_ARRIVING = {"upper": "uplink", "lower": "downlink"}


class SniffError(NetemError, RuntimeError):
    """A link capture could not start, or died; the message says which and why."""


@dataclass(frozen=True)
class SniffConfig:
    """One link to capture (see the module doc). `stats_path`: where the process writes what
    the file holds when it ends."""

    link: str
    path: str
    lower_netns: str
    lower_ifname: str
    upper_netns: str
    upper_ifname: str
    stats_path: str | None = None

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> SniffConfig:
        return cls(**json.loads(text))


def open_socket(netns: str, ifname: str) -> socket.socket:
    """An AF_PACKET socket on `ifname` in `netns` that reads IP packets behind a virtio-net
    header, with the kernel's arrival time."""
    with in_netns(netns):
        # SOCK_RAW: the kernel gives a virtio-net header only there (the Ethernet header
        # comes with it and is cut off in `Sniffer.read`).
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
        try:
            sock.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
            sock.bind((ifname, ETH_P_ALL))
        except OSError as exc:
            sock.close()
            raise SniffError(f"cannot capture on {ifname} in {netns}: {exc.strerror}") from None
    sock.setblocking(False)
    return sock


class Sniffer:
    """Writes what arrives on the two sockets into one pcapng file (see the module doc)."""

    def __init__(self, config: SniffConfig, lower: socket.socket, upper: socket.socket) -> None:
        self.cfg = config
        self.writer = PcapngWriter(config.path)
        self.sockets = {"lower": lower, "upper": upper}
        self.interfaces = {d: self.writer.interface(f"{config.link} {d}") for d in DIRECTIONS}
        self.packets = {"uplink": 0, "downlink": 0}
        self._held: list[tuple[int, str, bytes]] = []  # (arrival ns, direction, data)
        self.unstamped = 0  # reads the kernel gave no arrival time (stamped when read)

    def read(self, *ends: str, flush: bool = False) -> None:
        """Take what the sockets of `ends` hold now, and write, in arrival order, what
        arrived more than `HOLD_NS` ago (everything with `flush`). The two sockets are read
        one after the other, so a packet and its answer can come in different reads; holding
        them a moment puts them in the file in the order they arrived."""
        for end in ends:
            self._held += self._drain(end)
        if not self._held:
            return
        self._held.sort(key=lambda g: g[0])
        cut = len(self._held)
        if not flush:
            horizon = time.time_ns() - HOLD_NS
            cut = next((k for k, g in enumerate(self._held) if g[0] > horizon), cut)
        ready, self._held = self._held[:cut], self._held[cut:]
        for stamp, direction, data in ready:
            flag = "outbound" if direction == "uplink" else "inbound"
            for packet in ip_packets(data):
                self.writer.packet(self.interfaces[direction], packet, stamp, direction=flag)
                self.packets[direction] += 1

    def _drain(self, end: str) -> list[tuple[int, str, bytes]]:
        sock, direction = self.sockets[end], _ARRIVING[end]
        out: list[tuple[int, str, bytes]] = []
        while True:
            try:
                data, anc, _flags, address = sock.recvmsg(VNET_LEN + ETH_HLEN + 65535, _ANCILLARY)
            except BlockingIOError:
                return out
            # address: (ifname, protocol, packet type, hardware type, hardware address)
            if address[2] == socket.PACKET_OUTGOING or address[1] not in (ETH_P_IP, ETH_P_IPV6):
                continue
            stamp = None
            for level, kind, value in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = _TIMESPEC.unpack_from(value)
                    stamp = sec * 1_000_000_000 + nsec
            if address[3] == ARPHRD_ETHER:
                data = _without_ethernet(data)
            if stamp is None:
                self.unstamped += 1
            out.append((time.time_ns() if stamp is None else stamp, direction, data))

    def capture_drops(self) -> int:
        """Packets the sockets' queues overflowed with since they opened (capture losses)."""
        total = 0
        for sock in self.sockets.values():
            with contextlib.suppress(OSError):
                _, drops = struct.unpack("=II", sock.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8))
                total += drops
        return total

    def close(self) -> dict[str, Any]:
        self.read(flush=True)
        missed = self.capture_drops()
        now = time.time_ns()
        for direction, iface in self.interfaces.items():
            self.writer.statistics(iface, now, self.packets[direction], 0)
        self.writer.close()
        for sock in self.sockets.values():
            sock.close()
        return {
            "path": self.cfg.path,
            "packets": dict(self.packets),
            "dropped": None,  # the link's drops are netem's (see the module doc)
            "capture_missed": missed,
            "unstamped": self.unstamped,
        }


def _without_ethernet(data: bytes) -> bytes:
    """A raw read (virtio-net header, Ethernet header, IP packet) as an offloading TUN would
    give it: the header's checksum start counted from the IP header instead."""
    flags, gso_type, hdr_len, gso_size, start, offset = VNET.unpack_from(data)
    head = VNET.pack(flags, gso_type, max(hdr_len - ETH_HLEN, 0), gso_size,
                     max(start - ETH_HLEN, 0), offset)  # fmt: skip
    return head + data[VNET_LEN + ETH_HLEN :]


def serve(config: SniffConfig) -> int:
    """Capture until SIGTERM/SIGINT (the process's main); writes the result to stats_path."""
    lower = open_socket(config.lower_netns, config.lower_ifname)
    try:
        upper = open_socket(config.upper_netns, config.upper_ifname)
    except SniffError:
        lower.close()
        raise
    sniffer = Sniffer(config, lower, upper)
    stop_r, stop_w = socket.socketpair()
    stop_w.setblocking(False)

    def on_signal(*_: object) -> None:
        with contextlib.suppress(OSError):
            stop_w.send(b"x")

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    sel = selectors.DefaultSelector()
    sel.register(lower, selectors.EVENT_READ, "lower")
    sel.register(upper, selectors.EVENT_READ, "upper")
    sel.register(stop_r, selectors.EVENT_READ, None)
    print(json.dumps({"event": "ready", "pid": os.getpid()}), flush=True)
    try:
        running = True
        while running:
            ready = [key.data for key, _ in sel.select(HOLD_NS / 1e9)]
            running = None not in ready
            sniffer.read("lower", "upper")
        sniffer.read("lower", "upper", flush=True)  # what arrived before the stop
    finally:
        sel.close()
        result = sniffer.close()
        if config.stats_path:
            Path(config.stats_path).write_text(json.dumps(result))
    return 0


class LinkSniffer:
    """One link's capture as a process; a context manager (`close()` returns what it holds)."""

    def __init__(self, config: SniffConfig) -> None:
        self._dir = tempfile.mkdtemp(prefix="sniff-")
        self.config = SniffConfig(**{**asdict(config), "stats_path": f"{self._dir}/stats.json"})
        self.proc: subprocess.Popen[str] | None = None

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def start(self, timeout_s: float = 10.0) -> LinkSniffer:
        cfg = Path(self._dir) / "config.json"
        cfg.write_text(self.config.to_json())
        cmd = [sys.executable, "-m", "netem.tc.sniff", str(cfg), "--die-with-parent",
               "--link", self.config.link]  # fmt: skip
        self.proc, why = spawn_ready(cmd, Path(self._dir) / "sniff.log", timeout_s)
        if self.proc is None:
            self.close()
            raise SniffError(f"capture of {self.config.link} did not start: {why}")
        return self

    def close(self, timeout_s: float = 5.0) -> dict[str, Any]:
        """Stop the process (it finishes the file); returns {path, packets, dropped, ...}."""
        stop(self.proc, timeout_s)
        self.proc = None
        result: dict[str, Any] = {}
        with contextlib.suppress(OSError, ValueError):
            result = json.loads(Path(self.config.stats_path or "").read_text())
        remove_dir(self._dir)
        return result

    def __enter__(self) -> LinkSniffer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m netem.tc.sniff", description=__doc__.splitlines()[0]
    )
    p.add_argument("config", help="the capture's SniffConfig as JSON (a file)")
    p.add_argument("--die-with-parent", action="store_true", help="exit when the parent dies")
    p.add_argument("--link", help="the link's name (for ps and `testbed clean`)")
    args = p.parse_args(argv)
    if args.die_with_parent and not die_with_parent():
        return 1
    try:
        return serve(SniffConfig.from_json(Path(args.config).read_text()))
    except (OSError, ValueError, NetemError) as exc:
        print(f"sniff: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
