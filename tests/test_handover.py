"""Event-A3 handover (`netem.nr.handover`): where a drive past two cells hands over, against a
geometric oracle computed here, and the time-to-trigger, L3 filter and settings one by one.

The oracle: a UE drives at constant speed along a straight road past two sites with the same
power and model, without shadowing. The neighbour's RSRP minus the serving one's is then the
serving path loss minus the neighbour's, so the A3 entering condition Mn - Hys > Ms + Off first
holds where PL_s(x) - PL_n(x) = Hys + Off, found by bisection on TR 38.901 Table 7.4.1-1 typed
again below. Without an L3 filter the handover must trigger TTT after that point, within one
measurement step.
"""

from __future__ import annotations

import math

import pytest

from netem.nr.channel import Channel, Site
from netem.nr.handover import A3Handover, HandoverDecision, HandoverError, Interruption

H_UT = 1.5
FC = 3.5


def table_path_loss(model: str, los: bool, d2d: float, h_bs: float) -> float:
    """TR 38.901 Table 7.4.1-1 (UMa, UMi-Street Canyon) at 3.5 GHz for a 1.5 m UE."""
    d2d = max(d2d, 10.0)
    dh = h_bs - H_UT
    d3d = math.sqrt(d2d**2 + dh**2)
    d_bp = 4 * (h_bs - 1) * (H_UT - 1) * FC * 1e9 / 3e8
    if model == "uma":
        if d2d <= d_bp:
            pl = 28 + 22 * math.log10(d3d) + 20 * math.log10(FC)
        else:
            pl = 28 + 40 * math.log10(d3d) + 20 * math.log10(FC) - 9 * math.log10(d_bp**2 + dh**2)
        nlos = 13.54 + 39.08 * math.log10(d3d) + 20 * math.log10(FC)
    else:
        if d2d <= d_bp:
            pl = 32.4 + 21 * math.log10(d3d) + 20 * math.log10(FC)
        else:
            pl = (
                32.4
                + 40 * math.log10(d3d)
                + 20 * math.log10(FC)
                - 9.5 * math.log10(d_bp**2 + dh**2)
            )
        nlos = 22.4 + 35.3 * math.log10(d3d) + 21.3 * math.log10(FC)
    return pl if los else max(pl, nlos)


def a3_entry_x(
    model: str, los: bool, h_bs: float, site_b_x: float, road_y: float, margin_db: float
) -> float:
    """Where on the road y = road_y (x from 0 towards site B) PL_A - PL_B first exceeds the
    margin (Hys + Off): bisection, the margin being crossed once between the sites."""

    def gap(x: float) -> float:
        pl_a = table_path_loss(model, los, math.hypot(x, road_y), h_bs)
        pl_b = table_path_loss(model, los, math.hypot(x - site_b_x, road_y), h_bs)
        return pl_a - pl_b - margin_db

    lo, hi = 0.0, site_b_x
    assert gap(lo) < 0 < gap(hi)
    for _ in range(100):
        mid = (lo + hi) / 2
        if gap(mid) > 0:
            hi = mid
        else:
            lo = mid
    return hi


@pytest.mark.parametrize(
    ("model", "los", "h_bs", "ttt_ms", "step_s"),
    [
        ("uma", True, 25.0, 320, 0.04),
        ("uma", True, 25.0, 0, 0.04),
        ("uma", False, 25.0, 640, 0.04),
        ("umi", True, 10.0, 1280, 0.04),
        ("umi", False, 10.0, 100, 0.02),
    ],
)
def test_a_drive_past_two_cells_hands_over_ttt_after_the_a3_point(
    model: str, los: bool, h_bs: float, ttt_ms: int, step_s: float
) -> None:
    speed, road_y, b_x = 15.0, 30.0, 600.0
    offset, hysteresis = 2.0, 1.0
    sites = [Site("A", 0.0, 0.0, height_m=h_bs), Site("B", b_x, 0.0, height_m=h_bs)]
    channel = Channel(sites, model=model, los="los" if los else "nlos", shadowing=False)
    a3 = A3Handover(offset, hysteresis, ttt_ms, filter_k=None, step_s=step_s, serving="A")
    decisions = []
    for k in range(round(b_x / speed / step_s)):
        t = k * step_s
        sample = channel.step(t, speed * t, road_y, a3.serving or "A")
        decision = a3.observe(t, sample.rsrp_dbm)
        if decision is not None:
            decisions.append(decision)
    assert [(d.source, d.target) for d in decisions] == [("A", "B")]
    t_entry = a3_entry_x(model, los, h_bs, b_x, road_y, offset + hysteresis) / speed
    ttt = ttt_ms / 1000
    assert t_entry + ttt - 1e-9 <= decisions[0].t <= t_entry + ttt + step_s + 1e-9
    assert a3.serving == "B"


def test_the_l3_filter_delays_the_handover() -> None:
    sites = [Site("A", 0.0, 0.0), Site("B", 600.0, 0.0)]

    def handover_time(filter_k: int | None) -> float:
        channel = Channel(sites, los="los", shadowing=False)
        a3 = A3Handover(2.0, 1.0, 320, filter_k=filter_k, step_s=0.04, serving="A")
        for k in range(1000):
            t = k * 0.04
            decision = a3.observe(t, channel.step(t, 15.0 * t, 30.0, "A").rsrp_dbm)
            if decision is not None:
                return decision.t
        raise AssertionError("no handover")

    unfiltered, filtered = handover_time(None), handover_time(4)
    assert unfiltered < filtered < unfiltered + 2.0


def feed(a3: A3Handover, rows: list[tuple[float, float, float]]) -> list[HandoverDecision]:
    """(t, serving RSRP, neighbour RSRP) rows with the serving cell `s` and neighbour `n`."""
    out = []
    for t, s, n in rows:
        d = a3.observe(t, {"s": s, "n": n})
        if d is not None:
            out.append(d)
    return out


def test_a_neighbour_better_for_less_than_ttt_never_triggers() -> None:
    # TTT 320 ms at 40 ms steps: better at 7 consecutive measurements (240 ms) then worse,
    # over and over: never a handover.
    a3 = A3Handover(3.0, 1.0, 320, filter_k=None, step_s=0.04, serving="s")
    rows = []
    for k in range(500):
        better = k % 10 < 7
        rows.append((k * 0.04, -80.0, -70.0 if better else -90.0))
    assert feed(a3, rows) == []
    # Better for 9 measurements (0..320 ms): triggers at the ninth, 320 ms after the first.
    a3 = A3Handover(3.0, 1.0, 320, filter_k=None, step_s=0.04, serving="s")
    rows = [(k * 0.04, -80.0, -70.0 if k >= 2 else -90.0) for k in range(20)]
    assert feed(a3, rows) == [HandoverDecision(pytest.approx(0.08 + 0.32), "s", "n")]


def test_the_entering_condition_is_strict() -> None:
    # Mn - Hys = Ms + Off exactly: not entered.
    a3 = A3Handover(3.0, 1.0, 0, filter_k=None, step_s=0.04, serving="s")
    assert feed(a3, [(k * 0.04, -80.0, -76.0) for k in range(50)]) == []
    assert feed(a3, [(2.0, -80.0, -75.5)]) == [HandoverDecision(2.0, "s", "n")]


def test_l3_filter_per_38_331() -> None:
    # k = 4: a = 1/2^(4/4) = 1/2. F1 = M1 = -90, then M = -70: F2 = -80, F3 = -75.
    a3 = A3Handover(filter_k=4, step_s=0.2, l1_period_s=0.2, serving="s")
    assert a3.alpha == pytest.approx(0.5)
    filtered = []
    for k, m in enumerate((-90.0, -70.0, -70.0)):
        a3.observe(k * 0.2, {"s": m})
        filtered.append(a3.filtered["s"])
    assert filtered == pytest.approx([-90.0, -80.0, -75.0])
    # k = 8 (a = 1/4) measured twice per L1 period: two steps do what one step of a period
    # does, (1 - a')^2 = 1 - a.
    fast = A3Handover(filter_k=8, step_s=0.1, l1_period_s=0.2, serving="s")
    for k, m in enumerate((-90.0, -70.0, -70.0)):
        fast.observe(k * 0.1, {"s": m})
    # F after two steps of -70 from -90: -70 + (-20)(1 - a')^2 = -70 - 20 * 0.75 = -85.
    assert fast.filtered["s"] == pytest.approx(-85.0)


def test_measurements_are_taken_every_step_whatever_the_call_rate() -> None:
    a3 = A3Handover(filter_k=4, step_s=0.04, l1_period_s=0.04, serving="s")
    seen = []
    for k in range(20):  # called every 10 ms
        a3.observe(k * 0.01, {"s": -90.0 if k == 0 else -70.0})
        seen.append(a3.filtered["s"])
    # Measured at 0, 40, 80, 120, 160 ms: -90, -80, -75, -72.5, -71.25, held in between.
    expected = [-90.0] * 4 + [-80.0] * 4 + [-75.0] * 4 + [-72.5] * 4 + [-71.25] * 4
    assert seen == pytest.approx(expected)


def test_first_measurement_selects_the_strongest_cell_and_the_strongest_neighbour_wins() -> None:
    a3 = A3Handover(0.0, 0.0, 0, filter_k=None)
    assert a3.serving is None
    assert a3.observe(0.0, {"a": -90.0, "b": -80.0, "c": -85.0}) is None
    assert a3.serving == "b"
    decision = a3.observe(0.04, {"a": -70.0, "b": -80.0, "c": -60.0})
    assert decision == HandoverDecision(0.04, "b", "c")
    assert a3.serving == "c"


def test_a_neighbour_that_goes_unheard_starts_its_ttt_again() -> None:
    a3 = A3Handover(3.0, 1.0, 160, filter_k=None, step_s=0.04, serving="s")
    assert a3.observe(0.00, {"s": -80.0, "n": -70.0}) is None
    assert a3.observe(0.04, {"s": -80.0, "n": -70.0}) is None
    assert a3.observe(0.08, {"s": -80.0}) is None  # lost
    for k in range(3, 7):
        assert a3.observe(k * 0.04, {"s": -80.0, "n": -70.0}) is None
    assert a3.observe(0.28, {"s": -80.0, "n": -70.0}) == HandoverDecision(0.28, "s", "n")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"ttt_ms": 50},
         r"ttt_ms must be one of TS 38.331's TimeToTrigger values 0, 40, 64.*got 50"),
        ({"ttt_ms": 0.32}, "ttt_ms must be one of"),
        ({"hysteresis_db": 0.3}, r"hysteresis_db must be 0\.\.15 dB in 0\.5 dB steps"),
        ({"hysteresis_db": -1.0}, "hysteresis_db must be"),
        ({"offset_db": 20.0}, r"offset_db \(a3-Offset\) must be -15\.\.15 dB"),
        ({"filter_k": 10}, "filter_k must be one of TS 38.331's FilterCoefficient values"),
        ({"step_s": 0.0}, "step_s must be > 0"),
    ],
)  # fmt: skip
def test_bad_settings_say_what_is_wrong(kwargs: dict, message: str) -> None:
    with pytest.raises(HandoverError, match=message):
        A3Handover(**kwargs)


def test_bad_measurements_say_what_is_wrong() -> None:
    a3 = A3Handover(serving="s")
    with pytest.raises(HandoverError, match=r"serving cell s is not among the cells measured"):
        a3.observe(0.0, {"n": -80.0})
    a3 = A3Handover(serving="s")
    a3.observe(1.0, {"s": -80.0})
    with pytest.raises(HandoverError, match="before the previous one"):
        a3.observe(0.5, {"s": -80.0})
    with pytest.raises(HandoverError, match="RSRP of cell s"):
        a3.observe(2.0, {"s": math.nan})


def test_interruption_defaults_and_window() -> None:
    gap = Interruption()
    assert gap.interruption_s == 0.040 and gap.lossless
    assert gap.window(HandoverDecision(12.5, "a", "b")) == pytest.approx((12.5, 12.54))
    with pytest.raises(HandoverError, match=r"interruption_s must be 0\.\.10 s"):
        Interruption(interruption_s=-0.01)
