"""Learned against fixed splits and the oracle (issue #14), the robust fusion weight, and the
measured-latency model a real run's comparison uses.

The default-scenario assertions read replays (the same algorithms as the ROS nodes); nothing
is a stored number. Issue #14's full goal (error monotone in latency across the splits in every
phase) is not met yet: its test is a strict xfail, so it fails loudly the day it starts passing.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.signal
import scipy.stats

from nodes.edgeloc import geometry
from nodes.edgeloc.compare import (
    PhaseFigures,
    PolicyRow,
    SplitComparison,
    block_means,
    compare_splits,
    paired_noise_m,
)
from nodes.edgeloc.dataset import Dataset
from nodes.edgeloc.fusion import EdgeLocFuser, latency_weight
from nodes.edgeloc.latency import LatencyModel, MeasuredLatency, MeasuredRequest
from nodes.edgeloc.metrics import error_autocorrelation
from nodes.edgeloc.model import LocNet
from nodes.edgeloc.premise import path_scale_error
from nodes.edgeloc.replay import (
    Answer,
    InferenceCache,
    NoiseAnswers,
    Replay,
    config_dataset,
    run_replay,
)
from nodes.edgeloc.settings import ReplayConfig
from nodes.edgeloc.train import load_model
from testbed.replay import latency_model, replay_config
from testbed.scenario import load

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


@pytest.fixture(scope="module")
def default_inputs() -> tuple[ReplayConfig, LatencyModel, Dataset, LocNet, InferenceCache]:
    scenario = load(SCENARIOS / "default.yaml")
    cfg = replay_config(scenario)
    ds = config_dataset(cfg)
    model = load_model(cfg.weights)
    return cfg, latency_model(scenario), ds, model, InferenceCache(model, ds, cfg.codec)


@pytest.fixture(scope="module")
def default_comparison(
    default_inputs: tuple[ReplayConfig, LatencyModel, Dataset, LocNet, InferenceCache],
) -> SplitComparison:
    return compare_splits(*default_inputs)


def test_comparison_has_every_policy_and_the_oracle_plays_its_schedule(
    default_comparison: SplitComparison,
) -> None:
    c = default_comparison.to_dict()
    policies = [r["policy"] for r in c["rows"]]
    assert policies == [
        "learned",
        "fixed:image",
        "fixed:conv3",
        "fixed:vehicle",
        "oracle",
        "learned, paper fusion",
    ]
    assert len(c["phases"]) == 3 and c["latency_source"] == "model"
    # the latency-best split per phase is the one the scenario's comments predict
    assert [p["latency_best"] for p in c["phases"]] == ["image", "conv3", "image"]
    # a disagreement between the fastest and the most accurate split is said in words
    for p in c["phases"]:
        said = any(f"{p['start_s']:g}-{p['end_s']:g} s" in d for d in c["disagreements"])
        assert said == (not p["agree"] or p["monotone"] is False)


def test_learned_beats_every_fixed_split_on_the_default_scenario(
    default_comparison: SplitComparison,
) -> None:
    c = default_comparison
    print({k: round(r.total_m, 1) for k, r in c.fixed.items()}, round(c.learned.total_m, 1))
    assert c.learned_beats_fixed is True
    # and the uncertainty-aware fusion (beyond the paper) beats the paper's bare form here
    assert c.paper_fusion is not None and c.learned.total_m < c.paper_fusion.total_m


@pytest.mark.xfail(
    strict=True,
    reason="issue #14 open: phase 0-30 s is not monotone, by less than the drive's noise (the "
    "up-to-ties test below). The DNN's errors are correlated over ~150 ms "
    "(tests/bench/bench_splits.py, sections 0 and 'error memory'), so a faster split's extra "
    "answers repeat what the fusion already heard; with white answers it is monotone here. "
    "Seed 7's VO is off by only 1.1%, so answers have little drift to correct "
    "(tests/bench/bench_premise.py; the drifting drive's test below)",
)
def test_error_is_monotone_in_latency_in_every_phase(default_comparison: SplitComparison) -> None:
    assert all(default_comparison.monotone(j) for j in range(len(default_comparison.bounds)))


def test_error_is_monotone_in_latency_up_to_ties_in_every_phase(
    default_comparison: SplitComparison,
) -> None:
    """What the default drive does show: where a slower split is more accurate (phase 0-30 s,
    the xfail above), it is by less than the drive's noise, a tie this drive cannot resolve."""
    c = default_comparison
    phases = range(len(c.bounds))
    assert all(c.monotone_within_noise(j) for j in phases)
    ties = [v for j in phases for v in c.inversions(j)]
    print([(v.faster, v.slower, round(v.by_m, 3), round(v.noise_m, 3)) for v in ties])
    assert ties and all(0 <= v.by_m <= v.noise_m for v in ties)


def test_on_a_drive_whose_vo_drifts_the_premise_holds_strictly_and_learning_pays() -> None:
    """What the xfail above misses on seed 7 holds where the paper's mechanism has something to
    correct: a DNN answer is worth what the VO drifted since the last one. Seed 9's VO has a
    scale error of 2.3%; over seeds 1-48 every drive whose VO is off by >= 2% (15 of 48) was
    strictly monotone in every phase with the learned run ahead of every fixed split, and no
    drive off by < 1% (17) was monotone in every phase (`tests/bench/bench_premise.py`)."""
    scenario = load(SCENARIOS / "default.yaml")
    cfg = replace(replay_config(scenario), seed=9)
    ds = config_dataset(cfg)
    assert path_scale_error(ds.gt_poses, ds.vo_poses) >= 0.02
    c = compare_splits(cfg, latency_model(scenario), ds, load_model(cfg.weights))
    print({k: [round(p.mean_error_m, 2) for p in r.phases] for k, r in c.fixed.items()})
    assert all(c.monotone(j) for j in range(len(c.bounds)))
    assert c.learned_beats_fixed is True


def test_with_white_noise_answers_the_fastest_split_is_the_most_accurate(
    default_inputs: tuple[ReplayConfig, LatencyModel, Dataset, LocNet, InferenceCache],
) -> None:
    """The diagnosis of the xfail above: the same replay, latencies and fusion, with answers
    that are ground truth plus white noise of the DNN's median error (1.68 m: σ = 1.43 m per
    axis) instead of the DNN's. Then error does fall with latency in every phase and the
    learner beats every fixed split, so what breaks the premise is the DNN's error memory,
    not the fusion or the latency model."""
    cfg, latency, ds, model, cache = default_inputs
    white = NoiseAnswers(cache, 1.43)
    c = compare_splits(cfg, latency, ds, model, white)
    print({k: [round(p.mean_error_m, 2) for p in r.phases] for k, r in c.fixed.items()})
    assert all(c.monotone(j) for j in range(len(c.bounds)))
    assert c.learned_beats_fixed is True
    # the answers are white: one frame apart they share nothing, unlike the DNN's
    frames = range(0, 600)
    e = np.array([white.answer(i, "image").pose[:2] - ds.gt_pose(i)[:2] for i in frames])
    assert abs(error_autocorrelation(e, 1)[0]) < 0.1
    assert white.answer(5, "image").payload == cache.answer(5, "image").payload


def test_noise_answers_have_the_spread_and_the_memory_they_are_given() -> None:
    """The ablation's answers against their closed form: lag-k autocorrelation exp(−k·dt/τ)
    (0 for white), the same spread σ per axis whatever τ, the same answer at every split and
    the real payload of each split (a stand-in for the DNN, isolated on purpose)."""

    class Drive:
        timestamps = tuple(0.05 * k for k in range(20_000))

        def gt_pose(self, frame: int) -> np.ndarray:
            return np.array([3.0 * frame, -1.0, 0.5])

    class Real:
        model = SimpleNamespace(eval=lambda: None)
        dataset, codec = Drive(), "fp16-zlib"

        def answer(self, frame: int, split: str) -> Answer:
            return Answer(np.zeros(3), {"image": 36_896, "conv3": 2_801}[split])

    real = Real()
    for tau in (0.0, 0.05, 0.15):
        answers = NoiseAnswers(real, 1.4, correlation_s=tau, seed=3)  # type: ignore[arg-type]
        e = np.array([answers.answer(i, "image").pose - real.dataset.gt_pose(i) for i in
                      range(20_000)])  # fmt: skip
        expected = np.exp(-0.05 * np.arange(1, 5) / tau) if tau else np.zeros(4)
        np.testing.assert_allclose(error_autocorrelation(e[:, :2], 4), expected, atol=0.03)
        assert e[:, :2].std(axis=0) == pytest.approx([1.4, 1.4], rel=0.05)
        assert e[:, 2].std() == pytest.approx(0.02, rel=0.05)
        again = answers.answer(7, "conv3")
        assert np.array_equal(again.pose, answers.answer(7, "image").pose)
        assert again.payload == 2_801
    with pytest.raises(ValueError, match="correlation time >= 0"):
        NoiseAnswers(real, 1.4, correlation_s=-0.1)  # type: ignore[arg-type]


def _row(policy: str, latency_s: float | None, blocks: list[float]) -> PolicyRow:
    figures = PhaseFigures(float(np.mean(blocks)), latency_s, latency_s, 10, tuple(blocks))
    return PolicyRow(policy, float(sum(blocks)), (figures,))


def _comparison(
    phases: dict[str, tuple[float, list[float]]], learned: list[float] | None = None
) -> SplitComparison:
    """One phase: per split its mean latency and its 2-s block errors."""
    fixed = {k: _row(f"fixed:{k}", lat, b) for k, (lat, b) in phases.items()}
    mine = None if learned is None else _row("learned", None, learned)
    return SplitComparison(((0.0, 30.0),), mine, fixed, None, None, "model", {})


def test_an_inversion_is_weighed_against_the_drives_noise() -> None:
    """A slower split that is more accurate is an inversion; it is beyond the noise when the
    paired block differences are significant at 5% (scipy's ttest_rel as the oracle)."""
    rng = np.random.default_rng(5)
    base = list(0.5 + 0.2 * rng.standard_normal(15))
    steady = [b - 0.02 + 0.002 * rng.standard_normal() for b in base]  # always a bit better
    swing = [0.3 * (-1) ** k for k in range(14)] + [0.0]  # better on average only
    shaky = [b - 0.02 + w for b, w in zip(base, swing, strict=True)]
    for slower, beyond in ((steady, True), (shaky, False)):
        c = _comparison({"image": (0.07, base), "conv3": (0.12, slower)})
        assert c.monotone(0) is False
        [v] = c.inversions(0)
        assert (v.faster, v.slower) == ("image", "conv3")
        assert v.by_m == pytest.approx(np.mean(base) - np.mean(slower))
        p = scipy.stats.ttest_rel(base, slower).pvalue
        assert v.beyond_noise is bool(p < 0.05) is beyond
        assert c.monotone_within_noise(0) is (not beyond)
        said = c.to_dict()["phases"][0]  # type: ignore[index]
        assert said["inversions"][0]["beyond_noise"] is beyond
        assert any(("beyond" if beyond else "within") + " the drive's noise" in d
                   for d in c.disagreements())  # fmt: skip
    ordered = _comparison({"image": (0.07, [b - 0.1 for b in base]), "conv3": (0.12, base)})
    assert ordered.monotone(0) and ordered.inversions(0) == []
    assert ordered.monotone_within_noise(0) is True
    assert paired_noise_m([1.0], [1.5]) == math.inf  # one block: nothing to judge by
    short = _comparison({"image": (0.07, [0.5]), "conv3": (0.12, [0.4])})
    assert "too short a stretch to tell from the drive's noise" in short.disagreements()[-1]


def test_the_noise_band_holds_its_level_on_differences_with_memory() -> None:
    """Oracle: zero-mean differences with a known memory (AR(1), 20 Hz, one 30-s phase), cut
    into `block_means` as a replay's errors are. A band that holds its 95% level calls a
    difference real in ~5% of draws; with memories of up to 4 s this one stays under 12%."""
    rng = np.random.default_rng(11)
    n, draws = 600, 600
    for tau_s in (0.0, 1.0, 4.0):
        rho = math.exp(-1 / (20 * tau_s)) if tau_s else 0.0
        e = rng.standard_normal((draws, n))
        x = scipy.signal.lfilter([math.sqrt(1 - rho**2)], [1, -rho], e[:, 1:], axis=1)
        x = np.hstack([e[:, :1], x + rho ** np.arange(1, n) * e[:, :1]])  # stationary start
        false = 0
        for d in x:
            blocks = block_means(d, 30.0)
            assert len(blocks) == 3
            false += abs(d.mean()) > paired_noise_m(blocks, [0.0] * len(blocks))
        print(f"memory {tau_s:g} s: a zero difference called real in {false / draws:.3f}")
        assert false / draws < 0.12, tau_s  # 2-s blocks, 2 SE: 0.145 at 1 s, 0.418 at 4 s


def test_a_learned_run_that_loses_is_weighed_against_the_drives_noise() -> None:
    base = [0.5 + 0.1 * math.sin(k) for k in range(15)]
    swing = [0.3 * (-1) ** k for k in range(14)] + [0.0]
    fixed = {"image": (0.07, base), "conv3": (0.12, [b + 0.2 for b in base])}
    close = _comparison(fixed, [b + 0.01 + w for b, w in zip(base, swing, strict=True)])
    clear = _comparison(fixed, [b + 0.05 for b in base])
    ahead = _comparison(fixed, [b - 0.05 for b in base])
    assert close.learned_beats_fixed is False and clear.learned_beats_fixed is False
    by, noise = close.learned_deficit()  # type: ignore[misc]
    assert by == pytest.approx(0.01) and noise > by
    assert close.learned_beats_fixed_within_noise is True
    by, noise = clear.learned_deficit()  # type: ignore[misc]
    assert by == pytest.approx(0.05) and noise == pytest.approx(0.0, abs=1e-9)
    assert clear.learned_beats_fixed_within_noise is False
    assert "loses to fixed image" in clear.disagreements()[-1]
    assert "beyond the drive's noise" in clear.disagreements()[-1]
    assert "within the drive's noise" in close.disagreements()[-1]
    assert ahead.learned_deficit() is None and ahead.learned_beats_fixed_within_noise is True
    assert close.to_dict()["learned_beats_fixed_within_noise"] is True


def test_smoke_replay_puts_edgeloc_ahead_of_all_three_baselines() -> None:
    scenario = load(SCENARIOS / "smoke.yaml")
    s = run_replay(replay_config(scenario), latency_model(scenario)).summary()
    reductions = {r["versus"]: r["ours_pct"] for r in s["paper_comparison"]["reductions"]}
    print(s["headline"])
    assert set(reductions) == {"vo", "dnn", "kalman"}
    assert all(v > 0 for v in reductions.values()), reductions


# ---- the robust weight ------------------------------------------------------------------------


def _fuser_with_history(c: float | None, innovations: list[float]) -> EdgeLocFuser:
    fuser = EdgeLocFuser(k_s=2.0, dt0_s=-1.4, initial=geometry.pose(0, 0, 0), robust_c=c)
    fuser.on_vo(geometry.pose(0, 0, 0), 0.0)
    for k, r in enumerate(innovations):
        fuser._pose = geometry.pose(0, 0, 0)  # each answer judged against the same estimate
        fuser.on_dnn(geometry.pose(r, 0, 0), 0.0, 0.1 + 1e-3 * k)
    return fuser


def test_robust_weight_is_the_cauchy_weight_of_the_innovation() -> None:
    history = [1.0, 2.0, 1.5, 1.0, 2.0, 1.5, 1.0]  # median 1.5
    fuser = _fuser_with_history(2.0, history)
    fuser._pose = geometry.pose(0, 0, 0)
    fuser.on_dnn(geometry.pose(30.0, 0, 0), 0.0, 0.2)
    u_paper = latency_weight(0.2, 2.0, -1.4)
    expected = u_paper / (1 + (30.0 / (2.0 * 1.5)) ** 2)  # the formula in the module doc
    assert fuser.last_update.weight == pytest.approx(expected, rel=1e-9)
    assert fuser.last_update.weight < 0.01 * u_paper
    bare = _fuser_with_history(None, history)
    bare._pose = geometry.pose(0, 0, 0)
    bare.on_dnn(geometry.pose(30.0, 0, 0), 0.0, 0.2)
    assert bare.last_update.weight == pytest.approx(u_paper)


def test_robust_c_must_be_positive() -> None:
    with pytest.raises(ValueError, match="robust c"):
        EdgeLocFuser(k_s=2.0, dt0_s=0.0, robust_c=0.0)


# ---- measured latencies and schedules ---------------------------------------------------------


def test_measured_latency_draws_from_the_phase_then_the_whole_run() -> None:
    reqs = [MeasuredRequest(t, "image", 0.05, False) for t in (1.0, 2.0, 3.0)]
    reqs += [MeasuredRequest(t, "image", 0.40, False) for t in (31.0, 32.0)]
    reqs += [MeasuredRequest(35.0, "conv3", 0.20, True)]  # one lost request, phase 2 only
    lm = MeasuredLatency(reqs, phase_starts=[0.0, 30.0], timeout_s=1.0)
    rng = np.random.default_rng(0)
    assert {lm.timing("image", 5.0, 100, rng).latency_s for _ in range(20)} == {0.05}
    assert {lm.timing("image", 40.0, 100, rng).latency_s for _ in range(20)} == {0.40}
    # one conv3 sample in its phase (< MIN_SAMPLES): the whole run's, and a lost one is the timeout
    t = lm.timing("conv3", 1.0, 100, rng)
    assert t.lost and t.latency_s == 1.0
    assert lm.knows("conv3") and not lm.knows("vehicle")
    with pytest.raises(ValueError, match="never measured"):
        lm.timing("vehicle", 1.0, 100, rng)
    assert lm.expected_s("image", 40.0, 100) == pytest.approx(0.40)
    assert math.isinf(lm.expected_s("conv3", 40.0, 100))


def test_replay_plays_a_split_schedule_and_refuses_an_unknown_split() -> None:
    scenario = load(SCENARIOS / "smoke.yaml")
    cfg = replace(replay_config(scenario), duration_s=6.0, splits=("image", "conv3", "vehicle"))
    lm = latency_model(scenario)
    schedule = [(0.0, "vehicle"), (3.0, "image")]
    replay = Replay(cfg, lm, config_dataset(cfg), load_model(cfg.weights), schedule=schedule)
    replay.run()
    assert {p.split for p in replay.plays if p.sent_s < 3.0} == {"vehicle"}
    assert {p.split for p in replay.plays if p.sent_s >= 3.0} == {"image"}
    # the learner is not taught when a schedule plays
    assert replay.learning is False and replay.learner.bandit.total_plays == 0
    with pytest.raises(ValueError, match="conv9"):
        run_replay(cfg, lm, schedule=[(0.0, "conv9")])


def test_measured_comparison_leaves_out_a_split_the_run_never_played() -> None:
    scenario = load(SCENARIOS / "smoke.yaml")
    cfg = replace(replay_config(scenario), duration_s=6.0, splits=("image", "conv3", "vehicle"))
    reqs = [MeasuredRequest(0.1 * k, "image" if k % 2 else "conv3", 0.08, False) for k in range(60)]
    lm = MeasuredLatency(reqs, phase_starts=[0.0], timeout_s=1.0)
    ds = config_dataset(cfg)
    c = compare_splits(cfg, lm, ds, load_model(cfg.weights))
    assert sorted(c.fixed) == ["conv3", "image"] and "vehicle" in c.skipped
    assert c.latency_source == "measured" and c.learned is not None


def test_ekf_fusion_beats_the_papers_weight_and_kalman_on_the_default_replay(
    default_comparison: SplitComparison,
) -> None:
    """Beyond the paper: `fusion.method: ekf` on the same drive, network and learner."""
    scenario = load(SCENARIOS / "default.yaml")
    cfg = replace(replay_config(scenario), fusion_method="ekf")
    s = run_replay(cfg, latency_model(scenario)).summary()
    reductions = {r["versus"]: r["ours_pct"] for r in s["paper_comparison"]["reductions"]}
    totals = {t["method"]: t["ours"] for t in s["paper_comparison"]["totals"]}
    print(totals, reductions)
    assert s["fusion"]["method"] == "ekf" and "BEYOND THE PAPER" in s["fusion"]["description"]
    assert totals["edgeloc"] < default_comparison.learned.total_m  # type: ignore[union-attr]
    assert reductions["kalman"] > 30.26, reductions  # the paper's reduction against its KF


def test_replays_on_forked_workers_equal_one_after_another() -> None:
    """The comparison's replays go to one worker per CPU: each must come back exactly as the
    same replay run alone, and the answers the workers computed must reach the caller's cache
    (the oracle, replayed afterwards, asks for them again)."""
    from nodes.edgeloc.compare import replays

    scenario = load(SCENARIOS / "smoke.yaml")
    cfg = replay_config(scenario)
    ds = config_dataset(cfg)
    model = load_model(cfg.weights)
    configs = {k: replace(cfg, learner=replace(cfg.learner, fixed_split=k)) for k in cfg.splits[:3]}
    one = replays(configs, latency_model(scenario), ds, model, None, workers=1)
    cache = InferenceCache(model, ds, cfg.codec)
    two = replays(configs, latency_model(scenario), ds, model, cache, workers=2)
    assert list(two) == list(configs)
    for k in configs:
        a, b = one[k], two[k]
        assert a.plays == b.plays, k
        assert set(a.poses) == set(b.poses)
        for method in a.poses:
            np.testing.assert_array_equal(a.poses[method], b.poses[method], err_msg=k)
    asked = {(p.frame, p.split) for r in two.values() for p in r.plays}
    assert asked and asked <= set(cache.answers())
