"""A handover's interruption on a real link: UDP datagrams through the relay between two
namespaces while `UserspaceLink.interrupt` cuts it.

A sends a numbered datagram every millisecond to B over a link with a 5 ms delay. A 40 ms
"hold" gap must leave B without a datagram for 40 ms (one 30 kHz slot, 0.5 ms, either way,
plus up to the 1 ms send period: the last datagram before the gap left up to a period before
it began), then deliver every datagram, in order. A "drop" gap must lose one contiguous run
of 40 ms of sending and nothing else. Arrival times are the kernel's receive timestamps (run
with -s to see the measured figures). Each test creates its own namespaces and deletes them,
also when it fails; the relay stops with its `UserspaceLink`.
"""

from __future__ import annotations

import itertools
import socket
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from netem.profile import LinkProfile
from tests.test_relay_root import ADDR_B, PORT, link_for, namespaces, udp_socket
from tests.test_rrc_root import _stamp

pytestmark = [pytest.mark.root, pytest.mark.alone]

SO_TIMESTAMPNS = 35  # <asm-generic/socket.h>
DELAY_S = 0.005
PERIOD_S = 0.001  # one datagram per ms
GAP_S = 0.040
SLOT_S = 0.0005  # one slot at 30 kHz subcarrier spacing: the precision asked of the gap
COUNT = 400  # 0.4 s of sending; the gap starts 0.15 s in
PROFILE = LinkProfile(delay_s=DELAY_S)


@pytest.fixture
def pair() -> Iterator[tuple[str, ...]]:
    with namespaces("a", "b") as names:
        yield names


def send_through_a_gap(pair: tuple[str, ...], mode: str) -> tuple[list[tuple[int, float]], Any]:
    """Send COUNT datagrams A -> B, one per PERIOD_S, and interrupt the link for GAP_S in
    `mode` 150 ms in; return (seq, kernel receive time) in arrival order, and the relay's
    counters."""
    received: list[tuple[int, float]] = []
    with link_for(pair, uplink=PROFILE, downlink=PROFILE) as link:
        receiver = udp_socket(pair[1], (ADDR_B, PORT))
        receiver.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        receiver.settimeout(0.1)
        sender = udp_socket(pair[0])
        done = threading.Event()

        def receive() -> None:
            while not done.is_set():
                try:
                    data, ancillary, _flags, _peer = receiver.recvmsg(2048, 64)
                except TimeoutError:
                    continue
                received.append((struct.unpack("!I", data[:4])[0], _stamp(ancillary)))

        thread = threading.Thread(target=receive, daemon=True)
        thread.start()
        # The gap from its own thread, so the sender keeps its pace through the request.
        interrupter = threading.Timer(0.150, link.interrupt, (GAP_S, mode))
        try:
            start = time.monotonic()
            interrupter.start()
            for i in range(COUNT):
                # On an absolute schedule: a late wake-up is caught up, not carried forward.
                time.sleep(max(0.0, start + i * PERIOD_S - time.monotonic()))
                sender.sendto(struct.pack("!I", i) + bytes(60), (ADDR_B, PORT))
            interrupter.join(2)
            time.sleep(0.2)  # the last datagram's delay
            counters = link.counters()
            # The relay's clock is CLOCK_MONOTONIC, the receive stamps the wall clock.
            wall = time.time() - time.monotonic()
            for d in ("uplink", "downlink"):
                gap = counters[d].get("handover")
                if gap is not None:
                    gap["since_wall"], gap["until_wall"] = gap["since"] + wall, gap["until"] + wall
        finally:
            interrupter.cancel()
            done.set()
            thread.join(2)
            receiver.close()
            sender.close()
    return received, counters


def test_a_hold_gap_delays_everything_by_the_gap_and_loses_nothing(pair) -> None:
    received, counters = send_through_a_gap(pair, "hold")
    seqs = [seq for seq, _ in received]
    times = [t for _, t in received]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    widest = max(range(len(gaps)), key=gaps.__getitem__)
    others = sorted(gaps[:widest] + gaps[widest + 1 :])
    burst = sum(1 for g in gaps[widest + 1 :] if g < 0.0002)  # the held ones, back to back
    held = counters["uplink"]["handover"]
    # When the held datagrams came, against when the relay said the gap ends.
    late = times[widest + 1] - held["until_wall"]
    print(
        f"\nhold: widest receive gap {gaps[widest] * 1e3:.3f} ms after seq {seqs[widest]};"
        f" held ones {late * 1e3:+.3f} ms after the gap's end; next widest"
        f" {others[-1] * 1e3:.3f} ms; median spacing {others[len(others) // 2] * 1e3:.3f} ms;"
        f" {held['held_packets']} held for {held['held_s'] * 1e3:.1f} ms in all; {burst} back"
        " to back after the gap"
    )
    assert seqs == list(range(COUNT)), "a datagram was lost or reordered"
    # The last datagram before the gap left up to one send period before it began, so the
    # silence at B is the gap plus that much: 40 ms ± one slot, plus at most one period.
    assert GAP_S - SLOT_S <= gaps[widest] <= GAP_S + PERIOD_S + SLOT_S, gaps[widest]
    assert -SLOT_S <= late <= SLOT_S, late  # released at the gap's end, to a slot
    assert times[widest] < held["since_wall"] + SLOT_S  # the one before left before it
    assert others[-1] < GAP_S / 4, "a second silence: the gap was not the only one"
    assert held["gaps"] == 1
    assert held["held_packets"] == pytest.approx(GAP_S / PERIOD_S, abs=2)
    assert counters["uplink"]["total"]["dropped_packets"] == {}


def test_a_drop_gap_loses_one_run_of_the_gap_s_worth_and_nothing_else(pair) -> None:
    received, counters = send_through_a_gap(pair, "drop")
    seqs = [seq for seq, _ in received]
    lost = sorted(set(range(COUNT)) - set(seqs))
    times = [t for _, t in received]
    widest = max(b - a for a, b in itertools.pairwise(times))
    gap = counters["uplink"]["handover"]
    after = next(t for seq, t in received if lost and seq > lost[-1])
    before = max(t for seq, t in received if lost and seq < lost[0])
    print(
        f"\ndrop: lost {len(lost)} datagrams, seq {lost[0] if lost else None}.."
        f"{lost[-1] if lost else None}; widest receive gap {widest * 1e3:.3f} ms; last one"
        f" before {(before - gap['since_wall']) * 1e3:+.3f} ms from the gap's start, first"
        f" after {(after - gap['until_wall']) * 1e3:+.3f} ms from its end"
    )
    assert seqs == sorted(seqs), "the datagrams that crossed were reordered"
    assert lost == list(range(lost[0], lost[-1] + 1)), f"not one contiguous run: {lost}"
    assert len(lost) == pytest.approx(GAP_S / PERIOD_S, abs=2)
    assert counters["uplink"]["total"]["dropped_packets"] == {"handover": len(lost)}
    assert counters["uplink"]["handover"]["dropped_packets"] == len(lost)
    # Between the last datagram before and the first after: the gap, as for a hold, and
    # around the relay's window to a slot (those in it were lost, not late).
    assert GAP_S - SLOT_S <= widest <= GAP_S + PERIOD_S + SLOT_S, widest
    assert -PERIOD_S - SLOT_S <= before - gap["since_wall"] < SLOT_S
    assert -SLOT_S <= after - gap["until_wall"] < PERIOD_S + SLOT_S
