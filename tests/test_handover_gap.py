"""A handover's interruption in the relay's pipelines (`netem.nr.handover_gap.HandoverGap`), with a
fake clock (no root), and the relay's `interrupt` op over SEQPACKET socket pairs.

"hold" (a lossless handover: PDCP forwarding, TS 38.300 §9.2.3.2) keeps what would leave the
link during the gap and lets it go, in order, at its end; "drop" loses exactly that. The
gap acts where packets leave the link, after the delay, so what is in flight is caught too.
"""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from netem.errors import ProfileError
from netem.gso import Frame
from netem.nr.handover_gap import HandoverGap
from netem.profile import LinkProfile
from netem.relay.direction import build_pipeline
from netem.relay.process import Relay
from netem.stages import Delay, Pipeline
from tests.test_stages import ask


def packet(seq: int, size: int = 100) -> bytes:
    return seq.to_bytes(4, "big") + bytes(size - 4)


def seq_of(p: bytes) -> int:
    return int.from_bytes(p[:4], "big")


def drain(pipe: Pipeline, until: float) -> list[tuple[float, int]]:
    """Run a fake clock event by event up to `until`: (time, seq) of each packet that left."""
    out: list[tuple[float, int]] = []
    while True:
        due = pipe.next_due()
        if due is None or due > until:
            return out
        out += [(due, seq_of(p)) for p in pipe.pop_ready(due)]


# -- the stage in a pipeline -------------------------------------------------------------------


def test_the_gap_is_the_last_stage_and_transparent_without_a_gap() -> None:
    pipe = build_pipeline(LinkProfile(delay_s=0.010))
    # Last, after the delay: it cuts the link where packets leave it.
    assert [s.name for s in pipe.stages[-2:]] == ["delay", "handover"]
    pipe.push(packet(1), 0.0)
    assert pipe.next_exit() == pytest.approx(0.010, abs=1e-12)
    assert drain(pipe, 1.0) == [(pytest.approx(0.010, abs=1e-12), 1)]
    assert "handover" not in pipe.snapshot()  # like "rrc": only once a gap was started
    assert pipe.snapshot()["stages"]["handover"]["packets_out"] == 1


def test_hold_releases_everything_at_the_end_in_the_order_it_came() -> None:
    pipe = build_pipeline(LinkProfile())
    pipe.push(packet(0), 0.5)
    assert [seq_of(p) for p in pipe.pop_ready(0.5)] == [0]
    pipe.interrupt(1.0, 0.04, "hold")
    times = [1.0, 1.01, 1.02, 1.03, 1.0399]
    for seq, t in enumerate(times, start=1):
        pipe.push(packet(seq), t)
        assert pipe.pop_ready(t) == []
        # Nothing leaves before the gap's end: the relay sleeps until then, exactly.
        assert pipe.next_due() == pipe.next_exit() == pytest.approx(1.04, abs=1e-12)
        assert pipe.deadlines() == (None, pytest.approx(1.04, abs=1e-12))
    assert pipe.pop_ready(1.04 - 1e-9) == []
    assert [seq_of(p) for p in pipe.pop_ready(1.04)] == [1, 2, 3, 4, 5]
    assert pipe.next_due() is None
    pipe.push(packet(6), 1.05)  # after the gap: at once
    assert [seq_of(p) for p in pipe.pop_ready(1.05)] == [6]
    gap = pipe.snapshot()["handover"]
    assert gap["gaps"] == 1 and gap["mode"] == "hold"
    assert gap["held_packets"] == 5 and gap["dropped_packets"] == 0
    assert gap["held_s"] == pytest.approx(sum(1.04 - t for t in times), abs=1e-9)
    assert pipe.snapshot()["total"]["packets_out"] == 7


def test_packets_after_the_gap_never_overtake_the_held_ones() -> None:
    # A 10 ms delay, one packet every ms; a relay that wakes late (once, 30 ms after the gap
    # ended) must still deliver in sending order, the held ones at the gap's end.
    pipe = build_pipeline(LinkProfile(delay_s=0.010))
    t0, gap_s = 0.1005, 0.040
    out: list[tuple[float, int]] = []
    interrupted = False
    for i in range(200):
        t = i * 1e-3
        if not interrupted and t >= t0:
            out += drain(pipe, t0)
            pipe.interrupt(t0, gap_s, "hold")
            interrupted = True
        if not (t0 + gap_s <= t < t0 + gap_s + 0.030):  # the relay is asleep meanwhile
            out += drain(pipe, t)
        pipe.push(packet(i), t)
    out += drain(pipe, 1.0)
    assert [seq for _, seq in out] == list(range(200))
    held = [seq for when, seq in out if when == pytest.approx(t0 + gap_s, abs=1e-12)]
    # Those that reached the exit in [t0, t0 + 40 ms): sent 10 ms earlier.
    assert held == [i for i in range(200) if t0 - 0.010 <= i * 1e-3 < t0 + gap_s - 0.010]
    assert len(held) == 40
    times = [when for when, _ in out]
    assert times == sorted(times)
    for when, seq in out:
        if seq not in held:
            assert when == pytest.approx(seq * 1e-3 + 0.010, abs=1e-12)  # not delayed


def test_drop_loses_exactly_what_reaches_the_exit_during_the_gap() -> None:
    pipe = build_pipeline(LinkProfile(delay_s=0.010))
    t0, gap_s = 0.1005, 0.040  # between two packets' exits: no float ties at the edges
    out: list[tuple[float, int]] = []
    for i in range(200):
        t = i * 1e-3
        if i == 101:  # t0 lies between the pushes at 100 and 101 ms
            out += drain(pipe, t0)
            pipe.interrupt(t0, gap_s, "drop")
        out += drain(pipe, t)
        pipe.push(packet(i), t)
    out += drain(pipe, 1.0)
    lost = sorted(set(range(200)) - {seq for _, seq in out})
    # Packets in flight when the gap began are lost too: those sent in [t0-10ms, t0+T-10ms).
    assert lost == [i for i in range(200) if t0 - 0.010 <= i * 1e-3 < t0 + gap_s - 0.010]
    assert lost == list(range(91, 131))
    assert [seq for _, seq in out] == sorted(seq for _, seq in out)  # the rest in order
    for when, seq in out:
        assert when == pytest.approx(seq * 1e-3 + 0.010, abs=1e-12)  # and on time
    snap = pipe.snapshot()
    assert snap["stages"]["handover"]["dropped_packets"] == {"handover": 40}
    assert snap["stages"]["handover"]["dropped_bytes"] == {"handover": 40 * 100}
    assert snap["total"]["dropped_packets"] == {"handover": 40}
    assert snap["handover"]["dropped_packets"] == 40 and snap["handover"]["held_packets"] == 0
    assert snap["handover"]["mode"] == "drop"


def test_the_window_is_half_open() -> None:
    for mode in ("hold", "drop"):
        gap = HandoverGap()
        gap.start(1.0, 0.5, mode)
        gap.push(packet(1), 0.75)  # before: passes
        gap.push(packet(2), 1.0)  # at the start: caught
        gap.push(packet(3), 1.5)  # at the end: passes (after any held one)
        got = []
        while (due := gap.next_due()) is not None:
            got += [(due, seq_of(p)) for p in gap.pop_ready(due)]
        expected = [(0.75, 1), (1.5, 3)] if mode == "drop" else [(0.75, 1), (1.5, 2), (1.5, 3)]
        assert got == expected, mode


def test_a_gap_started_during_another_makes_one_gap_of_their_union() -> None:
    pipe = build_pipeline(LinkProfile())
    pipe.interrupt(1.0, 0.040, "hold")
    pipe.push(packet(1), 1.01)
    assert pipe.pop_ready(1.01) == []
    assert pipe.deadlines() == (None, pytest.approx(1.04))
    # A second, longer gap from 1.02: the end moves on, the held packet waits for it.
    # (`interrupt` forgets the cached deadlines, which now are wrong.)
    pipe.interrupt(1.02, 0.040, "hold")
    assert pipe.deadlines() == (None, pytest.approx(1.06, abs=1e-12))
    # A shorter one inside it changes nothing of the end...
    pipe.interrupt(1.03, 0.005, "hold")
    assert pipe.next_exit() == pytest.approx(1.06, abs=1e-12)
    # ...but its mode applies from its start: what comes now is lost, the held one is not.
    pipe.interrupt(1.04, 0.0, "drop")
    pipe.push(packet(2), 1.05)
    assert pipe.pop_ready(1.0599) == []
    assert [seq_of(p) for p in pipe.pop_ready(1.06)] == [1]
    pipe.push(packet(3), 1.06)
    assert [seq_of(p) for p in pipe.pop_ready(1.06)] == [3]
    gap = pipe.snapshot()["handover"]
    assert gap["gaps"] == 4 and gap["since"] == 1.0 and gap["until"] == pytest.approx(1.06)
    assert gap["held_packets"] == 1 and gap["dropped_packets"] == 1
    assert gap["held_s"] == pytest.approx(0.05, abs=1e-9)


def test_a_new_gap_after_the_last_one_ended_releases_its_packets_at_its_end() -> None:
    gap = HandoverGap()
    gap.start(1.0, 0.1, "hold")
    gap.push(packet(1), 1.05)
    gap.start(2.0, 0.1, "hold")  # nobody popped in between (a late relay)
    gap.push(packet(2), 2.05)
    assert [seq_of(p) for p in gap.pop_ready(1.1)] == [1]  # left at the first gap's end
    assert gap.pop_ready(2.0999) == []
    assert [seq_of(p) for p in gap.pop_ready(2.1)] == [2]
    assert gap.held_s == pytest.approx(0.10, abs=1e-9)


def test_super_packets_are_held_whole_and_counted_as_their_wire_packets() -> None:
    pipe = build_pipeline(LinkProfile())  # no rate, no radio: frames stay whole
    frame = Frame(b"\0" * 5800, segments=4, wire_len=5800)
    pipe.interrupt(0.0, 0.010, "hold")
    pipe.push(frame, 0.001)
    pipe.push(packet(9), 0.002)
    assert pipe.pop_ready(0.009) == []
    out = pipe.pop_ready(0.010)
    assert out[0] is frame and seq_of(out[1]) == 9
    snap = pipe.snapshot()
    assert snap["handover"]["held_packets"] == 5
    assert snap["handover"]["held_s"] == pytest.approx(4 * 0.009 + 0.008, abs=1e-12)
    assert snap["stages"]["handover"]["packets_out"] == 5
    pipe.interrupt(0.02, 0.010, "drop")
    pipe.push(frame, 0.021)
    assert pipe.pop_ready(0.05) == []
    assert pipe.snapshot()["stages"]["handover"]["dropped_packets"] == {"handover": 4}
    assert pipe.snapshot()["stages"]["handover"]["dropped_bytes"] == {"handover": 5800}


def test_the_relay_sleeps_until_the_end_of_a_hold_even_behind_a_delay() -> None:
    # A packet still in the delay stage may reach the gap before its end: the next exit is
    # its hand-off (it might leave), then, once held, the gap's end.
    pipe = build_pipeline(LinkProfile(delay_s=0.010))
    pipe.push(packet(1), 0.0)
    pipe.interrupt(0.005, 0.040, "hold")
    assert pipe.next_exit() == pytest.approx(0.010, abs=1e-12)
    assert pipe.pop_ready(0.010) == []
    assert pipe.deadlines() == (None, pytest.approx(0.045, abs=1e-12))
    assert pipe.queued() == 1
    assert [seq_of(p) for p in pipe.pop_ready(0.045)] == [1]


@pytest.mark.parametrize(
    ("seconds", "mode", "error"),
    [
        (0.04, "pause", r"`mode` = 'pause': must be hold or drop"),
        (0.04, None, "must be hold or drop"),
        (-0.001, "hold", r"`seconds` = -0.001: must be a number of seconds in 0\.\.10"),
        (10.5, "hold", "in 0..10"),
        (math.inf, "drop", "in 0..10"),
        (math.nan, "drop", "in 0..10"),
        (True, "hold", "in 0..10"),
        ("0.04", "hold", "in 0..10"),
    ],
)
def test_a_bad_gap_is_refused_and_changes_nothing(seconds, mode, error: str) -> None:
    pipe = build_pipeline(LinkProfile())
    with pytest.raises(ProfileError, match=error) as info:
        pipe.interrupt(1.0, seconds, mode)
    assert isinstance(info.value, ValueError)
    pipe.push(packet(1), 1.01)
    assert len(pipe.pop_ready(1.01)) == 1
    assert "handover" not in pipe.snapshot()


def test_a_gap_of_zero_seconds_holds_nothing() -> None:
    pipe = build_pipeline(LinkProfile())
    pipe.interrupt(1.0, 0, "hold")
    pipe.push(packet(1), 1.0)
    assert len(pipe.pop_ready(1.0)) == 1
    assert pipe.snapshot()["handover"]["held_packets"] == 0


def test_a_delay_stage_alone_still_works_as_a_last_stage() -> None:
    # Pipelines built by hand (tests, benches) may still end in the delay stage.
    pipe = Pipeline([Delay(delay_s=0.01)])
    pipe.push(packet(1), 0.0)
    assert pipe.next_exit() == pytest.approx(0.01)
    assert len(pipe.pop_ready(0.01)) == 1


# -- the relay's `interrupt` op over socket pairs --------------------------------------------


@contextlib.contextmanager
def socket_relay(
    tmp_path: Path, uplink: Pipeline, downlink: Pipeline
) -> Iterator[tuple[socket.socket, socket.socket, str]]:
    """A running Relay whose TUN ends are SEQPACKET socket pairs (one datagram = one packet):
    (the a-side app end, the b-side app end, its control socket's path)."""
    a_app, a_relay = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    b_app, b_relay = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for s in (a_relay, b_relay):
        s.setblocking(False)
    for s in (a_app, b_app):
        s.settimeout(2)
    control = str(tmp_path / "c.sock")
    relay = Relay(a_relay.fileno(), b_relay.fileno(), uplink, downlink, control_path=control)
    thread = threading.Thread(target=relay.run, daemon=True)
    thread.start()
    try:
        yield a_app, b_app, control
    finally:
        relay.stop()
        thread.join(5)
        relay.close()
        for s in (a_app, a_relay, b_app, b_relay):
            s.close()


def test_the_relay_wakes_at_the_end_of_a_hold_to_deliver_what_it_held(tmp_path: Path) -> None:
    uplink = build_pipeline(LinkProfile(delay_s=0.005))
    with socket_relay(tmp_path, uplink, build_pipeline(LinkProfile())) as ends:
        a_app, b_app, control = ends
        a_app.send(b"\0\0\0\0before")
        assert b_app.recv(100) == b"\0\0\0\0before"
        asked = time.monotonic()
        assert ask(control, {"op": "interrupt", "seconds": 0.05, "mode": "hold"}) == {"ok": True}
        answered = time.monotonic()
        for i in range(1, 4):
            a_app.send(packet(i, 20))
            time.sleep(0.005)
        # Nothing more happens on any fd: only the relay's own timer can deliver them.
        got = [seq_of(b_app.recv(100)) for _ in range(3)]
        arrived = time.monotonic()
        counters = ask(control, {"op": "counters"})
    assert got == [1, 2, 3]
    # The gap began while the relay handled the request, between `asked` and `answered`.
    assert asked + 0.05 <= arrived < answered + 0.05 + 0.015, (arrived - asked, answered - asked)
    gap = counters["uplink"]["handover"]
    assert gap["gaps"] == 1 and gap["held_packets"] == 3
    assert asked <= gap["since"] <= answered  # the relay's clock is this one (monotonic)
    assert counters["downlink"]["handover"]["gaps"] == 1  # "both" by default


def test_interrupt_requests_are_checked(tmp_path: Path) -> None:
    pipes = build_pipeline(LinkProfile()), build_pipeline(LinkProfile())
    with socket_relay(tmp_path, *pipes) as (_, _, control):
        cases = [
            ({"op": "interrupt", "seconds": 0.04, "mode": "pause"}, "interrupt: handover gap"),
            ({"op": "interrupt", "seconds": 0.04, "mode": "pause"}, "must be hold or drop"),
            ({"op": "interrupt", "mode": "hold"}, "`seconds` = None: must be"),
            ({"op": "interrupt", "seconds": 11}, "in 0..10"),
            ({"op": "interrupt", "seconds": -1}, "in 0..10"),
            ({"op": "interrupt", "seconds": 0.04, "direction": "sideways"}, "direction must be"),
            ({"op": "jump"}, "interrupt"),  # the unknown op's message lists it
        ]
        for message, error in cases:
            reply = ask(control, message)
            assert not reply["ok"] and error in reply["error"], reply
        # None of them started a gap.
        counters = ask(control, {"op": "counters"})
        assert "handover" not in counters["uplink"] and "handover" not in counters["downlink"]
        reply = ask(
            control, {"op": "interrupt", "seconds": 0.01, "mode": "drop", "direction": "downlink"}
        )
        assert reply == {"ok": True}
        counters = ask(control, {"op": "counters"})
        assert "handover" not in counters["uplink"]
        assert counters["downlink"]["handover"]["mode"] == "drop"
