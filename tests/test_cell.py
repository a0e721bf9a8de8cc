"""A shared NR cell (`netem.nr.cell`): UEs of one gNB take turns in its slots (fake clock, no
root)."""

from __future__ import annotations

import itertools

import pytest

from netem.nr.cell import Cell, CellError
from netem.nr.radio import Radio
from netem.nr.ue import Slots
from netem.profile import LinkProfile
from netem.relay.direction import build_pipeline


def ue(radio: Radio, cell: Cell, seed: int) -> Slots:
    pipeline = build_pipeline(LinkProfile(radio=radio, queue_packets=None), seed=seed)
    slots = pipeline.stage("slots")
    assert isinstance(slots, Slots)
    cell.join(slots)
    return slots


def drive(stages: list[Slots], arrivals: list[list[tuple[float, bytes]]], until: float) -> list:
    """Push each UE's packets at their times and collect (UE, arrival, left, size)."""
    events = sorted((t, i, p) for i, a in enumerate(arrivals) for t, p in a)
    out: list[tuple[int, float, float, int]] = []
    born: dict[int, float] = {}

    def collect(now: float) -> None:
        for i, s in enumerate(stages):
            for p in s.pop_ready(now):
                out.append((i, born[id(p)], now, len(p)))

    k = 0
    while True:
        dues = [d for s in stages if (d := s.next_due()) is not None]
        due = min(dues) if dues else None
        if k < len(events) and (due is None or events[k][0] < due):
            t, i, p = events[k]
            born[id(p)] = t
            stages[i].push(p, t)
            k += 1
            continue
        if due is None or due > until:
            return out
        collect(due)


def saturating(n: int, size: int = 1500) -> list[tuple[float, bytes]]:
    return [(0.0, bytes(size)) for _ in range(n)]


def goodput(out: list, who: int, start: float, end: float) -> float:
    return sum(size for i, _, t, size in out if i == who and start < t <= end) * 8 / (end - start)


@pytest.mark.parametrize("scheduler", ["rr", "pf"])
def test_two_saturating_ues_each_get_about_half_of_the_cell(scheduler: str) -> None:
    radio = Radio(ul_access="ideal")
    cell = Cell(scheduler)
    a, b = ue(radio, cell, 1), ue(radio, cell, 2)
    out = drive([a, b], [saturating(4000), saturating(4000)], until=1.0)
    total = radio.rate_bps("uplink")
    got = [goodput(out, i, 0.1, 0.9) for i in (0, 1)]
    assert sum(got) == pytest.approx(total, rel=0.03)
    for g in got:
        assert 0.4 <= g / sum(got) <= 0.6


def test_one_ue_alone_gets_the_whole_cell_and_a_light_one_barely_slows_it() -> None:
    radio = Radio()  # scheduling requests and grants
    cell = Cell("rr")
    heavy, light = ue(radio, cell, 1), ue(radio, cell, 2)
    sparse = [(0.5 + 0.04 * i, bytes(92)) for i in range(10)]
    out = drive([heavy, light], [saturating(6000), sparse], until=2.0)
    assert goodput(out, 0, 0.1, 0.45) == pytest.approx(radio.rate_bps("uplink"), rel=0.03)
    # The light UE's probes still arrive in the closed form's time: its share is small.
    oracle = radio.oracle("uplink", size_bytes=92)
    delays = [t - a for i, a, t, _ in out if i == 1]
    assert len(delays) == 10
    assert all(oracle.minimum - 0.0005 <= d <= oracle.maximum + 0.0005 for d in delays)
    assert goodput(out, 0, 0.5, 0.9) > 0.97 * radio.rate_bps("uplink")


def test_proportional_fair_gives_the_better_channel_more_bytes_and_equal_time() -> None:
    cell = Cell("pf")
    good = ue(Radio(ul_access="ideal", mcs=27), cell, 1)
    poor = ue(Radio(ul_access="ideal", mcs=5), cell, 2)
    out = drive([good, poor], [saturating(6000), saturating(6000)], until=1.0)
    g, p = goodput(out, 0, 0.1, 0.9), goodput(out, 1, 0.1, 0.9)
    full_g = Radio(mcs=27, ul_access="ideal").rate_bps("uplink")
    full_p = Radio(mcs=5, ul_access="ideal").rate_bps("uplink")
    # Each gets about half the air time, so about half of what it would alone.
    assert g / full_g == pytest.approx(0.5, abs=0.1)
    assert p / full_p == pytest.approx(0.5, abs=0.1)


def test_a_ue_of_another_tdd_period_cannot_join() -> None:
    cell = Cell()
    ue(Radio(), cell, 1)
    with pytest.raises(CellError, match="another TDD period"):
        ue(Radio(slots="DDSU", special=(10, 4, 0), sr_period_slots=4, sr_offset=3), cell, 2)
    with pytest.raises(CellError, match="scheduler must be one of rr, pf"):
        Cell("fifo")


def test_two_ues_retransmissions_never_overbook_an_occasion() -> None:
    # Both UEs saturate the cell and lose 30% of their blocks: each retransmission must find
    # a share of an occasion that the other UE's retransmissions left free, so no occasion's
    # reservations add up to more than its PRBs (before each UE looked at its own only: 24
    # such occasions in this drive).
    radio = Radio(ul_access="ideal", bler=0.3, max_retx=4)
    cell = Cell("rr")
    a, b = ue(radio, cell, 1), ue(radio, cell, 2)
    out = drive([a, b], [saturating(3000), saturating(3000)], until=1.0)
    assert out and cell.overbooked == 0
    assert sum(a.retransmissions[1:]) > 100 and sum(b.retransmissions[1:]) > 100


def test_rlc_retransmissions_go_ahead_of_new_data() -> None:
    # A saturated UE loses blocks for good (BLER 30%, two HARQ retries: 2.7% of blocks); RLC-AM
    # sends their packets again ahead of the backlog, so PDCP's in-order delivery never waits
    # for the buffer to drain: every packet leaves, with no long gap (at the back
    # of the buffer, nothing left for the rest of the drive after the first residual loss).
    radio = Radio(ul_access="ideal", bler=0.3, max_retx=2)
    pipeline = build_pipeline(LinkProfile(radio=radio, queue_packets=None), seed=4)
    slots = pipeline.stage("slots")
    assert isinstance(slots, Slots)
    packets = [(0.0, i.to_bytes(4, "big") + bytes(1496)) for i in range(2500)]
    out = drive([slots], [packets], until=5.0)
    assert slots.recovered > 5
    assert len(out) == len(packets)
    times = [t for _, _, t, _ in out]
    assert max(b - a for a, b in itertools.pairwise(times)) < 0.1
