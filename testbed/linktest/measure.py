"""Measuring a link: stamped UDP streams, TCP goodput and echoes between two namespaces.

Senders and receivers are forked processes that step into the namespaces (`in_namespace`), so
the link, not one interpreter's GIL, is what is measured; both ends share the host's monotonic
clock, so a datagram's send stamp gives its one-way delay exactly. These functions are shared
with `testbed.capacity` and the benchmarks (tests/bench/bench_relay.py, bench_links.py).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import socket
import struct
import time
from typing import Any

from netem.netns import netns_path
from testbed.errors import TestbedError
from testbed.namespaces import inside

STAMP = struct.Struct("!dI")  # send time (monotonic), sequence number
CTX = mp.get_context("fork")
PORT = 9100
#: The payload of a full TCP segment and of a full UDP datagram in a 1500-byte IP packet.
TCP_PAYLOAD, UDP_PAYLOAD, IP_PACKET = 1448, 1472, 1500


class Worker:
    """A forked process running one function inside a namespace; `result()` waits for it."""

    def __init__(self, netns: str, fn: Any, *args: Any, nice: int = -10) -> None:
        self.queue: Any = CTX.Queue()
        self.what = f"{getattr(fn, '__name__', fn)} in {netns}"

        def run() -> None:
            # Endpoints get the relay's priority: on a shared 2-core host an endpoint that
            # waits for a CPU would be measured as link delay.
            with contextlib.suppress(OSError):
                os.nice(nice)
            try:
                with inside(netns_path(netns)):
                    self.queue.put(("ok", fn(*args)))
            except BaseException as err:  # reported to the parent, never lost
                self.queue.put(("error", f"{type(err).__name__}: {err}"))

        self.proc = CTX.Process(target=run, daemon=True)
        self.proc.start()

    def result(self, timeout_s: float = 60.0) -> Any:
        try:
            status, value = self.queue.get(timeout=timeout_s)
        except Exception:
            self.proc.kill()
            raise TestbedError(
                f"a measurement process ({self.what}) gave no result in {timeout_s:.0f} s"
            ) from None
        finally:
            self.proc.join(5)
        if status != "ok":
            raise TestbedError(f"a measurement process ({self.what}) failed: {value}")
        return value


def in_namespace(netns: str, fn: Any, *args: Any) -> Worker:
    """Start `fn(*args)` in a forked process inside namespace `netns` (a name in /run/netns)."""
    return Worker(netns, fn, *args)


def udp_receive(
    ready: Any, addr: str, port: int, duration_s: float, idle_s: float = 0.0
) -> list[tuple[float, float, int, int]]:
    """(receive time, send stamp, sequence, size) of each datagram, for up to `duration_s`;
    with `idle_s`, also stop once nothing has come for that long after the first datagram."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind((addr, port))
    sock.settimeout(0.05)
    ready.set()
    out: list[tuple[float, float, int, int]] = []
    end = time.monotonic() + duration_s
    buf = bytearray(65535)
    last = 0.0
    while (now := time.monotonic()) < end:
        if idle_s and out and now - last > idle_s:
            break
        try:
            n = sock.recv_into(buf)
        except TimeoutError:
            continue
        last = time.monotonic()
        sent, seq = STAMP.unpack_from(buf)
        out.append((last, sent, seq, n))
    sock.close()
    return out


#: getsockopt(IPPROTO_IP, IP_MTU) on a connected socket: the MTU of its route (linux/in.h).
IP_MTU = 14


def route_mtu(addr: str) -> int:
    """The MTU of this namespace's route to `addr` (a UE's air interface: 1456, room for
    GTP-U on N3)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect((addr, PORT))
        return int(sock.getsockopt(socket.IPPROTO_IP, IP_MTU))


def udp_send(addr: str, port: int, count: int, size: int, rate_bps: float) -> int:
    """Send `count` stamped datagrams of `size` bytes, paced at `rate_bps` of UDP payload."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    pad = bytes(max(0, size - STAMP.size))
    t0 = time.monotonic()
    for seq in range(count):
        due = t0 + seq * size * 8 / rate_bps
        wait = due - time.monotonic()
        if wait > 0.0005:
            time.sleep(wait)
        # A full local queue loses the datagram, as on a real host; it counts as lost.
        with contextlib.suppress(OSError):
            sock.sendto(STAMP.pack(time.monotonic(), seq) + pad, (addr, port))
    sock.close()
    return count


def tcp_receive(ready: Any, addr: str, port: int, duration_s: float) -> list[tuple[float, int]]:
    """(time, bytes so far) after each recv, for `duration_s` after the connection opens."""
    server = socket.create_server((addr, port))
    server.settimeout(10)
    ready.set()
    conn, _ = server.accept()
    conn.settimeout(1.0)
    buf = bytearray(1 << 20)
    marks: list[tuple[float, int]] = []
    total = 0
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        try:
            n = conn.recv_into(buf)
        except TimeoutError:
            continue
        if n == 0:
            break
        total += n
        marks.append((time.monotonic(), total))
    conn.close()
    server.close()
    return marks


def tcp_send(addr: str, port: int, duration_s: float) -> int:
    """Send as fast as TCP lets us for `duration_s`; returns the bytes sent."""
    sock = socket.create_connection((addr, port), timeout=5)
    chunk = bytes(1 << 20)
    end = time.monotonic() + duration_s
    sent = 0
    with contextlib.suppress(OSError):
        while time.monotonic() < end:
            sent += sock.send(chunk)
    sock.close()
    return sent


def goodput_bps(marks: list[tuple[float, int]], start_s: float, end_s: float) -> float:
    """Goodput between `start_s` and `end_s` after the first mark, from (time, total) marks."""
    if not marks:
        return 0.0
    first = marks[0][0]
    window = [m for m in marks if first + start_s <= m[0] <= first + end_s]
    if len(window) < 2 or window[-1][0] <= window[0][0]:
        return 0.0
    return (window[-1][1] - window[0][1]) * 8 / (window[-1][0] - window[0][0])


def udp_stream(
    src_ns: str, dst_ns: str, addr: str, count: int, size: int, rate_bps: float, tail_s: float
) -> list[tuple[float, float, int, int]]:
    """Send `count` datagrams src -> dst and return what arrived (see `udp_receive`)."""
    ready = CTX.Event()
    duration = count * size * 8 / rate_bps
    receiver = in_namespace(dst_ns, udp_receive, ready, addr, PORT, duration + tail_s + 2, tail_s)
    if not ready.wait(5):
        raise TestbedError(f"the UDP receiver in {dst_ns} did not start")
    in_namespace(src_ns, udp_send, addr, PORT, count, size, rate_bps).result(duration + 30)
    return receiver.result(duration + tail_s + 30)


def tcp_goodput(src_ns: str, dst_ns: str, addr: str, seconds: float, warm_s: float) -> float:
    """Steady-state TCP goodput src -> dst (bit/s), skipping the first `warm_s`."""
    ready = CTX.Event()
    receiver = in_namespace(dst_ns, tcp_receive, ready, addr, PORT, seconds + 0.5)
    if not ready.wait(5):
        raise TestbedError(f"the TCP receiver in {dst_ns} did not start")
    sender = in_namespace(src_ns, tcp_send, addr, PORT, seconds)
    marks = receiver.result(seconds + 30)
    sender.result(30)
    return goodput_bps(marks, warm_s, seconds - 0.05)


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]
