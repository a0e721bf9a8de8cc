"""The cross-traffic generator's logic (`nodes.traffic.flows`) on a fake clock: schedules that
do not drift, a pacer that counts late and skipped packets, loss from sequence gaps with
reordering and duplicates, goodput over the active time, interval samples, delay quantiles,
and `struct tcp_info` read at the kernel's offsets. The processes themselves run through a
shaped veth in tests/test_traffic_root.py."""

from __future__ import annotations

import random
import struct

import pytest

from nodes.traffic import gen
from nodes.traffic.flows import (
    DATA,
    DUPLICATE,
    FIN,
    HEADER_SIZE,
    MS,
    NEW,
    NS,
    REORDERED,
    SAMPLE_KEYS,
    STALE,
    Cbr,
    Histogram,
    OnOff,
    Pacer,
    RecvAccount,
    SendAccount,
    SeqTracker,
    Ticker,
    nearest_rank,
    pack_header,
    parse_tcp_info,
    unpack_header,
)

# --- the header --------------------------------------------------------------------------------


def test_header_round_trips_and_leaves_the_payload_alone() -> None:
    buf = bytearray(b"\xaa" * 100)
    pack_header(buf, DATA, 0xDEADBEEF, 2**40 + 7, 123_456_789_012)
    assert unpack_header(buf, len(buf)) == (DATA, 0xDEADBEEF, 2**40 + 7, 123_456_789_012)
    assert buf[HEADER_SIZE:] == b"\xaa" * (100 - HEADER_SIZE)
    assert HEADER_SIZE == 24


def test_header_refuses_what_is_not_ours() -> None:
    buf = bytearray(HEADER_SIZE)
    pack_header(buf, FIN, 1, 2, 3)
    assert unpack_header(buf, HEADER_SIZE - 1) is None  # too short
    assert unpack_header(b"XX" + bytes(buf[2:]), HEADER_SIZE) is None  # magic
    assert unpack_header(bytes(buf[:2]) + b"\x09" + bytes(buf[3:]), HEADER_SIZE) is None  # version
    assert unpack_header(bytes(buf[:3]) + b"\x07" + bytes(buf[4:]), HEADER_SIZE) is None  # type
    assert unpack_header(buf, HEADER_SIZE) == (FIN, 1, 2, 3)


# --- schedules ---------------------------------------------------------------------------------


def test_cbr_sends_a_packet_every_size_times_8_over_rate_without_drift() -> None:
    cbr = Cbr(30_000_000, 1200)  # the 30 Mbit/s, 1200-byte flow of the root test
    assert cbr.interval_ns == 320_000
    assert [cbr.offset_ns(k) for k in range(4)] == [0, 320_000, 640_000, 960_000]
    assert cbr.offset_ns(3_125_000) == 1000 * NS  # a million and more steps: still exact
    # An interval that is not a whole number of ns: each offset is rounded down on its own,
    # never accumulated, so every third packet is exactly on the second.
    slow = Cbr(3, 1)
    assert [slow.offset_ns(k) for k in range(4)] == [0, 2_666_666_666, 5_333_333_333, 8 * NS]
    assert slow.offset_ns(3 * 10**9) == 8 * 10**18


@pytest.mark.parametrize(("rate", "size"), [(0, 100), (-5, 100), (1000, 0)])
def test_cbr_refuses_a_rate_or_size_that_is_not_positive(rate: int, size: int) -> None:
    with pytest.raises(ValueError):
        Cbr(rate, size)


def test_onoff_sends_cbr_while_on_and_nothing_while_off() -> None:
    flow = OnOff(8000, 100, on_s=0.25, off_s=0.75)  # a packet every 0.1 s while on
    assert flow.per_burst == 3  # 0.0, 0.1, 0.2; 0.3 would be past the end of the on period
    offsets = [flow.offset_ns(k) for k in range(9)]
    assert offsets == [
        0,
        NS // 10,
        2 * NS // 10,
        NS,
        NS + NS // 10,
        NS + 2 * NS // 10,
        2 * NS,
        2 * NS + NS // 10,
        2 * NS + 2 * NS // 10,
    ]
    assert all((o % NS) < 250 * MS for o in offsets)  # nothing in an off period
    # The mean rate over many cycles: 3 packets of 800 bits a second.
    k = 3 * 1000
    assert flow.offset_ns(k) == 1000 * NS
    assert k * flow.size * 8 / (flow.offset_ns(k) / NS) == pytest.approx(2400)


def test_onoff_counts_packets_per_burst_at_the_edge_and_never_goes_back() -> None:
    assert OnOff(8000, 100, on_s=0.3, off_s=0.2).per_burst == 3  # 0.3 is the next period's
    assert OnOff(8000, 100, on_s=0.31, off_s=0.2).per_burst == 4
    assert OnOff(8000, 100, on_s=0.01, off_s=1).per_burst == 1  # a burst is at least a packet
    # Off 0 with an on period of whole intervals (5 x 9.6 ms) is plain CBR; with 0.04 s it
    # would not be: each burst starts a packet at its very start.
    flow = OnOff(1_000_000, 1200, on_s=0.048, off_s=0.0)
    cbr = Cbr(1_000_000, 1200)
    assert [flow.offset_ns(k) for k in range(50)] == [cbr.offset_ns(k) for k in range(50)]
    with pytest.raises(ValueError):
        OnOff(8000, 100, on_s=0, off_s=1)
    with pytest.raises(ValueError):
        OnOff(8000, 100, on_s=1, off_s=-1)


# --- pacing ------------------------------------------------------------------------------------


def _send_all_due(pacer: Pacer, now: int) -> int:
    """What the sender loop does at `now`: skip what is hopelessly overdue, send what is due."""
    pacer.skip_overdue(now)
    sent = 0
    while pacer.due(now):
        pacer.sent(now)
        sent += 1
    return sent


def test_pacer_on_time_has_no_late_packets_and_keeps_the_rate() -> None:
    start = 10 * NS
    pacer = Pacer(Cbr(30_000_000, 1200), start)
    for k in range(3125):  # one second, woken exactly at each deadline
        now = start + k * 320_000
        assert pacer.next_ns == now
        assert _send_all_due(pacer, now) == 1
    assert (pacer.sent_count, pacer.late, pacer.skipped) == (3125, 0, 0)
    assert pacer.lags.max == 0


def test_pacer_sends_a_late_burst_counts_it_late_and_does_not_drift() -> None:
    start = 0
    pacer = Pacer(Cbr(30_000_000, 1200), start, late_after_ns=5 * MS)
    assert _send_all_due(pacer, 0) == 1
    # A 20 ms stall (the CPU went elsewhere): every packet due meanwhile goes at once.
    now = 20 * MS
    sent = _send_all_due(pacer, now)
    assert sent == 20 * MS // 320_000  # due at 0.32, 0.64, ..., 19.84 ms and at 20 ms
    # Late: those due before 15 ms (more than 5 ms late when sent at 20 ms).
    assert pacer.late == len([k for k in range(1, 63) if now - k * 320_000 > 5 * MS])
    assert pacer.lags.max == 20 * MS - 320_000
    # The schedule is where it would have been: the burst did not shift later deadlines.
    assert pacer.next_ns == 63 * 320_000
    assert pacer.skipped == 0


def test_pacer_skips_what_is_more_than_max_lag_overdue_exactly() -> None:
    schedule = OnOff(30_000_000, 1200, on_s=0.1, off_s=0.05)
    pacer = Pacer(schedule, 5 * NS, max_lag_ns=500 * MS)
    assert _send_all_due(pacer, 5 * NS) == 1
    now = 5 * NS + 2 * NS  # a 2 s stall
    skipped = pacer.skip_overdue(now)
    # Brute force: every packet due more than 0.5 s before now is given up, no other.
    due = [k for k in range(1, 100_000) if 5 * NS + schedule.offset_ns(k) < now - 500 * MS]
    assert skipped == len(due) and pacer.skipped == len(due)
    assert pacer.k == due[-1] + 1
    assert now - pacer.next_ns <= 500 * MS
    first = pacer.k
    sent = _send_all_due(pacer, now)
    assert sent == len([k for k in range(first, 100_000) if schedule.offset_ns(k) <= 2 * NS])
    late = [k for k in range(first, pacer.k) if now - 5 * NS - schedule.offset_ns(k) > 5 * MS]
    assert pacer.late == len(late) > 0
    assert pacer.skip_overdue(now) == 0  # nothing is skipped twice


def test_pacer_give_up_skips_one_packet() -> None:
    pacer = Pacer(Cbr(8000, 100), 0)
    pacer.give_up()
    assert (pacer.k, pacer.skipped, pacer.sent_count, pacer.next_ns) == (1, 1, 0, NS // 10)


def test_ticker_stays_on_its_grid_and_skips_missed_ticks() -> None:
    ticker = Ticker(1000, 500)
    assert not ticker.due(1499) and ticker.due(1500)
    ticker.advance(1530)  # a late tick: the next is still on the grid
    assert ticker.next_ns == 2000
    ticker.advance(3700)  # missed 2500, 3000, 3500: not made up
    assert ticker.next_ns == 4000
    with pytest.raises(ValueError):
        Ticker(0, 0)


# --- statistics --------------------------------------------------------------------------------


def test_histogram_quantiles_are_within_half_a_percent() -> None:
    rng = random.Random(7)
    values = [int(rng.lognormvariate(17, 0.6)) for _ in range(20_000)]  # delays around 24 ms
    hist = Histogram()
    hist.extend(values)
    for q in (0.01, 0.5, 0.95, 0.99, 1.0):
        exact = nearest_rank(values, q)
        assert exact is not None
        assert hist.quantile(q) == pytest.approx(exact, rel=0.006), q
    assert hist.max == max(values) and hist.min == min(values)
    assert hist.mean() == pytest.approx(sum(values) / len(values))
    assert len(hist.counts) < 500  # bounded by the range, not by the 20,000 values


def test_histogram_edges() -> None:
    hist = Histogram()
    assert hist.quantile(0.5) is None and hist.mean() is None
    for v in (0, 0, -3, 1000):  # a negative value (a clock step) reads as 0
        hist.add(v)
    assert hist.quantile(0.5) == 0.0
    assert hist.quantile(1.0) == 1000  # clamped to the largest value seen
    assert hist.min == 0 and hist.max == 1000


def test_nearest_rank() -> None:
    assert nearest_rank([], 0.5) is None
    assert nearest_rank([4, 1, 3, 2], 0.5) == 2
    assert nearest_rank([4, 1, 3, 2], 0.95) == 4
    assert nearest_rank([5], 0.01) == 5


# --- sequence numbers: loss, reordering, duplicates ----------------------------------------------


def test_in_order_flow_has_no_loss() -> None:
    t = SeqTracker()
    assert [t.observe(s) for s in range(100)] == [NEW] * 100
    assert (t.expected, t.received, t.lost) == (100, 100, 0)


def test_gaps_are_losses_and_a_late_arrival_fills_its_gap() -> None:
    t = SeqTracker()
    for s in (0, 1, 2, 5, 6, 9):
        assert t.observe(s) == NEW
    assert (t.expected, t.received, t.lost) == (10, 6, 4)  # 3, 4, 7, 8 missing
    assert t.observe(4) == REORDERED
    assert t.observe(8) == REORDERED
    assert (t.lost, t.reordered, t.received) == (2, 2, 8)
    assert t.observe(4) == DUPLICATE  # a second copy of a reordered one
    assert t.observe(9) == DUPLICATE
    assert t.observe(0) == DUPLICATE
    assert (t.lost, t.duplicates, t.received) == (2, 3, 8)


def test_loss_never_goes_negative_with_duplicates() -> None:
    t = SeqTracker()
    for s in [0, 1, 1, 1, 2, 2, 3]:
        t.observe(s)
    assert (t.expected, t.received, t.duplicates, t.lost) == (4, 4, 3, 0)


def test_fin_counts_loss_at_the_tail() -> None:
    t = SeqTracker()
    for s in range(10):
        t.observe(s)
    t.fin(15)  # the sender sent 15: the last 5 never came
    assert (t.expected, t.lost) == (15, 5)
    t.fin(3)  # a count below what arrived changes nothing
    assert t.expected == 10


def test_window_bounds_memory_and_older_arrivals_are_stale() -> None:
    t = SeqTracker(window=8)
    t.observe(0)
    t.observe(100)  # a jump: only the last 8 numbers below it are remembered as missing
    assert len(t._missing) == 8
    assert t.lost == 99
    assert t.observe(95) == REORDERED
    assert t.observe(50) == STALE  # older than the window: neither received nor duplicate
    for s in range(101, 200):
        t.observe(s)
    assert len(t._missing) == 0 and len(t._gaps) == 0  # the old gaps were let go
    assert t.observe(96) == STALE
    assert (t.received, t.stale, t.lost) == (1 + 1 + 1 + 99, 2, 200 - 102)


def test_random_reordering_and_duplicates_match_a_set() -> None:
    rng = random.Random(3)
    sent = list(range(5000))
    kept = [s for s in sent if rng.random() > 0.2]  # 20% lost
    doubled = set(rng.sample(kept, 300))
    arrivals = [copy for s in kept for copy in ([s, s] if s in doubled else [s])]
    # Local reordering: shuffle within small blocks (never farther than the window).
    for i in range(0, len(arrivals), 16):
        block = arrivals[i : i + 16]
        rng.shuffle(block)
        arrivals[i : i + 16] = block
    t = SeqTracker(window=1024)
    for s in arrivals:
        t.observe(s)
    t.fin(len(sent))
    assert t.received == len(set(kept))
    assert t.duplicates == 300
    assert t.lost == len(sent) - len(set(kept))
    assert t.stale == 0


# --- the receiver's and the sender's accounts -----------------------------------------------------


def test_receiver_goodput_is_the_rate_of_a_cbr_flow_exactly() -> None:
    start = 50 * NS
    acct = RecvAccount(start, datagrams=True)
    first = start + 200 * MS  # the flow starts 0.2 s after the receiver
    for k in range(1000):  # 1000 bytes every ms for 1 s: 8 Mbit/s
        now = first + k * MS
        acct.on_datagram(now, 1, k, now - 7 * MS, 1000)
    summary = acct.summary(start + 2 * NS)
    assert summary["goodput_bps"] == pytest.approx(8_000_000)
    assert summary["active_s"] == pytest.approx(0.999)
    assert summary["duration_s"] == pytest.approx(2.0)
    assert summary["loss"] == 0.0
    assert summary["delay_p50_ms"] == pytest.approx(7, rel=0.006)
    assert summary["delay_max_ms"] == 7


def test_receiver_samples_give_the_interval_and_cumulative_loss() -> None:
    start = 0
    acct = RecvAccount(start, datagrams=True)
    seq = 0
    samples = []
    for interval in range(4):
        for j in range(100):  # 100 datagrams of 500 bytes every 0.5 s: 800 kbit/s
            now = interval * 500 * MS + j * 5 * MS
            # Every 4th is lost in the second interval only.
            if not (interval == 1 and seq % 4 == 0):
                acct.on_datagram(now, 9, seq, now - (10 + interval) * MS, 500)
            seq += 1
        samples.append(acct.sample((interval + 1) * 500 * MS))
    assert all(list(s) == list(SAMPLE_KEYS) for s in samples)
    assert [s["packets"] for s in samples] == [100, 75, 100, 100]
    assert [s["bytes"] for s in samples] == [50_000, 37_500, 50_000, 50_000]
    assert [s["goodput_bps"] for s in samples] == pytest.approx([800e3, 600e3, 800e3, 800e3])
    assert [s["t"] for s in samples] == [0.5, 1.0, 1.5, 2.0]
    # Cumulative loss share: 25 lost by the end of the second interval, of 200, then of 300, 400.
    assert [s["loss"] for s in samples] == pytest.approx([0, 25 / 200, 25 / 300, 25 / 400])
    assert [s["delay_ms"] for s in samples] == [10, 11, 12, 13]
    assert all(s["rtt_ms"] is None and s["late"] is None for s in samples)
    summary = acct.summary(2 * NS)
    assert (summary["expected"], summary["lost"], summary["packets_received"]) == (400, 25, 375)
    assert summary["delay_p50_ms"] == pytest.approx(12, rel=0.006)


def test_receiver_leaves_duplicates_out_of_goodput_and_counts_fins() -> None:
    acct = RecvAccount(0, datagrams=True)
    for k in range(10):
        acct.on_datagram(k * MS, 1, k, k * MS, 100)
        acct.on_datagram(k * MS, 1, k, k * MS, 100)  # each one twice
    acct.on_fin(1, 12)  # two more were sent and lost
    s = acct.summary(NS)
    assert (s["packets_received"], s["bytes_received"], s["duplicates"]) == (10, 1000, 10)
    assert s["goodput_bps"] == pytest.approx(900 * 8 / 0.009)
    assert (s["expected"], s["lost"], s["fins"]) == (12, 2, 1)
    assert s["loss"] == pytest.approx(2 / 12)


def test_receiver_adds_up_flows() -> None:
    acct = RecvAccount(0, datagrams=True)
    for k in range(10):
        acct.on_datagram(k, 1, k, 0, 100)  # flow 1: all 10
        if k % 2:
            acct.on_datagram(k, 2, k, 0, 100)  # flow 2 (a sender restarted): every other
    s = acct.summary(NS)
    assert (s["flows"], s["expected"], s["lost"]) == (2, 20, 5)


def test_tcp_receiver_has_goodput_but_no_loss_or_delay() -> None:
    acct = RecvAccount(0, datagrams=False)
    assert acct.goodput_bps is None
    for k in range(11):
        acct.on_data(k * 10 * MS, 2500)  # 2500 bytes every 10 ms: 2 Mbit/s
    sample = acct.sample(200 * MS)
    assert sample["loss"] is None and sample["delay_ms"] is None
    assert sample["goodput_bps"] == pytest.approx(11 * 2500 * 8 / 0.2)
    s = acct.summary(NS)
    assert s["goodput_bps"] == pytest.approx(2_000_000)
    assert "loss" not in s and "delay_p50_ms" not in s


def test_sender_account_rate_rtt_and_acknowledged_goodput() -> None:
    acct = SendAccount(0, datagrams=False)
    for k in range(100):
        acct.on_send(k * MS, 1250)  # 10 Mbit/s written
    for rtt in (30, 10, 20):
        acct.on_rtt(rtt * MS)
    acct.on_acked(100 * MS, 100_000)  # 8 Mbit/s acknowledged over 0.1 s
    s1 = acct.sample(100 * MS, late=None)
    assert s1["rate_bps"] == pytest.approx(10e6)
    assert s1["goodput_bps"] == pytest.approx(8e6)
    assert s1["rtt_ms"] == 20 and s1["loss"] is None
    acct.on_acked(200 * MS, 150_000)
    s2 = acct.sample(200 * MS, late=3)
    assert s2["goodput_bps"] == pytest.approx(4e6)  # 50,000 more bytes in 0.1 s
    assert s2["bytes"] == 0 and s2["rtt_ms"] is None and s2["late"] == 3
    s = acct.summary(200 * MS)
    assert s["goodput_bps"] == pytest.approx(150_000 * 8 / 0.2)
    assert s["bytes_sent"] == 125_000 and s["packets_sent"] == 100
    assert s["rtt_p50_ms"] == pytest.approx(20, rel=0.006)
    assert s["rtt_samples"] == 3


def test_datagram_sender_has_no_goodput_of_its_own() -> None:
    acct = SendAccount(0, datagrams=True)
    acct.on_send(0, 1200)
    acct.on_send(NS, 1200)
    s = acct.summary(NS)
    assert s["goodput_bps"] is None and s["bytes_acked"] is None
    assert s["sent_bps"] == pytest.approx(2400 * 8)


# --- struct tcp_info -----------------------------------------------------------------------------


def _tcp_info_bytes(length: int) -> bytes:
    raw = bytearray(length)
    raw[0] = 1  # TCP_ESTABLISHED
    for offset, value in ((16, 1448), (20, 536), (68, 51_234), (72, 800), (80, 42), (100, 17)):
        struct.pack_into("=I", raw, offset, value)
    if length >= 136:
        struct.pack_into("=QQ", raw, 120, 9_535_537, 77)
    if length >= 160:
        struct.pack_into("=III", raw, 148, 45, 6596, 6658)
    return bytes(raw)


def test_tcp_info_fields_at_the_kernels_offsets() -> None:
    info = parse_tcp_info(_tcp_info_bytes(232))  # a newer kernel returns more than asked for
    assert info.state == 1
    assert (info.snd_mss, info.rcv_mss, info.rtt_us, info.rttvar_us) == (1448, 536, 51_234, 800)
    assert (info.snd_cwnd, info.total_retrans) == (42, 17)
    assert (info.bytes_acked, info.bytes_received) == (9_535_537, 77)
    assert (info.min_rtt_us, info.data_segs_in, info.data_segs_out) == (45, 6596, 6658)


def test_tcp_info_of_an_old_kernel_has_none_for_the_newer_fields() -> None:
    info = parse_tcp_info(_tcp_info_bytes(104))
    assert info.rtt_us == 51_234 and info.total_retrans == 17
    assert info.bytes_acked is None and info.min_rtt_us is None and info.data_segs_out is None
    with pytest.raises(ValueError):
        parse_tcp_info(bytes(100))


# --- the command line (every case is refused before a socket is opened) ---------------------


SMALL = ["--size", "10"]


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["send", "--kind", "udp", "--to", "10.0.0.1", "--port", "9"], "needs --rate"),
        (["send", "--kind", "onoff", "--to", "10.0.0.1", "--port", "9", "--rate", "1e6"], "--on"),
        (["send", "--kind", "udp", "--to", "host", "--port", "9", "--rate", "1"], "IP address"),
        (["send", "--kind", "udp", "--to", "10.0.0.1", "--port", "0", "--rate", "1"], "port"),
        (
            ["send", "--kind", "udp", "--to", "10.0.0.1", "--port", "9", "--rate", "1e6", *SMALL],
            "24..65507",
        ),
        (["send", "--kind", "tcp", "--to", "10.0.0.1", "--port", "9", "--rate", "-1"], "--rate"),
        (
            [
                "send",
                "--kind",
                "udp",
                "--to",
                "::1",
                "--port",
                "9",
                "--rate",
                "1",
                "--sndbuf",
                "-1",
            ],
            "--sndbuf",
        ),
        (["recv", "--kind", "onoff", "--port", "9"], "invalid choice"),
        (["recv", "--kind", "udp", "--port", "70000"], "port"),
    ],
)
def test_bad_command_lines_exit_2_and_say_why(
    argv: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        gen.main([*argv, "--stats", "/nonexistent/stats.json"])
    assert exit_.value.code == 2
    assert says in capsys.readouterr().err
