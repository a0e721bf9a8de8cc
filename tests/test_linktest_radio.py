"""The link self-test's radio figures, checked against scipy's own statistics and the
binomial: the distance of measured delays from the oracle, the HARQ shares, the per-slot
goodput, the timer floor and the lines that print them."""

from __future__ import annotations

import random

import numpy as np
import pytest
from scipy import stats

from netem.nr.radio import RADIO_PROFILES
from nodes.recording import linktable
from testbed.hostload import lateness_floor, timer_floor
from testbed.linktest import (
    CDF_QUANTILES,
    HARQ_SIGMAS,
    harq_shares,
    oracle_comparison,
    sampling_chance,
    slot_goodput,
)

OAI = RADIO_PROFILES["oai-tdd-30k"]


def _draws(n: int, shift_ms: float = 0.0, seed: int = 3) -> tuple[list[float], object]:
    oracle = OAI.oracle("uplink", size_bytes=92)
    rng = random.Random(seed)
    return [oracle.quantile(rng.random()) * 1000 + shift_ms for _ in range(n)], oracle


def test_delays_drawn_from_the_oracle_are_near_it_and_scipy_agrees() -> None:
    delays, oracle = _draws(2000)
    got = oracle_comparison(delays, oracle)  # type: ignore[arg-type]
    cdf = np.vectorize(lambda v: oracle.cdf(v / 1000))  # type: ignore[attr-defined]
    ks = stats.kstest(delays, cdf).statistic
    assert got["ks"] == pytest.approx(ks, abs=1e-9)
    fine = [oracle.quantile((i + 0.5) / 20000) * 1000 for i in range(20000)]  # type: ignore[attr-defined]
    assert got["w1_ms"] == pytest.approx(stats.wasserstein_distance(delays, fine), abs=0.02)
    assert got["w1_ms"] < 0.1 and got["ks"] < 0.05
    assert got["samples"] == 2000 and len(got["measured_ms"]) == len(CDF_QUANTILES) == 99
    assert got["oracle_ms"] == sorted(got["oracle_ms"])


def test_delays_a_slot_late_are_a_slot_from_the_oracle() -> None:
    delays, oracle = _draws(1000, shift_ms=0.5)
    got = oracle_comparison(delays, oracle)  # type: ignore[arg-type]
    assert got["w1_ms"] == pytest.approx(0.5, abs=0.05)
    assert got["ks"] > 0.05


def test_the_chance_distance_of_a_few_probes_matches_scipy_draws() -> None:
    # Draws made independently (inverse CDF with Python's RNG), their W1 from a fine
    # quantile grid computed by scipy: the 99th percentile over 200 draws of 100 probes.
    oracle = OAI.oracle("uplink", size_bytes=92)
    fine = [oracle.quantile((i + 0.5) / 4000) for i in range(4000)]
    rng = random.Random(11)
    scipy_w1 = [
        stats.wasserstein_distance([fine[int(rng.random() * 4000)] for _ in range(100)], fine)
        for _ in range(200)
    ]
    chance = sampling_chance(oracle, 100)  # type: ignore[arg-type]
    ours = chance.w1_s
    assert ours == pytest.approx(float(np.quantile(scipy_w1, 0.99)), rel=0.25)
    # The chance distance falls as 1 / sqrt(n).
    assert sampling_chance(oracle, 400).w1_s / ours == pytest.approx(0.5, abs=0.12)  # type: ignore[arg-type]
    # OAI's 5 ms HARQ tail makes 100 probes alone miss 0.5 ms often: why the tolerance has it.
    assert ours > 0.0005
    # The median of 100 probes: its spread against scipy's draws of the same kind.
    medians = [
        abs(float(np.median([fine[int(rng.random() * 4000)] for _ in range(100)])) - fine[2000])
        for _ in range(200)
    ]
    assert chance.median_s == pytest.approx(float(np.quantile(medians, 0.99)), rel=0.3)


def _counts(tries: list[int], blocks: int | None = None, out: int = 0) -> dict[str, object]:
    return {
        "retransmissions": tries,
        "blocks": sum(tries) if blocks is None else blocks,
        "bytes_out": out,
    }


def test_harq_shares_count_blocks_between_two_reads() -> None:
    before = _counts([100, 10, 1, 0, 0, 0])
    after = _counts([1000, 110, 11, 1, 0, 0])
    got = harq_shares(before, after, bler=0.1, max_retx=4)
    assert got["blocks"] == 900 + 100 + 10 + 1
    assert got["shares"][0] == pytest.approx(900 / 1011)
    assert got["first_failed"] == pytest.approx(111 / 1011)
    assert got["expected"][:3] == pytest.approx([0.9, 0.09, 0.009])
    assert got["expected"][-1] == pytest.approx(0.1**5)  # given up on after 4 retries
    assert sum(got["expected"]) == pytest.approx(1.0)


def test_the_harq_bound_holds_a_true_bler_and_refuses_a_wrong_one() -> None:
    rng = random.Random(11)
    n = 5000
    failed = sum(rng.random() < 0.1 for _ in range(n))
    got = harq_shares(_counts([0] * 6), _counts([n - failed, failed, 0, 0, 0, 0]), 0.1, 4)
    assert abs(got["first_failed"] - 0.1) <= got["bound"]
    # the bound is HARQ_SIGMAS binomial deviations: a 20% BLER is far outside it
    assert got["bound"] == pytest.approx(HARQ_SIGMAS * (0.09 / n) ** 0.5 + 1 / n)
    assert abs(0.2 - 0.1) > got["bound"]


def test_slot_goodput_counts_the_occasions_new_blocks_and_resends_took() -> None:
    grid = OAI.grid("uplink")
    # 500 new blocks: 440 decoded first time, 50 after one resend, 8 after two, 2 given up
    # on after all four: 50 + 16 + 8 = 74 resends, so 574 occasions used, in 1 s.
    before = {**_counts([0] * 6, blocks=100), "t": 10.0}
    after = {**_counts([440, 50, 8, 0, 0, 2], blocks=600, out=1_148_000), "t": 11.0}
    got = slot_goodput(before, after, grid, 0.1)
    assert (got["blocks"], got["occasions"]) == (500, 574)
    assert got["bytes_per_occasion"] == pytest.approx(2000.0)
    assert got["bytes_per_block"] == pytest.approx(1_148_000 / 500)
    caps = [o.capacity_bytes for o in grid.occasions]
    assert got["block_bytes"] == pytest.approx(sum(caps) / len(caps))
    assert got["expected_bytes_per_occasion"] == pytest.approx(0.9 * got["block_bytes"])
    assert got["occasions_per_s"] == pytest.approx(len(caps) / grid.period_s)
    assert got["used_share"] == pytest.approx(574 / got["occasions_per_s"])


def test_the_timer_floor_is_the_lateness_of_real_sleeps() -> None:
    floor = timer_floor(count=50)
    assert floor.count == 50 and 0 <= floor.p50_s <= floor.p99_s <= floor.max_s < 0.5
    fixed = lateness_floor([0.001] * 99 + [0.01])
    assert (fixed.p50_s, fixed.p99_s, fixed.max_s) == (0.001, 0.001, 0.01)
    assert "0.001 ms median" not in fixed.text() and "1.000 ms median" in fixed.text()


def test_radio_lines_print_the_cdf_points_harq_and_slots() -> None:
    delays, oracle = _draws(500)
    radio = oracle_comparison(delays, oracle)  # type: ignore[arg-type]
    radio["tolerance_ms"] = 0.5
    radio["harq"] = harq_shares(_counts([0] * 6), _counts([900, 90, 9, 1, 0, 0]), 0.1, 4)
    radio["slots"] = slot_goodput(
        _counts([0], blocks=0), _counts([0], blocks=10, out=25_000), OAI.grid("uplink"), 0.1
    )
    data = {
        "timer_floor": {"p99_ms": 0.143},
        "links": [{"link": "av1-gnb1", "directions": [{"direction": "uplink", "radio": radio}]}],
    }
    lines = linktable.radio_lines(data)
    assert lines[0].startswith("radio av1-gnb1 uplink: W1 ")
    assert "tolerance 0.5 ms; timer floor p99 0.143 ms" in lines[0]
    assert lines[1].split() == ["cdf", "p10", "p25", "p50", "p75", "p90", "p99"]
    measured = [float(x) for x in lines[2].removesuffix("ms").split()[1:]]
    assert measured == pytest.approx(
        [radio["measured_ms"][CDF_QUANTILES.index(q)] for q in linktable.SHOWN_QUANTILES],
        abs=0.006,
    )
    assert "blocks 1000: +0 90% (90), +1 9% (9)" in lines[4]
    assert "lost 0% (0.001)" in lines[4]
    assert lines[5].startswith("  per slot   2500 B per occasion (")
    assert "2500 B per new block, 10 occasions at saturation" in lines[5]
    # a plain link prints no radio lines
    assert linktable.radio_lines({"links": [{"directions": [{"direction": "uplink"}]}]}) == []
