"""RRC states on a real link: UDP datagrams through the relay between two namespaces.

The first datagram after a quiet spell longer than the inactivity timer must arrive `resume_s`
later than a datagram of the plain path (after a longer one still, `setup_s`), the ones after
it not at all, and one after a shorter spell not at all either. Delays are one-way, from the
send time in the payload to the kernel's receive timestamp, and are checked against the
configured timers (the oracle). Each test creates its own namespaces and deletes them; the
relay stops with its `UserspaceLink`.
"""

from __future__ import annotations

import selectors
import socket
import statistics
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

from netem.nr.rrc import RrcSettings
from netem.profile import LinkProfile
from tests.test_relay_root import ADDR_A, ADDR_B, PORT, link_for, namespaces, udp_socket

pytestmark = [pytest.mark.root, pytest.mark.alone]

SO_TIMESTAMPNS = 35  # <asm-generic/socket.h>
DELAY_S = 0.005  # each direction's own delay
#: What this host's timers and wake-ups may add to or take from a one-way delay (a VM whose
#: halted vCPUs wake slowly adds 0.5-2 ms after an idle spell; the relay leaves a packet at
#: most 0.3 ms early when its polling budget is spent).
TOLERANCE_S = 0.003
EARLY_S = 0.0005


@pytest.fixture
def pair() -> Iterator[tuple[str, ...]]:
    with namespaces("a", "b") as names:
        yield names


def _stamp(ancillary: list[tuple[int, int, bytes]]) -> float:
    """The kernel's receive time (SO_TIMESTAMPNS, wall clock) of a datagram."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            sec, nsec = struct.unpack("qq", data[:16])
            return sec + nsec * 1e-9
    raise AssertionError("the kernel gave no receive timestamp")


def one_way(
    pair: tuple[str, ...], profile: LinkProfile, schedule: list[tuple[float, str]]
) -> tuple[list[float], dict[str, Any]]:
    """Send one datagram per `(t, direction)` of `schedule` (t in s from the start, in order)
    over a link with `profile` both ways; return each one's one-way delay, in the schedule's
    order, and the relay's counters at the end."""
    received: dict[int, float] = {}
    with link_for(pair, uplink=profile, downlink=profile) as link:
        # Uplink: A -> B; downlink: B -> A. The payload: index and send time (wall clock).
        receivers = {
            "uplink": udp_socket(pair[1], (ADDR_B, PORT)),
            "downlink": udp_socket(pair[0], (ADDR_A, PORT)),
        }
        senders = {"uplink": udp_socket(pair[0]), "downlink": udp_socket(pair[1])}
        targets = {"uplink": (ADDR_B, PORT), "downlink": (ADDR_A, PORT)}
        sent: list[float] = []
        done = threading.Event()
        selector = selectors.DefaultSelector()
        for sock in receivers.values():
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            sock.setblocking(False)
            selector.register(sock, selectors.EVENT_READ)

        def receive() -> None:
            while not done.is_set():
                for key, _ in selector.select(0.1):
                    data, ancillary, _flags, _peer = key.fileobj.recvmsg(2048, 64)  # type: ignore[union-attr]
                    received[struct.unpack("!I", data[:4])[0]] = _stamp(ancillary)

        thread = threading.Thread(target=receive, daemon=True)
        thread.start()
        try:
            start = time.monotonic()
            for i, (t, direction) in enumerate(schedule):
                time.sleep(max(0.0, start + t - time.monotonic()))
                sent.append(time.time())
                senders[direction].sendto(struct.pack("!I", i) + bytes(60), targets[direction])
            time.sleep(0.5)  # the last one's delay and any promotion it pays
            counters = link.counters()
        finally:
            done.set()
            thread.join(2)
            selector.close()
            for sock in (*receivers.values(), *senders.values()):
                sock.close()
    assert sorted(received) == list(range(len(schedule))), "a datagram was lost"
    return [received[i] - sent[i] for i in range(len(schedule))], counters


def test_short_timers_the_first_datagram_after_quiet_pays_the_resume_or_the_setup(pair) -> None:
    rrc = RrcSettings(inactivity_s=1.0, idle_after_s=0.5, resume_s=0.030, setup_s=0.150)
    # The quiet spells count from the last packet of either direction, or from the end of the
    # promotion it paid: INACTIVE after 1.0 s, IDLE after 1.5 s.
    schedule = [
        (0.00, "uplink"),  # 0: the link's first packet (the UE has just attached)
        *[(0.05 * k, "uplink") for k in range(1, 6)],  # 1-5: plain, up to 0.25 s
        (1.05, "uplink"),  # 6: 0.8 s quiet: still connected
        (2.25, "uplink"),  # 7: 1.2 s quiet: INACTIVE, pays the resume (until 2.28)
        (2.26, "uplink"),  # 8: during the resume: waits for the rest of it
        (2.33, "uplink"),  # 9-11: after it: nothing
        (2.38, "uplink"),
        (2.43, "uplink"),
        (3.63, "downlink"),  # 12: 1.2 s quiet: the downlink pays the resume (paging)
        (3.70, "uplink"),  # 13: the UE is connected for the uplink too
        (5.70, "uplink"),  # 14: 2.0 s quiet: IDLE, pays the setup
        (5.95, "uplink"),  # 15: nothing
    ]
    delays, counters = one_way(pair, LinkProfile(delay_s=DELAY_S, rrc=rrc), schedule)
    plain = statistics.median(delays[1:6])
    shown = f"plain {plain * 1e3:.2f} ms; delays (ms) {[round(d * 1e3, 2) for d in delays]}"
    print(shown)
    assert plain == pytest.approx(DELAY_S, abs=TOLERANCE_S), shown
    for i in (6, 9, 10, 11, 13, 15):  # no promotion
        assert delays[i] == pytest.approx(plain, abs=TOLERANCE_S), (i, shown)
    for i, extra in ((7, rrc.resume_s), (12, rrc.resume_s), (14, rrc.setup_s)):
        assert delays[i] - plain == pytest.approx(extra, abs=TOLERANCE_S), (i, shown)
        assert delays[i] >= DELAY_S + extra - EARLY_S, (i, shown)  # never early
    # Datagram 8, sent 10 ms into the resume, leaves with datagram 7 (its send times are the
    # schedule's, so this holds up to the sender's own timing: compared with 7's arrival).
    assert delays[8] + 0.010 == pytest.approx(delays[7], abs=TOLERANCE_S), shown
    rrc_counters = counters["rrc"]
    assert rrc_counters["promotions"] == {"inactive": 2, "idle": 1}, rrc_counters
    assert rrc_counters["paging"] == 1
    assert counters["downlink"]["rrc"]["promotions"] == {"inactive": 1, "idle": 0}
    assert counters["uplink"]["rrc"]["waited_packets"] == 3  # 7, 8 and 14


@pytest.mark.slow
def test_idle_12_s_with_a_10_s_timer_pays_the_resume_once_idle_8_s_nothing(pair) -> None:
    """Issue #19's must-show with the default timers (10 s inactivity, 30 ms resume)."""
    rrc = RrcSettings()
    assert (rrc.inactivity_s, rrc.resume_s) == (10.0, 0.030)
    schedule = [
        (0.00, "uplink"),  # 0: the link's first packet
        *[(0.05 * k, "uplink") for k in range(1, 6)],  # 1-5: plain, up to 0.25 s
        (8.25, "uplink"),  # 6: 8 s quiet: nothing
        (8.30, "uplink"),  # 7
        (20.30, "uplink"),  # 8: 12 s quiet: INACTIVE, pays the resume
        (20.36, "uplink"),  # 9, 10: the next ones nothing
        (20.41, "uplink"),
    ]
    delays, counters = one_way(pair, LinkProfile(delay_s=DELAY_S, rrc=rrc), schedule)
    plain = statistics.median(delays[1:6])
    shown = f"plain {plain * 1e3:.2f} ms; delays (ms) {[round(d * 1e3, 2) for d in delays]}"
    print(shown)
    for i in (6, 7, 9, 10):
        assert delays[i] == pytest.approx(plain, abs=TOLERANCE_S), (i, shown)
    assert delays[8] - plain == pytest.approx(rrc.resume_s, abs=TOLERANCE_S), shown
    assert delays[8] >= DELAY_S + rrc.resume_s - EARLY_S, shown
    assert counters["rrc"]["promotions"] == {"inactive": 1, "idle": 0}
