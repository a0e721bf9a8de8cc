"""The traffic generator process, one end of a flow, started inside a node's network namespace.

    python -m nodes.traffic.gen recv --kind tcp|udp --port P --stats FILE [--samples FILE]
        [--bind ADDR] [--interval S] [--echo-every S] [--duration S] [--nice N]
        [--die-with-parent]
    python -m nodes.traffic.gen send --kind tcp|udp|onoff --to ADDR --port P --stats FILE
        [--samples FILE] [--rate BIT/S] [--size BYTES] [--on S --off S] [--duration S]
        [--start-at MONO_S] [--interval S] [--late-after S] [--max-lag S] [--sndbuf BYTES]
        [--connect-timeout S] [--nice N] [--die-with-parent]

Both ends print one line `{"event": "ready", ...}` to stdout, flushed, once their socket is
bound and listening (recv) or connected (send), and nothing else to stdout; errors go to
stderr. Each runs until SIGTERM or SIGINT (or `--duration`), then writes `--stats` as JSON
(a temporary file renamed over it, so a reader never sees half of one) and exits 0; 1 if its
socket could not be set up (the stats file is still written, with the reason in `errors`),
2 on a bad command line. `--samples` gets one JSON line per `--interval` (0.5 s), appended
and flushed as it is written, so a reader can follow it live: `t`, `time_ns` (wall clock,
for a recording's log time), `role`, `kind`, then `flows.SAMPLE_KEYS`.

`--rate` is payload bits per second (UDP payload, or bytes written to TCP), as iperf3
counts; `--size` is the UDP payload of one datagram (at least the 24-byte header), or one
TCP write. Stop the sender before the receiver: its last datagrams (FIN, the count it sent)
tell the receiver about loss at the flow's tail.

The stats JSON (None where a value does not apply or there was no data):

- every role: kind, role, pid, started_ns (wall clock), duration_s (from the receiver's
  ready line or the sender's first deadline, to its stop), active_s (first to last data),
  errors ({"what: why": count}, {} when none);
- recv: port, packets_received (new datagrams, or TCP reads), bytes_received (payload),
  goodput_bps (over active_s); udp also loss (0..1), expected, lost, reordered, duplicates,
  stale, flows, fins, delay_p50_ms, delay_p95_ms, delay_mean_ms, delay_max_ms (one-way),
  foreign (datagrams not ours), echoes, socket_drops (the receiver's own buffer overflowed);
  tcp also connections, resets, segments (data segments the kernel received);
- send: to, port, rate_bps, size, packets_sent (datagrams, or TCP writes), bytes_sent,
  sent_bps, goodput_bps and bytes_acked (TCP: what the receiver acknowledged), rtt_p50_ms,
  rtt_p95_ms, rtt_samples, late_packets, skipped_packets, lag_p95_ms, lag_max_ms (the
  generator's own shortfall; None for TCP without --rate); udp/onoff also flow, on_s,
  off_s, send_blocked, sndbuf; tcp also segments, mss, retransmits, min_rtt_ms.

A run that exits 1 has only the keys of every role.

The nouns: `Stopper` turns SIGTERM/SIGINT into a flag and a wake-up of the wait in progress;
`Output` writes the sample lines and the stats file; `recv_udp`, `recv_tcp`, `send_udp`,
`send_tcp` are the four loops, each returning its stats.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import ctypes
import ipaddress
import json
import math
import os
import select
import signal
import socket
import struct
import sys
import time
from pathlib import Path
from typing import Any, TextIO

from nodes.traffic.flows import (
    DATA,
    ECHO,
    FIN,
    HEADER_SIZE,
    MS,
    NS,
    TCP_INFO_LEN,
    Cbr,
    OnOff,
    Pacer,
    RecvAccount,
    Schedule,
    SendAccount,
    TcpInfo,
    Ticker,
    pack_header,
    parse_tcp_info,
    unpack_header,
)

PR_SET_PDEATHSIG, PR_SET_TIMERSLACK = 1, 29
SO_SNDBUFFORCE = getattr(socket, "SO_SNDBUFFORCE", 32)
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
#: Socket buffers of a datagram flow. The sender's must hold more than the link's queue: a
#: qdisc on the sender's own interface (an uplink profile or cap on a vehicle's egress) keeps
#: each queued datagram charged to the socket, and with the default 208 KiB a 20 Mbit/s tbf
#: holding 50 ms would block the sender before the queue is full, so it would never drop: a
#: 30 Mbit/s CBR flow would quietly become 20 Mbit/s with no loss (`--sndbuf 0` asks for
#: exactly that back-pressure). The receiver's absorbs a late wake-up.
DGRAM_BUF_BYTES = 4 << 20
#: How often a TCP sender reads TCP_INFO (its RTT samples, bytes acknowledged).
TCP_INFO_EVERY_NS = 20 * MS
#: When a UDP sender sends its FIN, from the moment it stopped: the first copies may be
#: dropped by a full queue at the bottleneck, the later ones find it drained.
FIN_AFTER_S = (0.0, 0.025, 0.1, 0.25)
#: At most this many reads or writes between two looks at the clock (samples, the stop flag).
BATCH = 256
MAX_UDP_PAYLOAD = 65507
DEFAULT_SIZE = {"udp": 1200, "onoff": 1200, "tcp": 16384}


class Stopper:
    """SIGTERM and SIGINT set `stopped` and wake `wait` at once (a self-pipe the signal
    writes into), so a loop sleeping until its next deadline stops without delay."""

    def __init__(self) -> None:
        self.stopped = False
        self._r, self._w = socket.socketpair()
        self._r.setblocking(False)
        self._w.setblocking(False)
        signal.set_wakeup_fd(self._w.fileno(), warn_on_full_buffer=False)
        signal.signal(signal.SIGTERM, self._handle)
        signal.signal(signal.SIGINT, self._handle)

    def _handle(self, signum: int, frame: object) -> None:
        self.stopped = True

    def wait(
        self,
        timeout_s: float,
        readers: list[socket.socket],
        writers: list[socket.socket] | None = None,
    ) -> tuple[list[socket.socket], list[socket.socket]]:
        """Sleep until a socket is ready, a signal comes, or `timeout_s` passes. select has
        microsecond resolution (poll's is a millisecond: too coarse for 3,000 packets/s)."""
        r, w, _ = select.select([self._r, *readers], writers or [], [], max(timeout_s, 0.0))
        if self._r in r:
            with contextlib.suppress(BlockingIOError):
                self._r.recv(64)
            r.remove(self._r)
        return r, w

    def sleep_until(self, deadline_ns: int) -> None:
        """Sleep until the monotonic clock reaches `deadline_ns` or a signal comes."""
        while not self.stopped and (left := deadline_ns - time.monotonic_ns()) > 0:
            self.wait(left / NS, [])


class Output:
    """The sample lines (appended and flushed one by one) and the stats file (atomic)."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.stats_path = Path(args.stats)
        self.role, self.kind = args.role, args.kind
        self.started_ns = time.time_ns()
        self.errors: collections.Counter[str] = collections.Counter()
        self._samples: TextIO | None = None
        if args.samples:
            self._samples = open(args.samples, "a")  # noqa: SIM115 - open for the whole run

    def sample(self, values: dict[str, Any]) -> None:
        if self._samples is None:
            return
        line = {"t": values["t"], "time_ns": time.time_ns(), "role": self.role, "kind": self.kind}
        line.update(values)
        self._samples.write(_dumps(line) + "\n")
        self._samples.flush()

    def error(self, what: str, exc: OSError) -> None:
        """Count an error by its kind (a refused datagram may repeat thousands of times)."""
        self.errors[f"{what}: {exc.strerror or exc}"] += 1

    def finish(self, stats: dict[str, Any]) -> None:
        out = {
            "kind": self.kind,
            "role": self.role,
            "pid": os.getpid(),
            "started_ns": self.started_ns,
            **stats,
            "errors": dict(self.errors),
        }
        tmp = self.stats_path.with_name(f".{self.stats_path.name}.{os.getpid()}.tmp")
        tmp.write_text(_dumps(out, indent=2) + "\n")
        tmp.replace(self.stats_path)
        if self._samples is not None:
            self._samples.close()


def _strict(value: Any) -> Any:
    """NaN and infinities as null: strict JSON that every reader accepts."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_strict(v) for v in value]
    return value


def _dumps(value: Any, indent: int | None = None) -> str:
    return json.dumps(_strict(value), indent=indent, allow_nan=False)


def _ready(**fields: Any) -> None:
    # The starter reads this line to know the socket exists; `"event"` must come first.
    print(json.dumps({"event": "ready", "pid": os.getpid(), **fields}), flush=True)


def _family(addr: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ipaddress.ip_address(addr).version == 6 else socket.AF_INET


def _grow_buffer(sock: socket.socket, plain: int, force: int, nbytes: int) -> None:
    """Set a socket buffer past net.core.[rw]mem_max where allowed (root), else as far as
    the limit lets an ordinary user."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, force, nbytes)
    except PermissionError:
        sock.setsockopt(socket.SOL_SOCKET, plain, nbytes)


def _tcp_info(sock: socket.socket) -> TcpInfo | None:
    try:
        return parse_tcp_info(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, TCP_INFO_LEN))
    except (OSError, ValueError):
        return None


def _udp_drops(sock: socket.socket) -> int | None:
    """Datagrams the kernel dropped because this socket's buffer was full (the `drops`
    column of /proc/net/udp, found by the socket's inode): loss at the receiver itself,
    which sequence gaps cannot tell from loss on the path."""
    inode = str(os.fstat(sock.fileno()).st_ino)
    for table in ("/proc/self/net/udp", "/proc/self/net/udp6"):
        with contextlib.suppress(OSError), open(table) as f:
            for line in f:
                fields = line.split()
                if len(fields) > 12 and fields[9] == inode:
                    return int(fields[12])
    return None


def _deadline(*deadlines: int | None) -> int:
    return min(d for d in deadlines if d is not None)


# --- receivers -------------------------------------------------------------------------------


def recv_udp(args: argparse.Namespace, stop: Stopper, out: Output) -> dict[str, Any]:
    sock = socket.socket(_family(args.bind), socket.SOCK_DGRAM)
    try:
        _grow_buffer(sock, socket.SO_RCVBUF, SO_RCVBUFFORCE, DGRAM_BUF_BYTES)
        sock.bind((args.bind, args.port))
        sock.setblocking(False)
        _ready(role="recv", kind="udp", addr=args.bind, port=sock.getsockname()[1])
        mono = time.monotonic_ns
        start = mono()
        end = start + round(args.duration * NS) if args.duration else None
        acct = RecvAccount(start, datagrams=True)
        ticker = Ticker(start, round(args.interval * NS))
        echo_every = round(args.echo_every * NS)
        last_echo = start - echo_every
        buf = bytearray(MAX_UDP_PAYLOAD + 1)
        reply = bytearray(HEADER_SIZE)
        foreign = echoes = 0
        while not stop.stopped:
            for _ in range(BATCH):
                try:
                    n, peer = sock.recvfrom_into(buf)
                except BlockingIOError:
                    break
                except OSError as exc:
                    out.error("recv", exc)
                    break
                now = mono()
                header = unpack_header(buf, n)
                if header is None:
                    foreign += 1
                    continue
                kind, flow, seq, send_ns = header
                if kind == DATA:
                    acct.on_datagram(now, flow, seq, send_ns, n)
                    # Echo one datagram per interval, not one in N: a slow flow still gets
                    # RTT samples, a fast one no more than it needs.
                    if now - last_echo >= echo_every:
                        last_echo = now
                        pack_header(reply, ECHO, flow, seq, send_ns)
                        try:
                            sock.sendto(reply, peer)
                            echoes += 1
                        except OSError as exc:
                            out.error("echo", exc)
                elif kind == FIN:
                    acct.on_fin(flow, seq)
            now = mono()
            if end is not None and now >= end:
                break
            if ticker.due(now):
                out.sample(acct.sample(now))
                ticker.advance(now)
            stop.wait((_deadline(ticker.next_ns, end) - mono()) / NS, [sock])
        stats = acct.summary(mono())
        stats.update(
            port=sock.getsockname()[1],
            foreign=foreign,
            echoes=echoes,
            socket_drops=_udp_drops(sock),
        )
        return stats
    finally:
        sock.close()


def recv_tcp(args: argparse.Namespace, stop: Stopper, out: Output) -> dict[str, Any]:
    listener = socket.socket(_family(args.bind), socket.SOCK_STREAM)
    conns: dict[int, socket.socket] = {}
    segs_in = 0

    def close(conn: socket.socket) -> None:
        nonlocal segs_in
        info = _tcp_info(conn)
        segs_in += (info.data_segs_in or 0) if info else 0
        conns.pop(conn.fileno(), None)
        conn.close()

    try:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((args.bind, args.port))
        listener.listen(16)
        listener.setblocking(False)
        _ready(role="recv", kind="tcp", addr=args.bind, port=listener.getsockname()[1])
        mono = time.monotonic_ns
        start = mono()
        end = start + round(args.duration * NS) if args.duration else None
        acct = RecvAccount(start, datagrams=False)
        ticker = Ticker(start, round(args.interval * NS))
        buf = bytearray(1 << 18)
        accepted = resets = 0
        while not stop.stopped:
            timeout = (_deadline(ticker.next_ns, end) - mono()) / NS
            readable, _ = stop.wait(timeout, [listener, *conns.values()])
            for s in readable:
                if s is listener:
                    with contextlib.suppress(BlockingIOError):
                        while True:
                            conn, _peer = listener.accept()
                            conn.setblocking(False)
                            conns[conn.fileno()] = conn
                            accepted += 1
                    continue
                for _ in range(BATCH):
                    try:
                        n = s.recv_into(buf)
                    except BlockingIOError:
                        break
                    except OSError:
                        # A reset is how a sender that was told to stop ends its connection.
                        resets += 1
                        close(s)
                        break
                    if n == 0:
                        close(s)
                        break
                    acct.on_data(mono(), n)
            now = mono()
            if end is not None and now >= end:
                break
            if ticker.due(now):
                out.sample(acct.sample(now))
                ticker.advance(now)
        stats = acct.summary(mono())
        for conn in list(conns.values()):
            close(conn)
        # For TCP, packets_received counts reads; segments is what the kernel got.
        stats.update(
            port=listener.getsockname()[1], connections=accepted, resets=resets, segments=segs_in
        )
        return stats
    finally:
        for conn in conns.values():
            conn.close()
        listener.close()


# --- senders ---------------------------------------------------------------------------------


def _schedule(args: argparse.Namespace) -> Schedule:
    rate = round(args.rate)
    if args.kind == "onoff":
        return OnOff(rate, args.size, args.on, args.off)
    return Cbr(rate, args.size)


def _start(args: argparse.Namespace, stop: Stopper) -> int:
    """Wait for `--start-at` (CLOCK_MONOTONIC seconds, shared by every namespace of the host,
    so a starter can start several generators early and have them begin together)."""
    if args.start_at is not None:
        stop.sleep_until(round(args.start_at * NS))
    return time.monotonic_ns()


def _pacer_stats(pacer: Pacer | None) -> dict[str, Any]:
    if pacer is None:
        return {
            "late_packets": None,
            "skipped_packets": None,
            "lag_p95_ms": None,
            "lag_max_ms": None,
        }
    p95 = pacer.lags.quantile(0.95)
    return {
        "late_packets": pacer.late,
        "skipped_packets": pacer.skipped,
        "lag_p95_ms": None if p95 is None else p95 / MS,
        "lag_max_ms": None if pacer.lags.max is None else pacer.lags.max / MS,
    }


def send_udp(args: argparse.Namespace, stop: Stopper, out: Output) -> dict[str, Any]:
    schedule = _schedule(args)
    sock = socket.socket(_family(args.to), socket.SOCK_DGRAM)
    try:
        if args.sndbuf:
            _grow_buffer(sock, socket.SO_SNDBUF, SO_SNDBUFFORCE, args.sndbuf)
        _grow_buffer(sock, socket.SO_RCVBUF, SO_RCVBUFFORCE, 1 << 20)
        # Connected: send() instead of sendto(), and only the receiver's echoes come back.
        sock.connect((args.to, args.port))
        sock.setblocking(False)
        flow = int.from_bytes(os.urandom(4), "big")
        _ready(role="send", kind=args.kind, to=args.to, port=args.port, flow=flow)
        mono = time.monotonic_ns
        start = _start(args, stop)
        end = start + round(args.duration * NS) if args.duration else None
        acct = SendAccount(start, datagrams=True)
        pacer = Pacer(schedule, start, round(args.late_after * NS), round(args.max_lag * NS))
        ticker = Ticker(start, round(args.interval * NS))
        size = args.size
        buf = bytearray(size)
        echo = bytearray(HEADER_SIZE + 64)
        blocked = 0

        def read_echoes() -> None:
            while True:
                try:
                    n = sock.recv_into(echo)
                except BlockingIOError:
                    return
                except OSError as exc:  # an ICMP error: the receiver's port is closed
                    out.error("recv", exc)
                    return
                header = unpack_header(echo, n)
                if header is not None and header[0] == ECHO and header[1] == flow:
                    acct.on_rtt(mono() - header[3])

        while not stop.stopped:
            now = mono()
            if end is not None and now >= end:
                break
            pacer.skip_overdue(now)
            full = False
            while pacer.next_ns <= now:
                pack_header(buf, DATA, flow, pacer.sent_count, now)
                try:
                    sock.send(buf)
                except BlockingIOError:
                    # The socket buffer is full: wait until it drains, the packet goes late.
                    full = True
                    blocked += 1
                    break
                except OSError as exc:
                    # An earlier datagram's ICMP error fails this send; it did not leave.
                    out.error("send", exc)
                    pacer.give_up()
                    continue
                pacer.sent(now)
                acct.on_send(now, size)
                now = mono()
            read_echoes()
            if ticker.due(now):
                out.sample(acct.sample(now, pacer.late))
                ticker.advance(now)
            wake = _deadline(ticker.next_ns, end, None if full else pacer.next_ns)
            stop.wait((wake - mono()) / NS, [sock], [sock] if full else None)
        stopped = mono()
        total = pacer.sent_count
        fin = bytearray(HEADER_SIZE)
        for after in FIN_AFTER_S:
            time.sleep(max(0.0, stopped / NS + after - mono() / NS))
            pack_header(fin, FIN, flow, total, mono())
            with contextlib.suppress(OSError):
                sock.send(fin)
            read_echoes()
        stats = acct.summary(stopped)
        stats.update(
            to=args.to,
            port=args.port,
            flow=flow,
            rate_bps=args.rate,
            size=size,
            on_s=args.on if args.kind == "onoff" else None,
            off_s=args.off if args.kind == "onoff" else None,
            send_blocked=blocked,
            sndbuf=sock.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF),
            **_pacer_stats(pacer),
        )
        return stats
    finally:
        sock.close()


def _connect_tcp(args: argparse.Namespace, stop: Stopper, out: Output) -> socket.socket | None:
    """Connect, retrying while the receiver is not listening yet (up to --connect-timeout)."""
    give_up = time.monotonic_ns() + round(args.connect_timeout * NS)
    while not stop.stopped:
        sock = socket.socket(_family(args.to), socket.SOCK_STREAM)
        sock.settimeout(max(0.1, (give_up - time.monotonic_ns()) / NS))
        try:
            sock.connect((args.to, args.port))
            return sock
        except OSError as exc:
            sock.close()
            if time.monotonic_ns() >= give_up or not isinstance(exc, ConnectionRefusedError):
                out.error("connect", exc)
                return None
        stop.sleep_until(time.monotonic_ns() + 100 * MS)
    return None


def send_tcp(args: argparse.Namespace, stop: Stopper, out: Output) -> dict[str, Any] | None:
    sock = _connect_tcp(args, stop, out)
    if sock is None:
        return None
    try:
        sock.setblocking(False)
        _ready(role="send", kind="tcp", to=args.to, port=args.port)
        mono = time.monotonic_ns
        start = _start(args, stop)
        end = start + round(args.duration * NS) if args.duration else None
        acct = SendAccount(start, datagrams=False)
        pacer = None
        if args.rate:
            pacer = Pacer(
                Cbr(round(args.rate), args.size),
                start,
                round(args.late_after * NS),
                round(args.max_lag * NS),
            )
        ticker = Ticker(start, round(args.interval * NS))
        info_ticker = Ticker(start, TCP_INFO_EVERY_NS)
        chunk = memoryview(bytearray(args.size))
        pending: memoryview | None = None
        info: TcpInfo | None = None
        peer_gone = False

        def read_info(now: int) -> None:
            nonlocal info
            info = _tcp_info(sock) or info
            if info is not None:
                if info.rtt_us:
                    acct.on_rtt(info.rtt_us * 1000)
                if info.bytes_acked is not None:
                    acct.on_acked(now, info.bytes_acked)

        while not stop.stopped and not peer_gone:
            now = mono()
            if end is not None and now >= end:
                break
            if pending is None:
                if pacer is None:
                    pending = chunk
                else:
                    pacer.skip_overdue(now)
                    if pacer.due(now):
                        pacer.sent(now)
                        pending = chunk
            full = False
            for _ in range(BATCH):
                if pending is None:
                    break
                try:
                    n = sock.send(pending)
                except BlockingIOError:
                    full = True
                    break
                except OSError as exc:
                    out.error("send", exc)
                    peer_gone = True
                    break
                acct.on_send(now, n)
                pending = pending[n:] if n < len(pending) else None
                if pending is None and pacer is None:
                    pending = chunk
            now = mono()
            if info_ticker.due(now):
                read_info(now)
                info_ticker.advance(now)
            if ticker.due(now):
                out.sample(acct.sample(now, None if pacer is None else pacer.late))
                ticker.advance(now)
            if full or pending is None:
                due = None if pending is not None or pacer is None else pacer.next_ns
                wake = _deadline(ticker.next_ns, info_ticker.next_ns, end, due)
                readable, _ = stop.wait((wake - mono()) / NS, [sock], [sock] if full else None)
                if readable:
                    # The receiver never sends: readable means it closed or reset.
                    try:
                        peer_gone = sock.recv(1) == b""
                    except BlockingIOError:
                        pass
                    except OSError as exc:
                        out.error("recv", exc)
                        peer_gone = True
                    if peer_gone:
                        out.errors["receiver closed the connection"] += 1
        stopped = mono()
        read_info(stopped)
        stats = acct.summary(stopped)
        stats.update(
            to=args.to,
            port=args.port,
            rate_bps=args.rate or None,
            size=args.size,
            # For TCP, packets_sent counts writes; segments is what the kernel sent.
            segments=info.data_segs_out if info else None,
            mss=info.snd_mss if info else None,
            retransmits=info.total_retrans if info else None,
            min_rtt_ms=info.min_rtt_us / 1000 if info and info.min_rtt_us else None,
            **_pacer_stats(pacer),
        )
        return stats
    finally:
        # Abort (RST) rather than close: a stopped flow must stop loading the link now, not
        # after its socket buffer (seconds of data on a slow path) has drained.
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.close()


# --- the command line ------------------------------------------------------------------------


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text!r}")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if not value >= 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a number >= 0, not {text!r}")
    return value


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m nodes.traffic.gen", description=__doc__.splitlines()[0]
    )
    roles = p.add_subparsers(dest="role", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--port", type=int, required=True, help="UDP/TCP port (recv: 0 = any)")
    common.add_argument("--stats", required=True, help="stats JSON, written at exit")
    common.add_argument("--samples", help="JSON lines, one per interval, flushed as written")
    common.add_argument("--interval", type=_positive, default=0.5, help="sample interval (s)")
    common.add_argument("--duration", type=_non_negative, help="stop after S seconds")
    common.add_argument("--nice", type=int, default=0, help="scheduling priority change")
    common.add_argument(
        "--die-with-parent", action="store_true", help="exit when the starting process dies"
    )

    recv = roles.add_parser("recv", parents=[common], help="receive and account a flow")
    recv.add_argument("--kind", choices=("tcp", "udp"), required=True)
    recv.add_argument("--bind", default="0.0.0.0", help="address to listen on")
    recv.add_argument(
        "--echo-every",
        type=_positive,
        default=0.05,
        help="UDP: echo one datagram per this many seconds to the sender (its RTT)",
    )

    send = roles.add_parser("send", parents=[common], help="send a flow")
    send.add_argument("--kind", choices=("tcp", "udp", "onoff"), required=True)
    send.add_argument("--to", required=True, help="the receiver's address")
    send.add_argument(
        "--rate", type=_non_negative, help="payload bit/s (UDP: required; TCP: a cap)"
    )
    send.add_argument("--size", type=int, help="UDP payload / TCP write, bytes")
    send.add_argument("--on", type=_positive, help="onoff: seconds sending")
    send.add_argument("--off", type=_non_negative, help="onoff: seconds silent")
    send.add_argument(
        "--start-at", type=_non_negative, help="begin at this CLOCK_MONOTONIC time (s)"
    )
    send.add_argument(
        "--late-after",
        type=_non_negative,
        default=0.005,
        help="a packet sent more than S after its time counts as late",
    )
    send.add_argument(
        "--max-lag",
        type=_positive,
        default=0.5,
        help="packets more than S overdue are skipped, not sent in a burst",
    )
    send.add_argument(
        "--sndbuf",
        type=int,
        default=DGRAM_BUF_BYTES,
        help="UDP: socket send buffer, bytes (0: the kernel's default, which lets a qdisc on"
        " this host's own interface block the sender instead of dropping)",
    )
    send.add_argument(
        "--connect-timeout", type=_non_negative, default=5.0, help="TCP: retry connecting for S"
    )
    return p


def _check(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """What argparse cannot check alone; fills in the kind's default --size."""
    addr = args.to if args.role == "send" else args.bind
    try:
        ipaddress.ip_address(addr)
    except ValueError:
        p.error(f"not an IP address: {addr!r}")
    if not 0 <= args.port <= 65535 or (args.role == "send" and args.port == 0):
        p.error(f"--port {args.port}: not a port to {args.role} on")
    if args.role == "recv":
        return
    if args.size is None:
        args.size = DEFAULT_SIZE[args.kind]
    if args.kind == "tcp":
        if args.size < 1:
            p.error(f"--size {args.size}: a write needs at least 1 byte")
        return
    if not args.rate:
        p.error(f"--kind {args.kind} needs --rate (bit/s)")
    if not HEADER_SIZE <= args.size <= MAX_UDP_PAYLOAD:
        p.error(f"--size {args.size}: a datagram carries {HEADER_SIZE}..{MAX_UDP_PAYLOAD} bytes")
    if args.sndbuf < 0:
        p.error(f"--sndbuf {args.sndbuf}: bytes, or 0 for the kernel's default")
    if args.kind == "onoff" and (args.on is None or args.off is None):
        p.error("--kind onoff needs --on and --off (seconds)")


def _prepare(args: argparse.Namespace) -> bool:
    """Process settings before the first socket; False if the parent is already gone."""
    libc = ctypes.CDLL(None, use_errno=True)
    # 1 ns timer slack: the sender's sleeps end when asked, not up to 50 us later.
    libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)
    if args.nice:
        try:
            os.nice(args.nice)
        except OSError as exc:
            print(
                f"traffic: warning: cannot change priority by {args.nice}: {exc}", file=sys.stderr
            )
    if args.die_with_parent:
        parent = os.getppid()
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        return os.getppid() == parent
    return True


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    _check(p, args)
    if not _prepare(args):
        return 1
    stop = Stopper()
    out = Output(args)
    loops = {
        ("recv", "udp"): recv_udp,
        ("recv", "tcp"): recv_tcp,
        ("send", "udp"): send_udp,
        ("send", "onoff"): send_udp,
        ("send", "tcp"): send_tcp,
    }
    stats: dict[str, Any] | None = None
    try:
        stats = loops[args.role, args.kind](args, stop, out)
    except OSError as exc:
        out.error("socket", exc)
        print(f"traffic: error: {exc}", file=sys.stderr)
    out.finish(stats or {})
    return 0 if stats is not None else 1


if __name__ == "__main__":
    sys.exit(main())
