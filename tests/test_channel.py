"""The per-UE channel model (`netem.nr.channel`) against the spec's formulas written out here.

The reference path loss below is TR 38.901 Table 7.4.1-1 typed again from the table, not
imported from the module; numbers are checked against hand-computed values at a few points and
against the formulas over a grid. The random parts (LOS state, shadowing) are checked by their
statistics over independent draws and their correlation at the decorrelation distance.
"""

from __future__ import annotations

import itertools
import math
import random
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from netem.nr.channel import (
    CQI_SINR_DB,
    CQI_TABLE_1,
    Channel,
    ChannelError,
    Gudmundson,
    RadioSample,
    RadioTrace,
    RadioTraceError,
    Site,
    bler,
    breakpoint_m,
    cqi_from_sinr,
    los_probability,
    mcs_from_cqi,
    mcs_threshold_db,
    path_loss_db,
)
from netem.nr.phy import MCS_TABLE_1

FC = 3.5  # GHz
H_UT = 1.5


def ref_path_loss(model: str, los: bool, d2d: float, h_bs: float, h_ut: float, fc: float) -> float:
    """TR 38.901 Table 7.4.1-1, UMa and UMi-Street Canyon, typed from the table."""
    d2d = max(d2d, 10.0)
    d3d = math.sqrt(d2d**2 + (h_bs - h_ut) ** 2)
    d_bp = 4 * (h_bs - 1.0) * (h_ut - 1.0) * fc * 1e9 / 3e8
    if model == "uma":
        pl1 = 28.0 + 22 * math.log10(d3d) + 20 * math.log10(fc)
        pl2 = (
            28.0
            + 40 * math.log10(d3d)
            + 20 * math.log10(fc)
            - 9 * math.log10(d_bp**2 + (h_bs - h_ut) ** 2)
        )
        nlos = 13.54 + 39.08 * math.log10(d3d) + 20 * math.log10(fc) - 0.6 * (h_ut - 1.5)
    else:
        pl1 = 32.4 + 21 * math.log10(d3d) + 20 * math.log10(fc)
        pl2 = (
            32.4
            + 40 * math.log10(d3d)
            + 20 * math.log10(fc)
            - 9.5 * math.log10(d_bp**2 + (h_bs - h_ut) ** 2)
        )
        nlos = 35.3 * math.log10(d3d) + 22.4 + 21.3 * math.log10(fc) - 0.3 * (h_ut - 1.5)
    pl_los = pl1 if d2d <= d_bp else pl2
    return pl_los if los else max(pl_los, nlos)


# --- path loss ---------------------------------------------------------------------------


def test_uma_los_at_100_m_is_the_first_slope_by_hand() -> None:
    # d3D = sqrt(100^2 + 23.5^2) = 102.724 m; 28 + 22 log10(102.724) + 20 log10(3.5)
    # = 28 + 44.2571 + 10.8814 = 83.138 dB
    d3d = math.sqrt(100**2 + 23.5**2)
    by_hand = 28 + 22 * math.log10(d3d) + 20 * math.log10(3.5)
    assert by_hand == pytest.approx(83.138, abs=1e-3)
    assert path_loss_db("uma", True, 100.0, 25.0, H_UT, FC) == pytest.approx(by_hand, abs=1e-9)


def test_breakpoints_and_the_second_slope() -> None:
    # d'BP = 4 (25 - 1)(1.5 - 1) 3.5e9 / 3e8 = 560 m (UMa); 4 (10 - 1)(0.5) 3.5e9 / 3e8 = 210 m
    assert breakpoint_m(25.0, H_UT, FC) == pytest.approx(560.0)
    assert breakpoint_m(10.0, H_UT, FC) == pytest.approx(210.0)
    d3d = math.sqrt(1000**2 + 23.5**2)
    second = 28 + 40 * math.log10(d3d) + 20 * math.log10(3.5) - 9 * math.log10(560**2 + 23.5**2)
    assert path_loss_db("uma", True, 1000.0, 25.0, H_UT, FC) == pytest.approx(second, abs=1e-9)
    # The two slopes meet at the breakpoint (the table's fit is continuous there).
    for model, h_bs, d_bp in (("uma", 25.0, 560.0), ("umi", 10.0, 210.0)):
        below = path_loss_db(model, True, d_bp - 1e-6, h_bs, H_UT, FC)
        above = path_loss_db(model, True, d_bp + 1e-6, h_bs, H_UT, FC)
        assert above == pytest.approx(below, abs=1e-4)


@pytest.mark.parametrize("model", ["uma", "umi"])
@pytest.mark.parametrize("fc", [0.7, 2.1, 3.5, 6.0])
@pytest.mark.parametrize("h_ut", [1.5, 10.0, 22.5])
def test_path_loss_matches_the_table_and_nlos_is_never_below_los(
    model: str, fc: float, h_ut: float
) -> None:
    h_bs = 25.0 if model == "uma" else 10.0 + h_ut  # a UMi mast above a high UE too
    for d2d in np.geomspace(1.0, 5000.0, 200):
        los = path_loss_db(model, True, d2d, h_bs, h_ut, fc)
        nlos = path_loss_db(model, False, d2d, h_bs, h_ut, fc)
        assert los == pytest.approx(ref_path_loss(model, True, d2d, h_bs, h_ut, fc), abs=1e-9)
        assert nlos == pytest.approx(ref_path_loss(model, False, d2d, h_bs, h_ut, fc), abs=1e-9)
        assert nlos >= los


def test_umi_nlos_by_hand_and_distances_below_10_m_are_held_at_10_m() -> None:
    d3d = math.sqrt(150**2 + 8.5**2)
    nlos = 35.3 * math.log10(d3d) + 22.4 + 21.3 * math.log10(3.5)  # 110.84 dB
    los = 32.4 + 21 * math.log10(d3d) + 20 * math.log10(3.5)  # 89.03 dB
    assert path_loss_db("umi", False, 150.0, 10.0, H_UT, FC) == pytest.approx(max(los, nlos))
    assert path_loss_db("umi", True, 150.0, 10.0, H_UT, FC) == pytest.approx(los)
    for model in ("uma", "umi"):
        at_10 = path_loss_db(model, True, 10.0, 25.0, H_UT, FC)
        assert path_loss_db(model, True, 0.0, 25.0, H_UT, FC) == at_10
        assert path_loss_db(model, True, 5.0, 25.0, H_UT, FC) == at_10


# --- LOS probability ---------------------------------------------------------------------


def test_los_probability_per_table_7_4_2_1() -> None:
    for model in ("uma", "umi"):
        assert los_probability(model, 0.0) == 1.0
        assert los_probability(model, 18.0) == 1.0
        assert los_probability(model, 18.01) < 1.0
    d = 100.0
    assert los_probability("uma", d) == pytest.approx(
        18 / d + math.exp(-d / 63) * (1 - 18 / d)
    )  # 0.3477
    assert los_probability("umi", d) == pytest.approx(
        18 / d + math.exp(-d / 36) * (1 - 18 / d)
    )  # 0.2310
    # A UE at 18 m height (C'(hUT) = 0.5^1.5) in UMa at 200 m:
    c = ((18 - 13) / 10) ** 1.5
    d = 200.0
    base = 18 / d + math.exp(-d / 63) * (1 - 18 / d)
    expected = base * (1 + c * 5 / 4 * (d / 100) ** 3 * math.exp(-d / 150))
    assert los_probability("uma", d, 18.0) == pytest.approx(expected)
    distances = np.linspace(18.0, 2000.0, 500)
    for model in ("uma", "umi"):
        p = [los_probability(model, float(x)) for x in distances]
        assert all(a >= b for a, b in itertools.pairwise(p))


def circle(radius: float, angle: float, cx: float = 0.0, cy: float = 0.0) -> tuple[float, float]:
    return cx + radius * math.cos(angle), cy + radius * math.sin(angle)


@pytest.mark.parametrize(("model", "radius"), [("uma", 100.0), ("uma", 300.0), ("umi", 60.0)])
def test_auto_los_draws_the_table_probability_over_independent_places(
    model: str, radius: float
) -> None:
    # On a circle around the site, alternating between (nearly) opposite points: 2 radii
    # apart, 2.4 or more LOS-state correlation distances, so the draws are nearly independent
    # and land anywhere between the field's knots.
    ch = Channel([Site("a", 0.0, 0.0)], model=model, los="auto", seed=3)
    n = 4000
    los = []
    for k in range(n):
        x, y = circle(radius, k * (math.pi + 0.01))
        los.append(ch.step(float(k), x, y, "a").los["a"])
    p = los_probability(model, radius)
    assert np.mean(los) == pytest.approx(p, abs=4 * math.sqrt(p * (1 - p) / n))


def test_auto_los_is_held_along_the_route() -> None:
    # 5 km on a 100 m circle in 1 m steps: 100 LOS-state correlation distances. A fresh draw at
    # every metre would switch ~2 p (1 - p) 5000 ~ 2300 times.
    ch = Channel([Site("a", 0.0, 0.0)], model="uma", los="auto", seed=5)
    states = []
    for k in range(5000):
        x, y = circle(100.0, k / 100.0)
        states.append(ch.step(float(k), x, y, "a").los["a"])
    switches = sum(a != b for a, b in itertools.pairwise(states))
    assert 2 <= switches <= 2 * 100 + 2
    assert 0.1 < np.mean(states) < 0.7


# --- shadowing ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("model", "los", "sigma", "d_corr"),
    [("uma", "los", 4.0, 37.0), ("uma", "nlos", 6.0, 50.0), ("umi", "nlos", 7.82, 13.0)],
)
def test_shadowing_has_the_table_sigma_and_correlation(
    model: str, los: str, sigma: float, d_corr: float
) -> None:
    """On a circle around one site the path loss is constant, so RSRP - mean = -shadowing.

    Pairs of steps one decorrelation distance apart (an arc whose chord is d_corr), then a
    jump to the opposite side of the circle (600 m: e^-12 or less of correlation left)."""
    radius = 300.0
    ch = Channel([Site("a", 0.0, 0.0)], model=model, los=los, seed=11)
    half_angle = 2 * math.asin(d_corr / (2 * radius))
    first, second = [], []
    for k in range(4000):
        base = k * (math.pi + 0.001)
        first.append(ch.step(2.0 * k, *circle(radius, base), "a").rsrp_dbm["a"])
        second.append(ch.step(2.0 * k + 1, *circle(radius, base + half_angle), "a").rsrp_dbm["a"])
    a, b = np.array(first), np.array(second)
    assert np.std(a) == pytest.approx(sigma, rel=0.05)
    assert np.corrcoef(a, b)[0, 1] == pytest.approx(math.exp(-1.0), abs=0.05)
    # and the independent draws are independent:
    assert abs(np.corrcoef(a[:-1], a[1:])[0, 1]) < 0.06


def test_gudmundson_lag_correlation_is_exponential_in_distance() -> None:
    process = Gudmundson(6.0, 50.0, random.Random(1))
    values = np.array([process.advance(5.0) for _ in range(100_000)])
    assert np.std(values) == pytest.approx(6.0, rel=0.03)
    for lag, expected in ((10, math.exp(-1.0)), (20, math.exp(-2.0))):  # 50 m and 100 m
        r = np.corrcoef(values[:-lag], values[lag:])[0, 1]
        assert r == pytest.approx(expected, abs=0.04)
    still = process.value_db
    assert process.advance(0.0) == still  # not moving keeps the value


# --- CQI, MCS, BLER ----------------------------------------------------------------------


def test_cqi_is_monotone_in_sinr_and_meets_its_thresholds() -> None:
    sinrs = np.linspace(-15.0, 35.0, 2001)
    cqis = [cqi_from_sinr(float(s)) for s in sinrs]
    assert all(a <= b for a, b in itertools.pairwise(cqis))
    assert cqis[0] == 0 and cqis[-1] == 15
    assert list(CQI_SINR_DB) == sorted(CQI_SINR_DB)
    assert CQI_SINR_DB[0] == pytest.approx(-6.7) and CQI_SINR_DB[-1] == pytest.approx(22.7)
    for cqi, threshold in enumerate(CQI_SINR_DB, start=1):
        assert cqi_from_sinr(threshold) == cqi
        assert cqi_from_sinr(threshold - 1e-6) == cqi - 1


def test_cqi_to_mcs_takes_the_largest_efficiency_not_above_the_cqi() -> None:
    # TS 38.214: CQI 15 is 64QAM at 948/1024 (5.5547 b/RE), exactly MCS 28's (Table
    # 5.1.3.1-1: 64QAM, 948). Table 1's MCSs were laid out so CQI k >= 2 lands on every other
    # MCS; CQI 1 (QPSK 78, 0.15 b/RE) is below MCS 0 (QPSK 120) and falls back to MCS 0.
    expected = {0: 0, 1: 0, 2: 0, 3: 2, 4: 4, 5: 6, 6: 8, 7: 11, 8: 13, 9: 15, 10: 18, 11: 20}
    expected |= {12: 22, 13: 24, 14: 26, 15: 28}
    assert {c: mcs_from_cqi(c) for c in range(16)} == expected
    for cqi in range(2, 16):
        qm, rate = CQI_TABLE_1[cqi - 1]
        target = qm * rate / 1024
        effs = [q * r / 1024 for q, r in MCS_TABLE_1]
        chosen = effs[mcs_from_cqi(cqi)]
        assert chosen <= target + 1e-12
        assert not any(chosen < e <= target for e in effs)
    with pytest.raises(ChannelError, match=r"cqi must be 0\.\.15"):
        mcs_from_cqi(16)


def test_bler_is_a_tenth_at_each_mcs_threshold_and_falls_with_sinr() -> None:
    assert mcs_threshold_db(0) == pytest.approx(-4.7)  # MCS 0 has CQI 2's efficiency
    assert mcs_threshold_db(28) == pytest.approx(22.7)  # MCS 28 has CQI 15's
    assert mcs_threshold_db(18) == pytest.approx(11.7)  # MCS 18 has CQI 10's
    for mcs in range(len(MCS_TABLE_1)):
        threshold = mcs_threshold_db(mcs)
        assert bler(mcs, threshold) == pytest.approx(0.1, abs=1e-12)
        near = [bler(mcs, threshold + dx) for dx in np.linspace(-8, 8, 81)]
        assert all(a > b for a, b in itertools.pairwise(near))
        far = [bler(mcs, threshold + dx) for dx in np.linspace(-30, 30, 121)]
        assert all(a >= b for a, b in itertools.pairwise(far))
        assert 0.0 <= far[-1] < 1e-10 and 1.0 - 1e-10 < far[0] <= 1.0
    # 1 / (1 + 9 e^(2 * 1 dB)) one dB above the threshold:
    assert bler(18, 12.7) == pytest.approx(1 / (1 + 9 * math.exp(2.0)))
    assert bler(18, 1e6) == 0.0 and bler(18, -1e6) == 1.0  # no overflow


# --- the channel end to end ---------------------------------------------------------------


def test_rsrp_and_sinr_of_two_sites_without_shadowing() -> None:
    a, b = Site("a", 0.0, 0.0), Site("b", 400.0, 0.0)
    ch = Channel([a, b], model="uma", los="los", shadowing=False)
    x, y = 120.0, 40.0
    s = ch.step(0.0, x, y, "a")
    pl_a = ref_path_loss("uma", True, math.hypot(x, y), 25.0, H_UT, FC)
    pl_b = ref_path_loss("uma", True, math.hypot(x - 400.0, y), 25.0, H_UT, FC)
    per_re = 10 * math.log10(12 * 273)  # 100 MHz at 30 kHz: 273 PRBs
    assert s.rsrp_dbm["a"] == pytest.approx(46 - per_re - pl_a)
    assert s.rsrp_dbm["b"] == pytest.approx(46 - per_re - pl_b)
    # Over the whole channel: S / (I + N), N = -174 + 10 log10(100 MHz) + 9 dB = -85 dBm.
    s_mw, i_mw = 10 ** ((46 - pl_a) / 10), 10 ** ((46 - pl_b) / 10)
    n_mw = 10 ** ((-174 + 80 + 9) / 10)
    sinr = 10 * math.log10(s_mw / (i_mw + n_mw))
    assert s.sinr_db == pytest.approx(sinr)
    assert s.cqi == cqi_from_sinr(sinr) and s.mcs == mcs_from_cqi(s.cqi)
    assert s.bler == pytest.approx(bler(s.mcs, sinr))
    assert s.los == {"a": True, "b": True} and s.strongest == "a"
    # Served by the far cell the SINR is the mirror image.
    s_b = ch.step(0.0, x, y, "b")
    assert s_b.sinr_db == pytest.approx(10 * math.log10(i_mw / (s_mw + n_mw)))
    # Alone, only noise: SNR = 46 - PL + 85.
    alone = Channel([a], model="uma", los="los", shadowing=False).step(0.0, x, y, "a")
    assert alone.sinr_db == pytest.approx(46 - pl_a + 85)


def test_another_carrier_does_not_interfere() -> None:
    a, b = Site("a", 0.0, 0.0), Site("b", 400.0, 0.0, carrier_ghz=3.7)
    with_b = Channel([a, b], los="los", shadowing=False).step(0.0, 100.0, 0.0, "a")
    alone = Channel([a], los="los", shadowing=False).step(0.0, 100.0, 0.0, "a")
    assert with_b.sinr_db == pytest.approx(alone.sinr_db)


def route(ch: Channel, n: int = 300) -> list[RadioSample]:
    return [ch.step(0.1 * k, 3.0 * k, 20.0 + 0.5 * k, "a") for k in range(n)]


def test_same_seed_same_trace_other_seed_another() -> None:
    sites = [Site("a", 0.0, 0.0), Site("b", 500.0, 100.0), Site("c", 250.0, 400.0)]
    first = route(Channel(sites, model="umi", seed=7, ue="car1"))
    again = route(Channel(sites, model="umi", seed=7, ue="car1"))
    assert first == again
    other = route(Channel(sites, model="umi", seed=8, ue="car1"))
    assert [s.rsrp_dbm for s in other] != [s.rsrp_dbm for s in first]
    other_ue = route(Channel(sites, model="umi", seed=7, ue="car2"))
    assert [s.rsrp_dbm for s in other_ue] != [s.rsrp_dbm for s in first]
    # One random stream per (UE, site): the order the sites are listed in does not matter.
    shuffled = route(Channel(sites[::-1], model="umi", seed=7, ue="car1"))
    assert [dict(s.rsrp_dbm) for s in shuffled] == [dict(s.rsrp_dbm) for s in first]
    # The samples follow the positions, not the clock.
    ch = Channel(sites, model="umi", seed=7, ue="car1")
    slow = [ch.step(10.0 * k, 3.0 * k, 20.0 + 0.5 * k, "a") for k in range(300)]
    assert [s.rsrp_dbm for s in slow] == [s.rsrp_dbm for s in first]


# --- bad input -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Channel([Site("north", 5, 5), Site("south", 5, 5)]),
         "sites north and south are at the same place"),
        (lambda: Channel([Site("a", 0, 0)], model="rma"),
         r"unknown model 'rma' \(known: uma, umi\)"),
        (lambda: Channel([Site("a", 0, 0)], los="maybe"),
         r"unknown los mode 'maybe' \(known: los, nlos, auto\)"),
        (lambda: Channel([Site("a", 0, 0), Site("a", 1, 0)]), "two sites are named 'a'"),
        (lambda: Channel([]), "at least one site"),
        (lambda: Channel([Site("a", 0, 0)], ue_height_m=30.0),
         r"ue_height_m must be 1\.5\.\.22\.5 m"),
        (lambda: Channel([Site("a", 0, 0, height_m=1.0)]), r"site a \(1 m\) must stand higher"),
        (lambda: Site("a", 0, 0, height_m=-3.0), "site a: height_m must be > 0 m, got -3"),
        (lambda: Site("a", 0, 0, bandwidth_mhz=33), r"bandwidth_mhz must be one of 5, 10.*got 33"),
        (lambda: Site("a", 0, 0, carrier_ghz=28.0), r"carrier_ghz must be 0\.5\.\.7\.125 GHz"),
        (lambda: Site("a", math.nan, 0), "site a: x must be a finite number"),
        (lambda: Site("", 0, 0), "a site needs a name"),
        (lambda: path_loss_db("inh", True, 10, 3, 1.5, 3.5), r"known: uma, umi"),
    ],
)  # fmt: skip
def test_bad_input_says_what_is_wrong(make: Callable[[], object], message: str) -> None:
    with pytest.raises(ChannelError, match=message):
        make()


def test_bad_steps_say_what_is_wrong() -> None:
    ch = Channel([Site("a", 0, 0), Site("b", 300, 0)])
    with pytest.raises(ChannelError, match=r"no site named 'c' \(sites: a, b\)"):
        ch.step(0.0, 10.0, 10.0, "c")
    ch.step(1.0, 10.0, 10.0, "a")
    with pytest.raises(ChannelError, match="time went back"):
        ch.step(0.5, 10.0, 10.0, "a")


# --- recorded traces ----------------------------------------------------------------------

GOOD = """\
time_s,ue,rsrp_dbm,sinr_db,mcs,cell
# a drive past two cells
0.0,car1,-80.5,12.0,18,gnb1
0.0,car2,-95,3.5,7,gnb2
0.5,car1,-82,11.0,17,gnb1

1.0,car1,-90,2,6,gnb2
"""


def test_a_trace_splits_per_ue_and_holds_each_sample(tmp_path: Path) -> None:
    path = tmp_path / "trace.csv"
    path.write_text(GOOD)
    trace = RadioTrace.load(path)
    assert trace.ues == ("car1", "car2")
    assert [s.t for s in trace.samples["car1"]] == [0.0, 0.5, 1.0]
    first = trace.samples["car1"][0]
    assert (first.rsrp_dbm, first.sinr_db, first.mcs, first.cell) == (-80.5, 12.0, 18, "gnb1")
    assert trace.at("car1", 0.7).mcs == 17
    assert trace.at("car1", 1.0).cell == "gnb2"
    assert trace.at("car1", -0.1) is None
    no_cell = RadioTrace.parse("time_s,ue,rsrp_dbm,sinr_db,mcs\n0,u,-100,0,3\n", "t.csv")
    assert no_cell.samples["u"][0].cell is None
    with pytest.raises(ChannelError, match="no UE 'car3'"):
        trace.at("car3", 0.0)


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("0,a,-80,12,18\n1,a,-80,12,18\n2,a,-80,12,18\n3,a,-80,12,18\n4,a,-80,12,18\n5,a,-80,x,18\n",
         "trace.csv:7: sinr_db: expected a number, got 'x'"),
        ("0,a,-80,12\n",
         r"trace.csv:2: expected 5 columns \(time_s,ue,rsrp_dbm,sinr_db,mcs\), got 4"),
        ("0,a,-80,12,29\n", r"trace.csv:2: mcs: expected a whole number 0\.\.28 .*got '29'"),
        ("0,a,-80,12,1.5\n", "trace.csv:2: mcs: expected a whole number"),
        ("0,a,-20,12,3\n", r"trace.csv:2: rsrp_dbm: -20 is outside the -156\.\.-31 dBm"),
        ("0,a,-80,45,3\n", r"trace.csv:2: sinr_db: 45 is outside the -23\.\.40 dB"),
        ("-1,a,-80,12,3\n", "trace.csv:2: time_s: -1 is negative"),
        ("0,,-80,12,3\n", "trace.csv:2: ue: empty"),
        ("1,a,-80,12,3\n1,a,-80,12,3\n",
         r"trace.csv:3: time_s: 1 is not after UE a's previous sample \(1\)"),
        ("", "trace.csv: no samples after the header"),
    ],
)  # fmt: skip
def test_bad_traces_name_file_line_and_field(tmp_path: Path, body: str, message: str) -> None:
    path = tmp_path / "trace.csv"
    path.write_text("time_s,ue,rsrp_dbm,sinr_db,mcs\n" + body)
    with pytest.raises(RadioTraceError, match=message):
        RadioTrace.load(path)


def test_trace_header_missing_file_and_many_problems(tmp_path: Path) -> None:
    path = tmp_path / "trace.csv"
    path.write_text("t,ue,rsrp,sinr,mcs\n0,a,-80,12,3\n")
    with pytest.raises(RadioTraceError, match=r"trace\.csv:1: header: expected 'time_s,ue,"):
        RadioTrace.load(path)
    path.write_text("")
    with pytest.raises(RadioTraceError, match=r"trace\.csv:1: header: the trace is empty"):
        RadioTrace.load(path)
    with pytest.raises(ChannelError, match="cannot read the radio trace"):
        RadioTrace.load(tmp_path / "missing.csv")
    many = "time_s,ue,rsrp_dbm,sinr_db,mcs\n" + "0,a,-80,12,x\n" * 9
    with pytest.raises(RadioTraceError) as err:
        RadioTrace.parse(many, "many.csv")
    assert len(err.value.problems) == 6
    assert err.value.problems[-1] == "many.csv: 4 more problem(s)"
