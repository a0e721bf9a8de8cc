"""The cross-traffic generator's processes (`python -m nodes.traffic.gen`) between two network
namespaces joined by a veth pair, shaped by tbf to 20 Mbit/s on the sender's side, checked
against what the shaper must give and against iperf3 (a generator we did not write) through
the same shaper.

What the shaper gives: tbf counts whole frames. A 1200-byte UDP payload is a 1242-byte frame
(+ 8 UDP, 20 IP, 14 Ethernet), so 20 Mbit/s of frames carries 19.32 Mbit/s of payload, and
a 30 Mbit/s CBR flow loses 1 - 19.32/30 = 35.6% of its datagrams; a TCP segment of MSS 1448
is a 1514-byte frame (+ 12 timestamp option, 20 TCP, 20 IP, 14 Ethernet): 19.13 Mbit/s of
goodput. A full tbf queue (`latency 50ms`: 50 ms of rate plus the 4 kB burst) delays each
datagram by about 51.6 ms.
"""

from __future__ import annotations

import json
import secrets
import selectors
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from nodes.traffic.flows import SAMPLE_KEYS

pytestmark = [pytest.mark.root, pytest.mark.alone]

REPO = Path(__file__).resolve().parents[1]
RATE_BPS = 20_000_000
UDP_SIZE = 1200
UDP_GOODPUT_BPS = RATE_BPS * UDP_SIZE / (UDP_SIZE + 42)
ETH_IP_TCP_TS = 14 + 20 + 20 + 12  # per segment on the wire, besides its MSS of payload


@dataclass(frozen=True)
class Pair:
    """Two namespaces, `a` (10.77.0.1, the sender's: its egress is shaped) and `b`
    (10.77.0.2), joined by a veth pair whose ends carry the namespaces' names."""

    a: str
    b: str
    addr_a: str = "10.77.0.1"
    addr_b: str = "10.77.0.2"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


def _netns() -> set[str]:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return {line.split()[0] for line in out.splitlines() if line.strip()}


@pytest.fixture
def pair() -> Iterator[Pair]:
    suffix = secrets.token_hex(3)
    p = Pair(a=f"eltg{suffix}a", b=f"eltg{suffix}b")
    try:
        _ip("netns", "add", p.a)
        _ip("netns", "add", p.b)
        _ip("link", "add", p.a, "netns", p.a, "type", "veth", "peer", "name", p.b, "netns", p.b)
        for ns, addr in ((p.a, p.addr_a), (p.b, p.addr_b)):
            _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", ns)
            _ip("-n", ns, "link", "set", ns, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
        shaper = ["rate", "20mbit", "burst", "32kbit", "latency", "50ms"]
        subprocess.run(
            ["tc", "-n", p.a, "qdisc", "add", "dev", p.a, "root", "tbf", *shaper],
            check=True,
            capture_output=True,
            text=True,
        )
        yield p
    finally:
        for ns in (p.a, p.b):  # the veth goes with its namespace
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
    left = {p.a, p.b} & _netns()
    assert not left, f"namespaces left behind: {left}"


def _gen(ns: str, *args: str) -> list[str]:
    return ["ip", "netns", "exec", ns, sys.executable, "-m", "nodes.traffic.gen", *args]


class Receiver:
    """A receiving generator in a namespace, started and waited for (its ready line)."""

    def __init__(self, ns: str, kind: str, tmp: Path) -> None:
        self.stats, self.samples = tmp / f"recv-{kind}.json", tmp / f"recv-{kind}.jsonl"
        cmd = _gen(ns, "recv", "--kind", kind, "--port", "0", "--die-with-parent")
        cmd += ["--stats", str(self.stats), "--samples", str(self.samples)]
        self.proc = subprocess.Popen(
            cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        assert self.proc.stdout is not None
        with selectors.DefaultSelector() as sel:
            sel.register(self.proc.stdout, selectors.EVENT_READ)
            line = self.proc.stdout.readline() if sel.select(15) else ""
        if not line:
            self.proc.kill()
            pytest.fail(f"receiver not ready: {self.proc.communicate()[1]}")
        self.ready = json.loads(line)
        self.port = int(self.ready["port"])

    def stop(self) -> dict[str, Any]:
        """SIGTERM; its stats once it has exited."""
        self.proc.send_signal(signal.SIGTERM)
        _, err = self.proc.communicate(timeout=10)
        assert self.proc.returncode == 0, err
        return json.loads(self.stats.read_text())

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


def _send(pair: Pair, port: int, tmp: Path, kind: str, *args: str) -> dict[str, Any]:
    """Run a sender from a to b for its --duration; its stats."""
    stats = tmp / f"send-{kind}.json"
    cmd = _gen(pair.a, "send", "--kind", kind, "--to", pair.addr_b, "--port", str(port))
    cmd += ["--stats", str(stats), "--samples", str(tmp / f"send-{kind}.jsonl"), *args]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.splitlines()[0])["event"] == "ready"
    return json.loads(stats.read_text())


def _flow(pair: Pair, tmp: Path, kind: str, *args: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """One flow a -> b; (sender's stats, receiver's stats)."""
    recv = Receiver(pair.b, "tcp" if kind == "tcp" else "udp", tmp)
    try:
        sent = _send(pair, recv.port, tmp, kind, *args)
        time.sleep(0.2)  # what is still queued at the shaper arrives
        return sent, recv.stop()
    finally:
        recv.kill()


def _samples(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _cbr(pair: Pair, tmp: Path, seconds: float) -> tuple[dict[str, Any], dict[str, Any]]:
    return _flow(
        pair, tmp, "udp", "--rate", "30e6", "--size", str(UDP_SIZE), "--duration", str(seconds)
    )


@pytest.mark.measure
def test_cbr_udp_at_30mbit_through_a_20mbit_shaper(
    pair: Pair, tmp_path: Path, quiet_machine: float
) -> None:
    sent, got = _cbr(pair, tmp_path, 4)
    print(
        f"\nours, UDP CBR 30 Mbit/s: loss {got['loss']:.4f}, goodput {got['goodput_bps'] / 1e6:.2f}"
        f" Mbit/s, delay p50 {got['delay_p50_ms']:.1f} ms, rtt p50 {sent['rtt_p50_ms']:.1f} ms,"
        f" late {sent['late_packets']}, lag p95 {sent['lag_p95_ms']:.3f} ms"
    )
    # The sender kept its rate and schedule: nothing late, skipped or refused.
    assert sent["sent_bps"] == pytest.approx(30e6, rel=0.01)
    assert sent["packets_sent"] == pytest.approx(4 * 3125, abs=3)
    assert sent["late_packets"] < 0.01 * sent["packets_sent"]
    assert sent["skipped_packets"] == 0 and sent["send_blocked"] == 0
    assert sent["errors"] == {} and got["errors"] == {}
    # The shaper drops a third and delivers its rate's worth of payload.
    assert 0.25 <= got["loss"] <= 0.42
    assert got["loss"] == pytest.approx(1 - UDP_GOODPUT_BPS / 30e6, abs=0.03)
    assert got["goodput_bps"] == pytest.approx(UDP_GOODPUT_BPS, rel=0.05)
    # Every datagram is accounted for: the FIN told the receiver how many were sent.
    assert got["fins"] == 1 and got["expected"] == sent["packets_sent"]
    assert got["packets_received"] + got["lost"] == sent["packets_sent"]
    assert got["socket_drops"] == 0 and got["duplicates"] == 0
    # A full 50 ms tbf queue: the one-way delay and the RTT (echoes come back unshaped).
    assert 40 <= got["delay_p50_ms"] <= 65
    assert 40 <= sent["rtt_p50_ms"] <= 70 and sent["rtt_samples"] >= 40
    samples = _samples(tmp_path / "recv-udp.jsonl")
    assert all(list(s)[4:] == list(SAMPLE_KEYS[1:]) for s in samples)
    full = [s for s in samples if s["packets"] and s["t"] > 1.5 and s["bytes"] > 1e6]
    assert len(full) >= 4
    for s in full:  # steady state, interval by interval
        assert s["goodput_bps"] == pytest.approx(UDP_GOODPUT_BPS, rel=0.1)
        assert 40 <= s["delay_ms"] <= 65


def test_with_the_default_send_buffer_the_shaper_blocks_the_sender(
    pair: Pair, tmp_path: Path
) -> None:
    # --sndbuf 0: the shaper's queue holds more than the socket may, so the sender waits
    # instead of the shaper dropping; the sender says so (blocked, late), the receiver sees
    # no loss at the shaper's rate.
    args = ("--rate", "30e6", "--size", str(UDP_SIZE), "--duration", "2", "--sndbuf", "0")
    sent, got = _flow(pair, tmp_path, "udp", *args)
    assert sent["sndbuf"] < 1 << 20 and sent["send_blocked"] > 100
    assert sent["late_packets"] > 0.2 * sent["packets_sent"]
    assert sent["sent_bps"] == pytest.approx(UDP_GOODPUT_BPS, rel=0.1)
    assert got["loss"] == 0 and got["expected"] == sent["packets_sent"]


@pytest.mark.measure
def test_bulk_tcp_gets_the_shaped_rate(pair: Pair, tmp_path: Path, quiet_machine: float) -> None:
    sent, got = _flow(pair, tmp_path, "tcp", "--duration", "4")
    expected = RATE_BPS * sent["mss"] / (sent["mss"] + ETH_IP_TCP_TS)
    print(
        f"\nours, bulk TCP: goodput {got['goodput_bps'] / 1e6:.2f} Mbit/s (receiver),"
        f" {sent['goodput_bps'] / 1e6:.2f} (sender, acked), expected {expected / 1e6:.2f};"
        f" rtt p50 {sent['rtt_p50_ms']:.1f} ms, retransmits {sent['retransmits']}"
    )
    assert sent["mss"] == 1448  # TCP_INFO read at the right offset (1500 - 40 - 12)
    assert got["goodput_bps"] == pytest.approx(expected, rel=0.05)
    assert sent["goodput_bps"] == pytest.approx(got["goodput_bps"], rel=0.05)
    # bytes_acked (TCP_INFO at the sender's stop) against what the receiver read: apart by
    # no more than what was in flight (the window, at most the shaper's 129 kB queue).
    assert abs(sent["bytes_acked"] - got["bytes_received"]) <= 256 * 1024
    assert sent["rtt_p50_ms"] > 0 and sent["rtt_samples"] >= 100
    assert got["connections"] == 1 and sent["errors"] == {} and got["errors"] == {}
    samples = _samples(tmp_path / "send-tcp.jsonl")
    assert all(list(s)[4:] == list(SAMPLE_KEYS[1:]) for s in samples)
    assert all(s["rtt_ms"] is not None for s in samples)


def test_tcp_capped_at_a_rate_keeps_it(pair: Pair, tmp_path: Path) -> None:
    # 8 Mbit/s in 16 KiB writes (one every 16.4 ms), well under the shaper.
    sent, got = _flow(pair, tmp_path, "tcp", "--rate", "8e6", "--duration", "3")
    assert sent["sent_bps"] == pytest.approx(8e6, rel=0.03)
    assert got["goodput_bps"] == pytest.approx(8e6, rel=0.05)
    assert sent["skipped_packets"] == 0 and sent["late_packets"] <= 3
    assert sent["retransmits"] == 0  # the shaper's queue never filled


def test_onoff_udp_alternates_and_averages(pair: Pair, tmp_path: Path) -> None:
    # 10 Mbit/s (under the shaper) on for 0.5 s, off for 0.5 s: 5 Mbit/s on average.
    args = (
        "--rate",
        "10e6",
        "--on",
        "0.5",
        "--off",
        "0.5",
        "--duration",
        "3",
        "--interval",
        "0.25",
    )
    sent, got = _flow(pair, tmp_path, "onoff", *args)
    assert sent["packets_sent"] == 3 * 521  # ceil(0.5 s / 0.96 ms) per on period, 3 periods
    assert got["loss"] == 0 and got["lost"] == 0
    # Active time: the first datagram to the last, the last off period not included.
    assert got["active_s"] == pytest.approx(2.5, abs=0.05)
    assert got["goodput_bps"] == pytest.approx(10e6 * 1.5 / 2.5, rel=0.05)
    rates = [s["rate_bps"] for s in _samples(tmp_path / "send-onoff.jsonl")]
    assert max(rates) == pytest.approx(10e6, rel=0.05) and min(rates) == 0


def test_a_sender_without_receiver_reports_it_and_ends_cleanly(pair: Pair, tmp_path: Path) -> None:
    # UDP: the receiver's ICMP port unreachable fails later sends; counted, not fatal.
    sent = _send(pair, 9, tmp_path, "udp", "--rate", "1e6", "--duration", "1")
    assert any("refused" in e for e in sent["errors"]), sent["errors"]
    assert sent["packets_sent"] + sent["skipped_packets"] == pytest.approx(105, abs=2)
    # TCP: nothing listens; the sender gives up after --connect-timeout, exit 1, stats say why.
    stats = tmp_path / "tcp.json"
    cmd = _gen(pair.a, "send", "--kind", "tcp", "--to", pair.addr_b, "--port", "9")
    out = subprocess.run(
        [*cmd, "--connect-timeout", "0.5", "--stats", str(stats)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert out.returncode == 1
    assert list(json.loads(stats.read_text())["errors"]) == ["connect: Connection refused"]


def test_the_receiver_stops_on_sigterm_and_leaves_no_temp_file(pair: Pair, tmp_path: Path) -> None:
    recv = Receiver(pair.b, "udp", tmp_path)
    try:
        assert recv.ready["event"] == "ready" and recv.ready["role"] == "recv"
        t0 = time.monotonic()
        stats = recv.stop()
        assert time.monotonic() - t0 < 1  # woken by the signal, not by a poll timeout
    finally:
        recv.kill()
    assert stats["packets_received"] == 0 and stats["loss"] is None
    assert stats["goodput_bps"] is None and stats["errors"] == {}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["recv-udp.json", "recv-udp.jsonl"]


# --- against iperf3 ------------------------------------------------------------------------------

IPERF3 = shutil.which("iperf3")
needs_iperf3 = pytest.mark.skipif(
    IPERF3 is None, reason="iperf3 is not installed (Debian: apt-get install iperf3)"
)


def _iperf3(pair: Pair, *client_args: str) -> dict[str, Any]:
    """One iperf3 test a -> b (server in b for one test); the client's JSON."""
    assert IPERF3 is not None
    port = "5201"
    server = subprocess.Popen(
        ["ip", "netns", "exec", pair.b, IPERF3, "-s", "-1", "-p", port, "-B", pair.addr_b],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 10
        listening = ["ip", "netns", "exec", pair.b, "ss", "-Hltn", f"sport = :{port}"]
        while not subprocess.run(listening, capture_output=True, text=True).stdout.strip():
            assert time.monotonic() < deadline, "iperf3 server did not listen"
            time.sleep(0.05)
        out = subprocess.run(
            [
                "ip",
                "netns",
                "exec",
                pair.a,
                IPERF3,
                "-c",
                pair.addr_b,
                "-p",
                port,
                "-J",
                *client_args,
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert out.returncode == 0, out.stdout + out.stderr
        return json.loads(out.stdout)
    finally:
        server.kill()
        server.communicate()


@pytest.mark.measure
@needs_iperf3
def test_udp_loss_matches_iperf3(pair: Pair, tmp_path: Path, quiet_machine: float) -> None:
    _, ours = _cbr(pair, tmp_path, 3)
    # -w 2M: iperf3's default socket buffer is smaller than the shaper's queue, so its sends
    # would block (no loss, 19 Mbit/s sent) instead of being dropped by tbf (see DGRAM_BUF_BYTES
    # in nodes.traffic.gen).
    theirs = _iperf3(pair, "-u", "-b", "30M", "-l", str(UDP_SIZE), "-w", "2M", "-t", "3")
    received = theirs["end"]["sum_received"]
    their_loss = received["lost_percent"] / 100
    print(
        f"\nUDP CBR 30 Mbit/s, loss: ours {ours['loss']:.4f}, iperf3 {their_loss:.4f};"
        f" goodput ours {ours['goodput_bps'] / 1e6:.2f}, iperf3"
        f" {received['bits_per_second'] / 1e6:.2f} Mbit/s"
    )
    assert ours["loss"] == pytest.approx(their_loss, abs=0.03)
    assert ours["goodput_bps"] == pytest.approx(received["bits_per_second"], rel=0.05)


@pytest.mark.measure
@needs_iperf3
def test_tcp_rate_matches_iperf3(pair: Pair, tmp_path: Path, quiet_machine: float) -> None:
    _, ours = _flow(pair, tmp_path, "tcp", "--duration", "3")
    theirs = _iperf3(pair, "-t", "3")["end"]["sum_received"]["bits_per_second"]
    print(
        f"\nbulk TCP goodput: ours {ours['goodput_bps'] / 1e6:.2f},"
        f" iperf3 {theirs / 1e6:.2f} Mbit/s"
    )
    assert ours["goodput_bps"] == pytest.approx(theirs, rel=0.05)
