"""Relay stages with a fake clock (no root): exact delay, jitter, rate, queues, loss, traces.

The last tests run the relay's event loop over SEQPACKET socket pairs standing in for the two
TUN ends, so the control protocol and the loop are checked without namespaces.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import socket
import statistics
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from netem.profile import GilbertElliott, LinkProfile
from netem.relay.direction import build_pipeline
from netem.relay.process import Relay
from netem.stages import (
    Delay,
    GilbertElliottLoss,
    Outage,
    Pipeline,
    RandomLoss,
    Rate,
    TraceLink,
    jitter_sd,
)
from netem.traces import load_trace, parse_csv, parse_mahimahi


def packet(seq: int, size: int = 100) -> bytes:
    return seq.to_bytes(4, "big") + bytes(size - 4)


def seq_of(p: bytes) -> int:
    return int.from_bytes(p[:4], "big")


def run_clock(stage, until: float, step: float = 1e-5) -> list[tuple[float, bytes]]:
    """Advance a fake clock event by event; return (time, packet) for each delivery."""
    out: list[tuple[float, bytes]] = []
    while True:
        due = stage.next_due()
        if due is None or due > until:
            return out
        out += [(due, p) for p in stage.pop_ready(due)]


# -- delay ------------------------------------------------------------------------------------


def test_delay_is_exact() -> None:
    d = Delay(delay_s=0.020)
    d.push(packet(1), 1.0)
    assert d.next_due() == pytest.approx(1.020, abs=1e-12)
    assert d.pop_ready(1.0199) == []
    assert [seq_of(p) for p in d.pop_ready(1.020)] == [1]
    assert d.next_due() is None


def test_pipeline_hands_packets_on_at_their_due_time_not_when_polled() -> None:
    pipe = build_pipeline(LinkProfile(rate_bps=1e6, delay_s=0.020))
    pipe.push(packet(1, 1250), 0.0)  # 10 ms on the wire at 1 Mbit/s
    assert pipe.pop_ready(0.0) == []
    assert pipe.next_due() == pytest.approx(0.010)
    # Not yet in the last stage, but it may leave 20 ms after the hand-off: a departure
    # the relay must wake for on time, not lazily.
    assert pipe.next_exit() == pytest.approx(0.030, abs=1e-12)
    # Polled 5 ms late: the packet still entered the delay stage at 10 ms.
    assert pipe.pop_ready(0.015) == []
    assert pipe.next_due() == pytest.approx(0.030, abs=1e-12)
    assert pipe.next_exit() == pytest.approx(0.030, abs=1e-12)
    assert len(pipe.pop_ready(0.030)) == 1


def test_a_delayed_packet_s_departure_is_a_deadline_from_the_moment_it_arrives() -> None:
    pipe = build_pipeline(LinkProfile(delay_s=0.010))
    pipe.push(packet(1), 1.0)
    assert pipe.next_exit() == pytest.approx(1.010, abs=1e-12)
    assert pipe.deadlines()[1] == pytest.approx(1.010, abs=1e-12)


@pytest.mark.parametrize("distribution", ["normal", "uniform", "pareto"])
def test_jitter_has_the_configured_spread(distribution: str) -> None:
    profile = LinkProfile(delay_s=0.050, jitter_s=0.005, jitter_distribution=distribution)
    d = Delay(seed=7)
    d.configure(profile)
    delays = []
    for i in range(20000):
        t = float(i)  # packets 1 s apart: the order rule never holds one back
        d.push(packet(i), t)
        delays.append(d.next_due() - t)
        assert len(d.pop_ready(t + 1.0)) == 1
    assert statistics.fmean(delays) == pytest.approx(0.050, abs=0.0002)
    assert statistics.stdev(delays) == pytest.approx(jitter_sd(profile), rel=0.05)
    if distribution == "uniform":
        assert min(delays) >= 0.045 and max(delays) <= 0.055
    if distribution == "pareto":  # heavy right tail, bounded left tail
        assert max(delays) - 0.050 > 4 * 0.005 > 0.050 - min(delays)


def test_jitter_keeps_order_unless_reorder() -> None:
    def deliveries(reorder: bool) -> list[tuple[float, int]]:
        d = Delay(delay_s=0.010, jitter_s=0.005, reorder=reorder, seed=3)
        got: list[tuple[float, int]] = []
        for i in range(2000):  # one packet per ms, jitter 5 ms: arrivals would overtake
            t = i * 0.001
            got += [(due, seq_of(p)) for due, p in run_clock(d, t)]
            d.push(packet(i), t)
        got += [(due, seq_of(p)) for due, p in run_clock(d, math.inf)]
        return got

    kept = deliveries(reorder=False)
    assert [s for _, s in kept] == list(range(2000))
    assert all(t1 <= t2 for (t1, _), (t2, _) in itertools.pairwise(kept))
    mixed = [s for _, s in deliveries(reorder=True)]
    assert sorted(mixed) == list(range(2000))
    assert sum(a > b for a, b in itertools.pairwise(mixed)) > 100


def test_negative_jitter_draws_are_clamped_to_zero_delay() -> None:
    d = Delay(delay_s=0.001, jitter_s=0.010, seed=1, reorder=True)
    for i in range(1000):
        d.push(packet(i), 5.0)
    assert d.next_due() == 5.0


# -- rate and queues --------------------------------------------------------------------------


def test_rate_serialises_back_to_back_and_from_idle() -> None:
    r = Rate(rate_bps=8e6)  # 1 byte per µs
    for i in range(10):
        r.push(packet(i, 1000), 0.0)
    times = [t for t, _ in run_clock(r, math.inf)]
    assert times == pytest.approx([0.001 * (k + 1) for k in range(10)], abs=1e-12)
    r.push(packet(99, 500), 1.0)  # idle link: starts at arrival
    assert r.next_due() == pytest.approx(1.0005, abs=1e-12)


def test_rate_drop_tail_by_packets() -> None:
    r = Rate(rate_bps=8e6, queue_packets=5)
    for i in range(10):
        r.push(packet(i, 1000), 0.0)
    assert [seq_of(p) for _, p in run_clock(r, math.inf)] == [0, 1, 2, 3, 4]
    assert r.counters.dropped_packets == {"queue_full": 5}
    assert r.counters.dropped_bytes == {"queue_full": 5000}


def test_rate_drop_tail_by_time() -> None:
    r = Rate(rate_bps=8e6, queue_time_s=0.0035)  # packet k would wait k ms
    for i in range(10):
        r.push(packet(i, 1000), 0.0)
    assert r.counters.dropped_packets == {"queue_time": 6}
    assert len(run_clock(r, math.inf)) == 4


def test_rate_goodput_over_a_second() -> None:
    pipe = build_pipeline(LinkProfile(rate_bps=10e6, queue_packets=10_000))
    t, sent = 0.0, 0
    while t < 1.0:  # offer 20 Mbit/s
        pipe.push(packet(sent, 1250), t)
        sent += 1
        t += 0.0005
    delivered = run_clock(pipe, 1.0)
    bits = sum(len(p) for _, p in delivered) * 8
    assert bits == pytest.approx(10e6, rel=0.002)


# -- loss -------------------------------------------------------------------------------------


@pytest.mark.parametrize("loss", [0.01, 0.05, 0.2])
def test_random_loss_rate(loss: float) -> None:
    stage = RandomLoss(loss, seed=11)
    n = 100_000
    for i in range(n):
        stage.push(b"x", float(i))
    dropped = stage.counters.dropped_packets.get("loss", 0)
    assert dropped / n == pytest.approx(loss, abs=0.005)
    assert len(stage.pop_ready(math.inf)) == n - dropped


def test_gilbert_elliott_stationary_loss_and_bursts() -> None:
    model = GilbertElliott(p=0.01, r=0.1, good_loss=0.0, bad_loss=1.0)
    stage = GilbertElliottLoss(model, seed=5)
    n = 300_000
    lost = []
    for _ in range(n):
        before = stage.counters.dropped
        stage.push(b"x", 0.0)
        lost.append(stage.counters.dropped > before)
    rate = sum(lost) / n
    assert rate == pytest.approx(model.stationary_loss(), abs=0.005)
    bursts = sum(1 for a, b in zip([False, *lost], lost, strict=False) if b and not a)
    assert sum(lost) / bursts == pytest.approx(1 / model.r, rel=0.1)  # mean burst length


def test_loss_model_from_profile_replaces_random_loss() -> None:
    pipe = build_pipeline(
        LinkProfile(loss=0.5, gilbert_elliott=GilbertElliott(p=0.0, r=1.0)), seed=1
    )
    for i in range(1000):
        pipe.push(packet(i), 0.0)
    assert len(pipe.pop_ready(0.0)) == 1000  # GE stays in the lossless good state


def test_outage_drops_only_while_on() -> None:
    gate = Outage()
    gate.start(1.0, 2.0)
    for t in (0.5, 1.0, 2.9, 3.0, 3.5):
        gate.push(packet(int(t * 10)), t)
    assert [seq_of(p) for p in gate.pop_ready(10.0)] == [5, 30, 35]
    assert gate.counters.dropped_packets == {"outage": 2}


# -- traces -----------------------------------------------------------------------------------


def test_mahimahi_opportunities_deliver_1500_bytes_each_and_loop() -> None:
    trace = parse_mahimahi("1\n1\n3\n")
    link = TraceLink()
    link.play(trace, 10.0, loop=True)
    for i in range(5):
        link.push(packet(i, 1500), 10.0)
    times = [round(t - 10.0, 6) for t, _ in run_clock(link, math.inf)]
    assert times == [0.001, 0.001, 0.003, 0.004, 0.004]


def test_mahimahi_small_and_large_packets() -> None:
    link = TraceLink()
    link.play(parse_mahimahi("\n".join(str(ms) for ms in range(1, 11))), 0.0, loop=False)
    for i in range(3):
        link.push(packet(i, 500), 0.0)  # three fit one opportunity
    link.push(packet(3, 4000), 0.0)  # needs three opportunities
    got = [(round(t, 6), seq_of(p)) for t, p in run_clock(link, math.inf)]
    assert got == [(0.001, 0), (0.001, 1), (0.001, 2), (0.004, 3)]


def test_trace_end_gives_the_rate_back_to_the_profile() -> None:
    pipe = build_pipeline(LinkProfile(rate_bps=12e6))  # 1 ms per 1500 B
    pipe.play_trace(parse_mahimahi("10\n20\n"), 0.0, loop=False)
    for i in range(4):
        pipe.push(packet(i, 1500), 0.0)
    times = [round(t, 6) for t, _ in run_clock(pipe, math.inf)]
    # Two opportunities, then the trace ends at 20 ms and the rest leaves at once.
    assert times == [0.010, 0.020, 0.020, 0.020]
    pipe.push(packet(9, 1500), 1.0)
    assert pipe.pop_ready(1.0) == []
    assert pipe.next_due() == pytest.approx(1.001)  # the profile's 12 Mbit/s again


def test_csv_trace_rates() -> None:
    trace = parse_csv("time_s,mbit\n0,12\n1,0\n2,24\n")
    assert trace.duration_s == 3.0
    assert trace.mean_rate_bps() == pytest.approx(12e6)
    link = TraceLink()
    link.play(trace, 0.0, loop=True)
    for i in range(10_000):
        link.push(packet(i, 1500), 0.0)
    got = [t for t, _ in run_clock(link, 3.0)]
    assert sum(1 for t in got if t <= 1.0) == 1000
    assert sum(1 for t in got if 1.0 < t <= 2.0) == 0
    assert sum(1 for t in got if 2.0 < t <= 3.0) == 2000


def test_load_trace_reports_the_bad_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.trace"
    bad.write_text("1\n2\nthree\n")
    with pytest.raises(ValueError, match=r"bad.trace line 3: expected an integer"):
        load_trace(bad)
    bad.write_text("5\n4\n")
    with pytest.raises(ValueError, match="line 2: timestamp 4 is earlier"):
        load_trace(bad)
    csv = tmp_path / "bw.csv"
    csv.write_text("time_s,mbit\n0,10\n1,-3\n")
    with pytest.raises(ValueError, match=r"bw.csv line 3: rate -3.0 Mbit/s is negative"):
        load_trace(csv)
    csv.write_text("0,10\n0,5\n")
    with pytest.raises(ValueError, match=r"line 2: time 0\.0 s is not after"):
        load_trace(csv)
    with pytest.raises(ValueError, match="cannot read"):
        load_trace(tmp_path / "missing.csv")
    good = tmp_path / "ok.csv"
    good.write_text("# comment\n0,10\n")
    assert load_trace(good).mean_rate_bps() == pytest.approx(10e6)


# -- in-place change --------------------------------------------------------------------------


def test_apply_keeps_queued_packets_and_order() -> None:
    pipe = build_pipeline(LinkProfile(delay_s=0.100))
    for i in range(5):
        pipe.push(packet(i), i * 0.001)
        assert pipe.pop_ready(i * 0.001) == []
    pipe.apply(LinkProfile(delay_s=0.010))
    pipe.push(packet(5), 0.010)  # would be due at 20 ms, but waits for its predecessors
    got = [(round(t, 6), seq_of(p)) for t, p in run_clock(pipe, math.inf)]
    assert got == [(0.100, 0), (0.101, 1), (0.102, 2), (0.103, 3), (0.104, 4), (0.104, 5)]
    assert pipe.snapshot()["total"]["packets_out"] == 6


def test_apply_changes_rate_of_the_queue_in_place() -> None:
    pipe = build_pipeline(LinkProfile(rate_bps=8e6))
    for i in range(4):
        pipe.push(packet(i, 1000), 0.0)
    pipe.apply(LinkProfile(rate_bps=16e6))  # head keeps its start; the rest go twice as fast
    times = [round(t, 7) for t, _ in run_clock(pipe, math.inf)]
    assert times == [0.0005, 0.001, 0.0015, 0.002]
    assert pipe.stage("rate").counters.dropped == 0


def test_bad_profile_is_named() -> None:
    with pytest.raises(ValueError, match=r"`loss` = 1.5: must be a fraction"):
        build_pipeline(LinkProfile(loss=1.5))
    with pytest.raises(ValueError, match="jitter_distribution"):
        build_pipeline(LinkProfile(jitter_distribution="gamma"))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="queue_packets"):
        build_pipeline(LinkProfile(queue_packets=0))


def test_same_seed_same_draws() -> None:
    def drops(seed: int) -> list[int]:
        pipe = build_pipeline(LinkProfile(loss=0.3), seed=seed)
        for i in range(200):
            pipe.push(packet(i), 0.0)
        return [seq_of(p) for p in pipe.pop_ready(0.0)]

    assert drops(1) == drops(1) != drops(2)


# -- the relay loop over socket pairs ---------------------------------------------------------


@contextlib.contextmanager
def socket_relay(
    tmp_path: Path, uplink: Pipeline, downlink: Pipeline, timeout_s: float | None = None
) -> Iterator[tuple[Relay, socket.socket, socket.socket, str]]:
    """A running Relay whose TUN ends are SEQPACKET socket pairs (one datagram = one packet):
    (relay, the a-side app end, the b-side app end, its control socket's path)."""
    a_app, a_relay = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    b_app, b_relay = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for s in (a_relay, b_relay):
        s.setblocking(False)
    if timeout_s is not None:
        for s in (a_app, b_app):
            s.settimeout(timeout_s)
    control = str(tmp_path / "c.sock")
    relay = Relay(a_relay.fileno(), b_relay.fileno(), uplink, downlink, control_path=control)
    thread = threading.Thread(target=relay.run, daemon=True)
    thread.start()
    try:
        yield relay, a_app, b_app, control
    finally:
        relay.stop()
        thread.join(5)
        relay.close()
        for s in (a_app, a_relay, b_app, b_relay):
            s.close()


@pytest.fixture
def fake_relay(tmp_path: Path) -> Iterator[tuple[Relay, socket.socket, socket.socket, str]]:
    with socket_relay(
        tmp_path,
        build_pipeline(LinkProfile(delay_s=0.020)),
        build_pipeline(LinkProfile()),
    ) as ends:
        yield ends


def ask(path: str, message: dict) -> dict:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(2)
        s.connect(path)
        s.sendall((json.dumps(message) + "\n").encode())
        data = b""
        while not data.endswith(b"\n"):
            data += s.recv(65536)
    return json.loads(data)


def test_relay_loop_delays_and_is_reconfigured_live(fake_relay) -> None:
    _, a_app, b_app, control = fake_relay
    b_app.settimeout(2)
    a_app.settimeout(2)
    t0 = time.monotonic()
    a_app.send(b"hello")
    assert b_app.recv(100) == b"hello"
    # Never early; the slack allows for a loaded 2-core host (precision: bench_relay.py).
    assert 0.020 <= time.monotonic() - t0 < 0.035
    b_app.send(b"back")  # downlink has no delay
    assert a_app.recv(100) == b"back"

    reply = ask(control, {"op": "set", "direction": "uplink", "profile": {"delay_s": 0.050}})
    assert reply["ok"] and reply["profiles"]["uplink"]["delay_s"] == 0.050
    t0 = time.monotonic()
    a_app.send(b"slow")
    assert b_app.recv(100) == b"slow"
    assert 0.050 <= time.monotonic() - t0 < 0.065
    counters = ask(control, {"op": "counters"})
    assert counters["uplink"]["total"]["packets_out"] == 2
    assert counters["downlink"]["total"]["bytes_out"] == 4


def test_relay_control_errors_are_clear(fake_relay, tmp_path: Path) -> None:
    _, _, _, control = fake_relay
    assert ask(control, {"op": "ping"})["ok"]
    cases = [
        ({"op": "jump"}, "unknown op 'jump'"),
        ({"op": "set", "direction": "up", "profile": {}}, "direction must be"),
        ({"op": "set", "direction": "uplink", "profile": {"delai_s": 1}}, "unknown profile"),
        ({"op": "set", "direction": "both", "profile": {"loss": 7}}, "`loss` = 7: must be"),
        ({"op": "outage", "seconds": -1}, "outage needs `seconds`"),
        ({"op": "trace", "direction": "uplink", "path": str(tmp_path / "no.csv")}, "cannot read"),
    ]
    for message, error in cases:
        reply = ask(control, message)
        assert not reply["ok"] and error in reply["error"], reply
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(2)
        s.connect(control)
        s.sendall(b"not json\n")
        assert "not JSON" in json.loads(s.recv(65536))["error"]
    # The relay kept both profiles as they were.
    assert ask(control, {"op": "counters"})["uplink"]["profile"]["loss"] == 0.0


def test_one_profile_check_for_both_backends() -> None:
    """`netem.profile.check_profile` is what the relay, its control protocol and the tc
    planner all run; the backends differ only in the smallest rate they can keep."""
    from netem.errors import ProfileError
    from netem.profile import check_profile
    from netem.tc.plan import leaf_for

    slow = LinkProfile(rate_bps=4.0)
    check_profile(slow)  # the relay's rate stage keeps 4 bit/s
    with pytest.raises(ProfileError, match=r"`rate_bps` = 4\.0: must be a rate of at least 8"):
        check_profile(slow, "tc")
    with pytest.raises(ProfileError, match="rate_bps"):
        leaf_for(slow)  # the tc planner runs the same check
    for bad in (
        LinkProfile(queue_packets=1.5),  # type: ignore[arg-type]
        LinkProfile(delay_s=math.inf),
        LinkProfile(loss=-0.1),
    ):
        for backend in ("tc", "userspace"):
            with pytest.raises(ProfileError):
                check_profile(bad, backend)  # type: ignore[arg-type]


# -- the relay's wake-up timer ----------------------------------------------------------------


def test_wake_timer_learns_a_slow_guest_timer_and_sleeps_short_of_the_departure() -> None:
    from netem.relay.timer import EARLY_MAX_S, WakeTimer

    timer = WakeTimer()

    # A guest timer 5% slow plus a fixed 0.1 ms: a 10 ms select ends 0.6 ms late.
    def sleep(asked: float) -> float:
        return asked * 1.05 + 0.0001

    for _ in range(200):
        timer.observe(0.0001, sleep(0.0001))  # short sleeps teach the fixed part
        timer.observe(0.010, sleep(0.010))  # long ones the stretch
    assert timer.early_s == pytest.approx(0.0001, abs=0.00003)
    assert timer.stretch == pytest.approx(0.05, abs=0.005)
    # A packet due in 10 ms: the first sleep ends before it is due, with room to spin.
    now, due = 100.0, 100.010
    first = timer.timeout(None, due, now)
    assert first is not None and now + sleep(first) < due - 0.0002
    # What is left is slept again, then polled; never slept past.
    now += sleep(first)
    second = timer.timeout(None, due, now)
    assert second is not None and (second == 0.0 or now + sleep(second) < due)
    # Without a stretch (a host whose timers keep time) the plan is the plain early wake.
    plain = WakeTimer()
    assert plain.timeout(None, 1.010, 1.0) == pytest.approx(0.010 - plain.early_s)
    assert plain.early_s <= EARLY_MAX_S


def test_the_relay_s_operations_table_makes_its_docstring_and_its_unknown_op_error(
    fake_relay,
) -> None:
    """One table (`netem.relay.control.OPS`): each entry's usage is a line of the module's
    docstring, and the error for an unknown op lists exactly its keys, in its order."""
    from netem.relay import control as protocol

    assert list(protocol.OPS)[:3] == ["ping", "set", "outage"]  # the table is the real one
    for name, op in protocol.OPS.items():
        assert f'{{"op": "{name}"' in op.usage
        assert op.usage.splitlines()[0] in (protocol.__doc__ or "")
    _, _, _, control = fake_relay
    reply = ask(control, {"op": "jump"})
    assert reply["error"].endswith("allowed: " + ", ".join(protocol.OPS))
