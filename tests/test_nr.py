"""The NR slot model (`netem.nr`) and the `Slots` stage, with a fake clock (no root).

Transport block sizes are checked against values computed outside this project (MATLAB's 5G
Toolbox, as published in srsRAN's scheduler unit-test data) and one derivation by hand; the
stage's delays against the closed-form oracle with a Kolmogorov-Smirnov test (scipy).
"""

from __future__ import annotations

import dataclasses
import math
import random

import numpy as np
import pytest

from netem.nr.oracle import DelayOracle
from netem.nr.phy import Carrier, NrError, TddPattern, occasions, rate_bps, tbs_bits
from netem.nr.ue import Slots
from netem.relay.direction import build_pipeline

stats = pytest.importorskip("scipy.stats", reason="scipy (in .[test]) runs the KS tests")

#: OpenAirInterface's default band-78 gNB (gnb.sa.band78.fr1.106PRB.usrpb210.conf).
OAI = TddPattern("DDDDDDDSUU", special=(6, 4, 4), numerology=1)
SLOT = 0.0005


def test_the_oai_pattern_gives_uplink_a_fifth_of_the_air_time() -> None:
    assert OAI.period_s == pytest.approx(0.005)
    ul = OAI.windows("uplink")
    symbol = SLOT / 14
    assert [(round(s, 9), round(e, 9), n) for s, e, n in ul] == [
        (round(7 * SLOT + 10 * symbol, 9), round(8 * SLOT, 9), 4),
        (round(8 * SLOT, 9), round(9 * SLOT, 9), 14),
        (round(9 * SLOT, 9), round(10 * SLOT, 9), 14),
    ]
    assert OAI.share("uplink") == pytest.approx((4 / 14 + 2) / 10)
    assert OAI.windows("downlink")[-1][1] == pytest.approx(7 * SLOT + 6 * symbol)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"slots": "DDXU"}, "string of D, S and U"),
        ({"slots": "DDDSU", "special": (10, 2, 1)}, "add up to 13, not 14"),
        ({"slots": "DDDSU", "numerology": 5}, r"numerology must be 0\.\.4"),
        ({"slots": "DDDDDSU"}, "3.5 ms"),
        ({"slots": "DDDD"}, "no uplink"),
    ],
)
def test_bad_patterns_say_what_is_wrong(kwargs: dict, message: str) -> None:
    with pytest.raises(NrError, match=message):
        TddPattern(**kwargs)


# Inputs (symbols, DMRS RE/PRB, overhead RE/PRB, code rate, Qm, layers, scaling field, PRBs)
# and TBS from srsRAN's tbs_calculator_test_data.h (generated with MATLAB's 5G Toolbox).
@pytest.mark.parametrize(
    ("args", "want"),
    [
        ((12, 6, 0, 0.1, 2, 1, 0, 6), 160),
        ((12, 6, 12, 0.9, 2, 1, 2, 6), 336),
        ((12, 36, 12, 0.9, 4, 4, 0, 11), 15112),
        ((12, 6, 0, 0.9, 8, 4, 0, 11), 44040),
        ((12, 6, 0, 0.1, 8, 4, 0, 11), 4872),
        ((12, 36, 0, 0.1, 8, 4, 0, 11), 3824),
    ],
)
def test_tbs_matches_matlab(args: tuple, want: int) -> None:
    symbols, dmrs, oh, rate, qm, layers, scaling, prbs = args
    got = tbs_bits(
        prbs, None, symbols, dmrs, oh, layers, qm=qm, code_rate=rate, scaling=2.0**-scaling
    )
    assert got == want


def test_tbs_of_a_full_oai_slot_by_hand() -> None:
    # 106 PRBs, MCS 20 (64QAM, R = 567/1024), 14 symbols, one DMRS symbol (12 RE/PRB):
    # N_RE = min(156, 168 - 12) x 106 = 16536; N_info = 16536 x 567/1024 x 6 = 54936.8;
    # n = floor(log2(54912.8)) - 5 = 10; N' = 1024 x round(53.63) = 55296; C = ceil(55320 /
    # 8424) = 7; TBS = 8 x 7 x ceil(55320 / 56) - 24 = 55304.
    assert tbs_bits(106, 20) == 55304
    with pytest.raises(NrError, match=r"mcs must be 0\.\.28"):
        tbs_bits(106, 29)


def test_rate_of_a_saturated_direction_is_its_transport_blocks_per_second() -> None:
    carrier = Carrier(n_prb=106, mcs=20)
    ul = occasions(OAI, "uplink", carrier)
    assert [o.capacity_bytes for o in ul] == [
        carrier.tbs_bits(4) // 8,
        55304 // 8,
        55304 // 8,
    ]
    assert rate_bps(OAI, "uplink", carrier) == pytest.approx(
        sum(o.capacity_bytes for o in ul) * 8 / 0.005
    )


# -- the stage ---------------------------------------------------------------------------------


def run(stage: Slots, arrivals: list[tuple[float, bytes]]) -> list[tuple[float, float, bytes]]:
    """Push each packet at its time, collect (arrival, departure, packet) in order."""
    out: list[tuple[float, float, bytes]] = []
    pending = list(arrivals)
    times: dict[int, float] = {}
    while pending or stage.queued():
        due = stage.next_due()
        if pending and (due is None or pending[0][0] < due):
            t, packet = pending.pop(0)
            times[id(packet)] = t
            stage.push(packet, t)
            continue
        assert due is not None
        for packet in stage.pop_ready(due):
            out.append((times[id(packet)], due, packet))
    return out


def poisson_probes(n: int, mean_gap_s: float, size: int, seed: int = 1) -> list:
    rng = random.Random(seed)
    t, out = 0.0, []
    for i in range(n):
        t += rng.expovariate(1 / mean_gap_s)
        out.append((t, i.to_bytes(4, "big") + bytes(size - 4)))
    return out


def sparse_probes(n: int, size: int, seed: int = 1) -> list:
    """One probe in each 40 ms, at a uniform time in its first 20 ms: each finds the UE idle,
    and the phases are uniform over any period dividing 20 ms, as the oracle assumes."""
    rng = random.Random(seed)
    return [
        (i * 0.04 + rng.uniform(0, 0.02), i.to_bytes(4, "big") + bytes(size - 4)) for i in range(n)
    ]


def test_uplink_leaves_only_at_the_end_of_uplink_windows_and_matches_the_oracle() -> None:
    carrier = Carrier()
    lead = 2 * SLOT  # K2 = 2 slots (OAI's min_rxtxtime)
    stage = Slots(occasions(OAI, "uplink", carrier), OAI.period_s, lead_s=lead)
    got = run(stage, poisson_probes(1000, 0.013, 100))
    assert len(got) == 1000
    ends = [o.end_s for o in occasions(OAI, "uplink", carrier)]
    for _, left, _ in got:
        phase = left % OAI.period_s
        assert (
            min(abs(phase - e) % OAI.period_s for e in ends) < 1e-9
            or min(abs(phase - e + OAI.period_s) for e in ends) < 1e-9
        )
    oracle = DelayOracle.for_direction(OAI, "uplink", carrier, lead_s=lead)
    delays = [left - arrived for arrived, left, _ in got]
    assert min(delays) >= oracle.minimum - 1e-9 and max(delays) <= oracle.maximum + 1e-9
    cdf = np.vectorize(oracle.cdf)
    assert stats.kstest(delays, cdf).pvalue > 0.05
    # The histogram repeats with the TDD period: the gaps between modes are 5 ms.
    assert oracle.maximum - oracle.minimum < OAI.period_s + lead


def test_the_oracle_is_a_distribution() -> None:
    oracle = DelayOracle.for_direction(OAI, "uplink", Carrier(), lead_s=0.001, fixed_s=0.002)
    assert oracle.cdf(oracle.minimum) == pytest.approx(0.0)
    assert oracle.cdf(oracle.maximum) == pytest.approx(1.0)
    xs = [oracle.minimum + i * 1e-5 for i in range(800)]
    assert all(a <= b for a, b in zip(map(oracle.cdf, xs), map(oracle.cdf, xs[1:]), strict=False))
    assert oracle.quantile(0.5) == pytest.approx(
        next(x for x in xs if oracle.cdf(x) >= 0.5), abs=2e-5
    )
    # Monte Carlo of the model's own definition against the closed-form mean.
    rng = random.Random(3)
    windows = [(o.start_s, o.end_s) for o in occasions(OAI, "uplink", Carrier())]
    total = 0.0
    for _ in range(20000):
        t = rng.uniform(0, OAI.period_s)
        ready = t + 0.001
        end = min(
            e + k * OAI.period_s
            for k in range(3)
            for s, e in windows
            if s + k * OAI.period_s >= ready
        )
        total += end - t + 0.002
    assert total / 20000 == pytest.approx(oracle.mean(), rel=0.01)


def test_a_saturating_flow_gets_the_sum_of_its_transport_blocks() -> None:
    carrier = Carrier(n_prb=51, mcs=16)
    stage = Slots(occasions(OAI, "uplink", carrier), OAI.period_s)
    got = run(stage, [(0.0, bytes(1500)) for _ in range(3000)])
    first, last = got[0][1], got[-1][1]
    carried = sum(len(p) for _, t, p in got if first < t <= last)
    assert carried * 8 / (last - first) == pytest.approx(rate_bps(OAI, "uplink", carrier), rel=0.02)


def test_a_200_kb_message_completes_when_the_occasions_have_carried_it() -> None:
    carrier = Carrier(n_prb=106, mcs=10)
    ul = occasions(OAI, "uplink", carrier)
    stage = Slots(ul, OAI.period_s, lead_s=2 * SLOT)
    got = run(stage, [(0.0001, bytes(200_000))])
    # Closed form: the first occasion starting after 0.0001 + 1 ms, then whole occasions
    # until the bytes are carried.
    left, k, n = 200_000, 0, 0
    while ul[k].start_s + n * OAI.period_s < 0.0011:
        k, n = (k + 1, n) if k + 1 < len(ul) else (0, n + 1)
    while True:
        left -= ul[k].capacity_bytes
        if left <= 0:
            break
        k, n = (k + 1, n) if k + 1 < len(ul) else (0, n + 1)
    assert got[0][1] == pytest.approx(ul[k].end_s + n * OAI.period_s, abs=1e-9)
    assert math.isclose(got[0][1] % OAI.period_s, ul[k].end_s % OAI.period_s, abs_tol=1e-9)


# -- a radio in a link profile ----------------------------------------------------------------


def test_a_profile_with_a_radio_gates_its_pipeline_and_round_trips_as_json() -> None:
    import json

    from netem.nr.radio import Radio
    from netem.profile import LinkProfile, check_profile

    radio = Radio(mcs=9, k2_slots=2)
    profile = LinkProfile(radio=radio, delay_s=0.001)
    assert LinkProfile.from_dict(json.loads(json.dumps(profile.to_dict()))) == profile
    pipeline = build_pipeline(profile)
    got = run(pipeline, sparse_probes(600, 200, seed=4))  # type: ignore[arg-type]
    oracle = radio.oracle("uplink", fixed_s=0.001, size_bytes=200)
    delays = [left - arrived for arrived, left, _ in got]
    assert stats.kstest(delays, np.vectorize(oracle.cdf)).pvalue > 0.05
    # In place: a worse MCS keeps the grid and shrinks the blocks; no radio makes it a wire.
    pipeline.apply(profile.replace(radio=Radio(mcs=0)))
    slots = pipeline.stage("slots")
    assert isinstance(slots, Slots) and slots.occasions[1].capacity_bytes < 1000
    pipeline.apply(profile.replace(radio=None))
    t0 = 100.0
    pipeline.push(bytes(100), t0)
    assert pipeline.pop_ready(t0 + 0.001) == [bytes(100)]
    with pytest.raises(ValueError, match="userspace relay only"):
        check_profile(profile, backend="tc")
    with pytest.raises(ValueError, match=r"`radio`: mcs must be 0\.\.28"):
        check_profile(LinkProfile(radio=Radio(mcs=31)))
    with pytest.raises(ValueError, match="`radio`: a TDD pattern"):
        check_profile(LinkProfile(radio=Radio(slots="DDQU")))


def test_a_radio_switched_off_with_packets_waiting_lets_them_go_and_the_next_radio_delivers() -> (
    None
):
    """The link test's neutral moment switches a radio off while packets wait for slots,
    for HARQ and for PDCP's order; they leave at once, in order, and the radio that comes
    back delivers every packet after them (it once kept each in `_reorder` for good)."""
    from netem.nr.radio import Radio
    from netem.profile import LinkProfile

    profile = LinkProfile(radio=Radio(bler=0.5, mcs=9))
    slots = build_pipeline(profile).stage("slots")
    assert isinstance(slots, Slots) and slots.in_order
    burst = [(0.0002 * i, i.to_bytes(4, "big") + bytes(196)) for i in range(60)]
    for t, packet in burst:
        slots.push(packet, t)
    first = slots.pop_ready(0.02)  # a few occasions: some decoded, some held for a resend
    assert slots.queued() > 0 and (slots._reorder or slots._recovering or slots._queue)
    slots.configure(profile.replace(radio=None))
    rest = slots.pop_ready(1.0)  # what waited left at once: nothing is due after 0.02 s
    assert slots.queued() == 0
    assert first + rest == [p for _, p in burst]  # all of them, in the order they came
    slots.configure(profile)
    later = [(2.0 + 0.003 * i, (100 + i).to_bytes(4, "big") + bytes(196)) for i in range(40)]
    got = run(slots, later)
    assert [p for _, _, p in got] == [p for _, p in later]


def test_a_downlink_pipeline_sends_in_the_downlink_windows() -> None:
    from netem.nr.radio import Radio
    from netem.profile import LinkProfile

    radio = Radio(k2_slots=1)
    pipeline = build_pipeline(LinkProfile(radio=radio), direction="downlink")
    got = run(pipeline, poisson_probes(400, 0.007, 300, seed=5))  # type: ignore[arg-type]
    ends = [o.end_s for o in radio.occasions("downlink")]
    period = radio.pattern().period_s
    assert all(
        min(abs((t - e) % period) for e in ends) < 1e-9
        or min(abs((t - e) % period - period) for e in ends) < 1e-9
        for _, t, _ in got
    )
    delays = [t - a for a, t, _ in got]
    oracle = radio.oracle("downlink")
    assert stats.kstest(delays, np.vectorize(oracle.cdf)).pvalue > 0.05
    assert oracle.mean() < radio.oracle("uplink").mean()  # 7 of 10 slots are downlink


# -- HARQ -------------------------------------------------------------------------------------


def radio_stage(seed: int = 5, **fields: object) -> tuple[Slots, object]:
    """The `Slots` stage of a pipeline whose radio has `fields`, and that radio."""
    from netem.nr.radio import Radio
    from netem.profile import LinkProfile

    radio = Radio(**fields)  # type: ignore[arg-type]
    pipeline = build_pipeline(LinkProfile(radio=radio), seed=seed)
    slots = pipeline.stage("slots")
    assert isinstance(slots, Slots)
    return slots, radio


def harq_stage(bler: float, max_retx: int = 4, rlc: str = "am") -> tuple[Slots, object]:
    # A gNB that sees the buffer: each probe is one block, and HARQ alone decides its delay.
    return radio_stage(9, bler=bler, max_retx=max_retx, ul_access="ideal", rlc=rlc)


def test_harq_retransmits_a_tenth_of_the_blocks_one_after_another() -> None:
    slots, radio = harq_stage(0.1)
    got = run(slots, poisson_probes(10_000, 0.011, 100, seed=11))
    shares = slots.retransmissions
    n = slots.blocks  # probes that met in one occasion share its block
    assert n == sum(shares) and n > 8000
    for j, p in enumerate((0.9, 0.09, 0.009)):
        sigma = math.sqrt(n * p * (1 - p))
        assert abs(shares[j] - n * p) <= 3 * sigma, (j, shares)
    delays = [left - arrived for arrived, left, _ in got]
    oracle = radio.oracle("uplink")  # type: ignore[attr-defined]
    assert stats.kstest(delays, np.vectorize(oracle.cdf)).pvalue > 0.01
    # A retransmission costs about one TDD period on OAI's 5 ms pattern.
    once = [d for d in delays if d > oracle.quantile(0.9) + 0.002]
    assert once and all(d < 2 * 0.005 + 0.006 for d in once[:50])


def test_a_block_that_fails_every_try_is_lost_with_its_packets() -> None:
    slots, _ = harq_stage(0.3, max_retx=1, rlc="um")
    n = 5_000
    got = run(slots, poisson_probes(n, 0.011, 100, seed=12))
    lost = slots.counters.dropped_packets.get("harq", 0)
    assert lost + len(got) == n
    p = 0.3**2  # BLER^(max_retx + 1)
    assert abs(lost - n * p) <= 3 * math.sqrt(n * p * (1 - p))


def test_packets_leave_in_order_and_retransmissions_take_their_occasions() -> None:
    slots, radio = harq_stage(0.2)
    got = run(slots, [(0.0, i.to_bytes(4, "big") + bytes(1496)) for i in range(4000)])
    seqs = [int.from_bytes(p[:4], "big") for _, _, p in got]
    assert seqs == sorted(seqs) and len(seqs) == 4000 - slots.counters.dropped
    times = [t for _, t, _ in got]
    assert times == sorted(times)
    # Saturated, a fifth of the occasions carry retransmissions instead of new data.
    carried = sum(len(p) for _, t, p in got if times[0] < t <= times[-1])
    rate = carried * 8 / (times[-1] - times[0])
    assert rate == pytest.approx(0.8 * radio.rate_bps("uplink"), rel=0.06)  # type: ignore[attr-defined]


# -- uplink access: scheduling request and grants, configured grant --------------------------


def test_an_idle_ue_asks_with_a_scheduling_request_and_its_delay_is_the_closed_forms() -> None:
    # OAI's pattern: SR in the special slot every 10 slots, a 72-byte first grant one period
    # later, then the rest of a 92-byte probe in the grant its buffer status report brings.
    slots, radio = radio_stage()
    got = run(slots, sparse_probes(1000, 92, seed=21))
    assert len(got) == 1000 and slots.scheduling_requests == 1000  # each probe asks
    delays = sorted(left - arrived for arrived, left, _ in got)
    oracle = radio.oracle("uplink", size_bytes=92)  # type: ignore[attr-defined]
    assert abs(delays[0] - oracle.minimum) <= SLOT
    assert abs(delays[len(delays) // 2] - oracle.quantile(0.5)) <= SLOT
    assert abs(delays[-1] - oracle.maximum) <= SLOT
    assert stats.kstest(delays, np.vectorize(oracle.cdf)).pvalue > 0.05
    # Two rounds (SR, then BSR) of a period each: far above the buffer-aware gNB's delay.
    ideal = dataclasses.replace(radio, ul_access="ideal").oracle("uplink")  # type: ignore[type-var]
    assert oracle.quantile(0.5) > ideal.quantile(0.5) + 2 * 0.005 - SLOT
    # A probe that fits the first grant needs one round fewer.
    small = radio.oracle("uplink", size_bytes=60)  # type: ignore[attr-defined]
    assert small.quantile(0.5) == pytest.approx(oracle.quantile(0.5) - 0.005, abs=SLOT)


def test_a_longer_sr_period_moves_the_median_as_the_formula_says() -> None:
    medians, oracles = {}, {}
    for period in (10, 40):
        slots, radio = radio_stage(sr_period_slots=period, sr_offset=7)
        got = run(slots, sparse_probes(800, 60, seed=22))
        medians[period] = sorted(t - a for a, t, _ in got)[len(got) // 2]
        oracles[period] = radio.oracle("uplink", size_bytes=60).quantile(0.5)  # type: ignore[attr-defined]
    # Waiting for an SR every 20 ms instead of every 5 ms adds half the difference.
    assert oracles[40] - oracles[10] == pytest.approx(0.0075, abs=SLOT)
    assert medians[40] - medians[10] == pytest.approx(oracles[40] - oracles[10], abs=SLOT)


def test_a_configured_grant_delays_uniformly_over_its_period() -> None:
    for period in (10, 20):
        slots, radio = radio_stage(ul_access="configured", cg_period_slots=period, cg_offset=8)
        got = run(slots, sparse_probes(800, 100, seed=23))
        assert slots.scheduling_requests == 0
        delays = [t - a for a, t, _ in got]
        # Wait for the next grant (uniform over the period), then its slot.
        uniform = stats.uniform(loc=SLOT, scale=period * SLOT)
        assert stats.kstest(delays, uniform.cdf).pvalue > 0.05
        oracle = radio.oracle("uplink")  # type: ignore[attr-defined]
        assert oracle.mean() == pytest.approx(SLOT + period * SLOT / 2, rel=1e-9)


def test_harq_on_the_first_grant_delays_the_buffer_status_report_as_the_oracle_says() -> None:
    slots, radio = radio_stage(bler=0.1)
    got = run(slots, sparse_probes(3000, 92, seed=24))
    delays = [t - a for a, t, _ in got]
    oracle = radio.oracle("uplink", size_bytes=92)  # type: ignore[attr-defined]
    assert stats.kstest(delays, np.vectorize(oracle.cdf)).pvalue > 0.01
    assert sum(slots.retransmissions[1:]) > 0.07 * slots.blocks


def test_a_200_kb_message_after_a_scheduling_request_completes_as_the_closed_form_says() -> None:
    slots, radio = radio_stage(mcs=10)
    oracle = radio.oracle("uplink", size_bytes=200_000)  # type: ignore[attr-defined]
    rng = random.Random(25)
    took = []
    for k in range(12):
        t0 = 1.0 * k + rng.uniform(0, 0.005)
        got = run(slots, [(t0, bytes(1460)) for _ in range(137)])  # 200 020 bytes at once
        assert len(got) == 137
        took.append(got[-1][1] - t0)
    period = 0.005
    assert all(oracle.minimum - period <= d <= oracle.maximum + period for d in took)
    assert sum(took) / len(took) == pytest.approx(oracle.mean(), abs=period)


def test_a_saturating_ue_that_asks_still_gets_the_sum_of_its_transport_blocks() -> None:
    slots, radio = radio_stage(n_prb=51, mcs=16)
    got = run(slots, [(0.0, bytes(1500)) for _ in range(3000)])
    first, last = got[0][1], got[-1][1]
    carried = sum(len(p) for _, t, p in got if first < t <= last)
    want = radio.rate_bps("uplink")  # type: ignore[attr-defined]
    assert carried * 8 / (last - first) == pytest.approx(want, rel=0.02)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"sr_offset": 2}, r"falls in slot 2 \(D\) of DDDDDDDSUU, which has no uplink"),
        ({"sr_period_slots": 3}, "sr_period must be one of"),
        ({"sr_offset": 12}, r"sr_offset must be a slot of the SR period 0\.\.9"),
        ({"ul_access": "configured", "cg_offset": 1}, r"falls in slot 1 \(D\)"),
        ({"ul_access": "configured", "cg_period_slots": 3}, "cg_period must be one of"),
        ({"ul_access": "grantless"}, "ul_access must be one of sr, sr_free, configured, ideal"),
        ({"sr_grant_bytes": 0}, "sr_grant must be 1..100000 bytes"),
    ],
)
def test_uplink_access_fields_out_of_range_are_refused(fields: dict, message: str) -> None:
    from netem.nr.radio import Radio

    with pytest.raises(NrError, match=message):
        Radio(**fields).check()


def test_uplink_access_changes_in_place_and_keeps_what_waits() -> None:
    from netem.nr.radio import Radio
    from netem.profile import LinkProfile

    profile = LinkProfile(radio=Radio())
    pipeline = build_pipeline(profile)
    out: list[bytes] = []
    t, seq = 0.0, 0
    # Each change comes while packets wait: an SR every 20 ms, a configured grant, the
    # buffer-aware gNB, SR again.
    for radio in (Radio(sr_period_slots=40), Radio(ul_access="configured"),
                  Radio(ul_access="ideal"), Radio()):  # fmt: skip
        for _ in range(30):  # a 30 kB burst: several periods of uplink
            pipeline.push(seq.to_bytes(4, "big") + bytes(996), t)
            seq += 1
        t += 0.004
        out += pipeline.pop_ready(t)
        assert pipeline.queued() > 0
        pipeline.apply(profile.replace(radio=radio))
    out += pipeline.pop_ready(t + 1.0)
    assert pipeline.queued() == 0
    assert [int.from_bytes(p[:4], "big") for p in out] == list(range(seq))


# -- RLC and PDCP -----------------------------------------------------------------------------


def test_rlc_am_sends_what_harq_gave_up_on_again_so_nothing_is_lost_and_order_is_kept() -> None:
    slots, radio = harq_stage(0.3, max_retx=1)  # rlc: am (the default)
    n = 5_000
    got = run(slots, poisson_probes(n, 0.011, 100, seed=12))
    assert slots.counters.dropped == 0 and len(got) == n
    seqs = [int.from_bytes(p[:4], "big") for _, _, p in got]
    assert seqs == list(range(n))
    p, blocks = 0.3**2, slots.blocks  # the share of the blocks HARQ gives up on
    gave_up = slots.retransmissions[-1]
    assert abs(gave_up - blocks * p) <= 3 * math.sqrt(blocks * p * (1 - p))
    assert slots.recovered >= gave_up  # each of their packets was sent again
    # A recovered packet waits for the status report (20 ms) on top of its two tries.
    delays = sorted(t - a for a, t, _ in got)
    late = [d for d in delays if d >= radio.rlc_status_s]  # type: ignore[attr-defined]
    assert len(late) >= 0.9 * slots.recovered


def test_rlc_am_gives_a_packet_up_after_its_max_retx_threshold() -> None:
    """Out of coverage (BLER near 1) RLC-AM stops after maxRetxThreshold resends, as the UE
    would declare a radio link failure: packets are lost, not sent again for ever."""
    slots, _ = radio_stage(21, bler=0.999, max_retx=0, ul_access="ideal", rlc_max_retx=3)
    n = 40
    got = run(slots, poisson_probes(n, 0.05, 100, seed=22))  # returns once all are out
    lost = slots.counters.dropped_packets.get("rlc", 0)
    # Each packet has 1 + 3 tries, each failing with 0.999: about 0.4% get through.
    assert lost + len(got) == n and lost >= n - 2
    # A lost packet was sent again exactly 3 times; one that got through, at most 3.
    assert 3 * lost <= slots.recovered <= 3 * n
    assert slots.radio_counters()["rlc_given_up"] == lost


def test_without_in_order_delivery_a_packet_leaves_when_it_is_decoded() -> None:
    ordered, _ = harq_stage(0.2)
    loose, _ = radio_stage(bler=0.2, ul_access="ideal", in_order=False)
    probes = poisson_probes(3000, 0.0015, 100, seed=13)  # close enough that HARQ overtakes
    got = {k: run(s, probes) for k, s in (("ordered", ordered), ("loose", loose))}
    seqs = {k: [int.from_bytes(p[:4], "big") for _, _, p in v] for k, v in got.items()}
    assert seqs["ordered"] == sorted(seqs["ordered"])
    assert seqs["loose"] != sorted(seqs["loose"]) and sorted(seqs["loose"]) == list(range(3000))
    mean = {k: sum(t - a for a, t, _ in v) / len(v) for k, v in got.items()}
    assert mean["loose"] < mean["ordered"]  # nobody waits for a retransmission but its own


def test_the_buffer_of_a_ue_is_drop_tail_in_bytes() -> None:
    slots, _ = radio_stage(buffer_bytes=20_000)
    got = run(slots, [(0.0, i.to_bytes(4, "big") + bytes(996)) for i in range(50)])
    # 20 of the 50 kB fit; the rest is dropped on arrival, the oldest kept.
    assert [int.from_bytes(p[:4], "big") for _, _, p in got] == list(range(20))
    assert slots.counters.dropped_packets == {"queue_full": 30}


def test_a_radio_pipelines_counters_say_what_the_air_interface_did() -> None:
    from netem.nr.radio import Radio
    from netem.profile import LinkProfile

    pipeline = build_pipeline(LinkProfile(radio=Radio(bler=0.1)), seed=3)
    got = run(pipeline, sparse_probes(400, 92, seed=31))  # type: ignore[arg-type]
    radio = pipeline.snapshot()["radio"]
    assert len(got) == 400 and radio["scheduling_requests"] == 400
    assert radio["blocks"] == sum(radio["retransmissions"]) >= 800  # 72 B, then the rest
    assert 0.05 < sum(radio["retransmissions"][1:]) / radio["blocks"] < 0.15
    assert "radio" not in build_pipeline(LinkProfile()).snapshot()


@pytest.mark.parametrize("t0", [1.0, 49_780.3, 86_400.0, 123_456.7, 3_000_000.0])
def test_a_grant_due_at_an_occasions_start_takes_it_at_any_uptime(t0: float) -> None:
    """The stage runs on the host's monotonic clock, ~10^5 s or more after boot, where a double
    resolves ~10^-11 s. A grant that falls due exactly at an occasion's start (an SR's end plus
    the grant delay, on the slot grid) must use that occasion however large the clock is: with
    a 10^-12 tolerance it slipped to the next one, 2.5 ms later, in half the packets."""
    from netem.nr.radio import Radio
    from netem.profile import LinkProfile

    radio = Radio(
        slots="DDDSU", special=(10, 4, 0), n_prb=106, mcs=16, dmrs_re_per_prb=6, ul_prbs=5,
        ul_symbols=3, sr_period_slots=5, sr_offset=4, sr_grant_bytes=1000, grant_slots=2,
        k2_slots=2, bler=0.0,
    )  # fmt: skip
    pipeline = build_pipeline(LinkProfile(radio=radio), 0, "uplink")
    period = radio.pattern().period_s
    base = math.ceil(t0 / period) * period
    delays = []
    for k in range(20):
        sent = base + k * 0.05 + 0.0021  # just after the uplink slot's start (2.0 ms)
        pipeline.push(bytes(128), sent)
        while (due := pipeline.next_due()) is not None:
            if pipeline.pop_ready(due):
                delays.append(round((due - sent) * 1000, 6))
                break
    # SR in the next uplink slot (2.5 ms on), its grant one period after it, then the
    # buffer status report's grants: 128 bytes in 48-byte blocks, one per uplink slot.
    assert delays == [10.4] * 20
