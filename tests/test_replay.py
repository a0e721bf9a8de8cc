"""Replay: latency model, plausibility gate, scenario adapter and the whole seeded loop."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from nodes.edgeloc.gate import GateSettings, PlausibilityGate
from nodes.edgeloc.latency import (
    ComputeProfile,
    Exchange,
    LatencyModel,
    PathSchedule,
    PathState,
    wire_bytes,
)
from nodes.edgeloc.metrics import read_tum
from nodes.edgeloc.model import SPLITS
from nodes.edgeloc.replay import ReplayConfig, convergence, run_replay
from testbed.cli import app
from testbed.errors import BadInput
from testbed.replay import latency_model, replay_config, replay_scenario
from testbed.scenario import load, loads

ROOT = Path(__file__).resolve().parents[1]
# A fixed compute profile (the reference, weights/compute.json, rounded) keeps the tests
# deterministic whatever the reference becomes.
COMPUTE = ComputeProfile(
    splits=SPLITS,
    head_core_s=(4.6e-4, 1.85e-3, 1.92e-3, 1.95e-3, 1.94e-3, 2.15e-3, 2.65e-3),
    tail_core_s=(2.71e-3, 2.35e-3, 2.17e-3, 1.90e-3, 1.55e-3, 1.26e-3, 4.4e-4),
)


# ---- latency model -----------------------------------------------------------------------------


def test_fold_takes_slowest_rate_and_sums_delays() -> None:
    a = PathState(rate_bps=50e6, delay_s=0.008, jitter_s=0.003, loss=0.01)
    b = PathState(rate_bps=1e9, delay_s=0.001, jitter_s=0.004, loss=0.02)
    f = PathState.fold([a, b])
    assert f.rate_bps == 50e6
    assert f.delay_s == pytest.approx(0.009)
    assert f.jitter_s == pytest.approx(0.005)
    assert f.loss == pytest.approx(1 - 0.99 * 0.98)


def test_transmit_integrates_rate_changes_and_waits_out_outages() -> None:
    s = PathSchedule(
        (0.0, 1.0, 2.0, 3.0),
        (
            PathState(rate_bps=1000.0),
            PathState(rate_bps=500.0),
            PathState(rate_bps=500.0, up=False),
            PathState(rate_bps=2000.0),
        ),
    )
    done, outage = s.transmit(0.5, 1000.0)  # 500 bits at 1000 b/s, 500 at 500 b/s
    assert done == pytest.approx(2.0) and not outage
    done, outage = s.transmit(1.5, 1250.0)  # 250 bits by 2 s, stalled to 3 s, 1000 at 2000
    assert done == pytest.approx(3.5) and outage


def test_cpu_budget_stretches_compute() -> None:
    slow = COMPUTE.with_budgets(vehicle_cpu=0.25, edge_cpu=4.0)
    assert slow.head_s("conv2") == pytest.approx(4 * COMPUTE.head_s("conv2"))
    assert slow.tail_s("conv2") == pytest.approx(COMPUTE.tail_s("conv2"))  # one thread, <= 1 core


def test_request_timing_adds_up_and_repeats_with_the_seed() -> None:
    up = PathSchedule.constant(PathState(rate_bps=8e6, delay_s=0.009, jitter_s=0.002))
    down = PathSchedule.constant(PathState(rate_bps=200e6, delay_s=0.009, jitter_s=0.002))
    model = LatencyModel(COMPUTE, up, down)
    a = model.timing("conv3", 1.0, 2763, np.random.default_rng(1))
    b = model.timing("conv3", 1.0, 2763, np.random.default_rng(1))
    assert a == b
    parts = a.head_s + a.uplink_s + a.tail_s + a.downlink_s
    assert a.latency_s == pytest.approx(parts)
    assert a.request_bytes == wire_bytes(2763 + 16)
    # noise-free: serialisation of the wire bytes at 8 Mbit/s plus the 9 ms delay
    assert model.expected_s("conv3", 0.0, 2763) > 0.009 * 2 + 8 * wire_bytes(2779) / 8e6


def test_drop_policy_loses_requests_and_charges_the_timeout() -> None:
    lossy = PathSchedule.constant(PathState(rate_bps=8e6, delay_s=0.01, loss=0.5))
    model = LatencyModel(COMPUTE, lossy, lossy, loss_policy="drop", timeout_s=0.7)
    rng = np.random.default_rng(0)
    timings = [model.timing("image", 0.0, 7220, rng) for _ in range(50)]
    assert any(t.lost for t in timings)
    assert all(t.latency_s == 0.7 for t in timings if t.lost)
    retry = LatencyModel(COMPUTE, lossy, lossy, loss_policy="retransmit", rto_s=0.2)
    slow = [retry.timing("image", 0.0, 7220, rng) for _ in range(50)]
    assert not any(t.lost and t.latency_s < 1.0 for t in slow)
    assert max(t.latency_s for t in slow) >= 0.2  # somebody paid a retransmission


def test_bad_latency_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="loss policy"):
        path = PathSchedule.constant(PathState())
        LatencyModel(COMPUTE, path, path, "maybe")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="starts at 0"):
        PathSchedule((1.0,), (PathState(),))
    with pytest.raises(ValueError, match="CPU budget"):
        COMPUTE.with_budgets(0.0, None)


# ---- gate --------------------------------------------------------------------------------------


def test_gate_rejects_far_answers_and_recovers_on_a_consistent_story() -> None:
    gate = PlausibilityGate(GateSettings(radius_m=10.0, growth_per_m=0.0, recover_after=3))
    here, vo = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0])
    assert gate.admit(np.array([3.0, 0.0, 0.0]), here, vo, 0.0)
    far = np.array([100.0, 0.0, 0.0])
    assert not gate.admit(far, here, vo, 1.0)
    assert not gate.admit(np.array([-80.0, 0.0, 0.0]), here, vo, 2.0)  # inconsistent outlier
    assert not gate.admit(far, here, vo, 3.0)
    assert not gate.admit(far, here, vo, 4.0)
    assert gate.admit(far, here, vo, 5.0)  # third consistent answer in a row: recovery
    assert gate.counts() == {"accepted": 2, "rejected": 4, "recoveries": 1}


def test_gate_radius_grows_with_distance_driven() -> None:
    gate = PlausibilityGate(GateSettings(radius_m=10.0, growth_per_m=0.1))
    assert gate.radius(0.0) == 10.0
    assert gate.radius(100.0) == pytest.approx(20.0)


# ---- scenario adapter --------------------------------------------------------------------------


def test_default_scenario_path_follows_the_timeline() -> None:
    """default_pipe.yaml is default.yaml over a plain pipe: the same timeline and workload."""
    sc = load(ROOT / "scenarios" / "default_pipe.yaml")
    nr = load(ROOT / "scenarios" / "default.yaml")
    strip = [dataclasses.replace(e, line=0) for e in sc.timeline]
    assert [dataclasses.replace(e, line=0) for e in nr.timeline] == strip
    assert nr.workload == sc.workload
    assert nr.links.get("av1-gnb1").uplink.radio is not None
    lm = latency_model(sc, COMPUTE)
    assert lm.uplink.times == (0.0, 30.0, 60.0)
    assert [s.rate_bps for s in lm.uplink.states] == [40e6, 2e6, 20e6]
    up = lm.uplink.states[0]
    assert up.delay_s == pytest.approx(0.009)  # air 8 ms + backhaul 1 ms
    assert up.jitter_s == pytest.approx(0.002)
    assert up.loss == pytest.approx(0.001)
    assert lm.downlink.at(45.0).rate_bps == 200e6  # the shape capped only the uplink
    cfg = replay_config(sc)
    assert cfg.phases == (0.0, 30.0, 60.0)
    assert cfg.splits == ("image", "conv3", "vehicle")
    assert cfg.learner.window == 100 and cfg.learner.detector_window == 30
    assert cfg.k_s == 2.0 and cfg.dt0_s == -1.4
    assert cfg.learner.detector_fit == "robust" and cfg.learner.bandit_fit == "robust"
    assert lm.compute.vehicle_cpu == 0.025  # the whole network takes ~106 ms on the vehicle
    assert lm.exchange.handshakes == 1  # the ROS nodes' SplitInference action


def test_outage_and_set_events_change_the_path() -> None:
    sc = load(ROOT / "scenarios" / "smoke.yaml")
    from testbed.scenario.model import OutageEvent, SetEvent

    events = (
        *sc.timeline,
        SetEvent(at_s=5.0, link="av1-gnb1", direction="uplink", changes={"delay_s": 0.05}),
        OutageEvent(at_s=12.0, link="av1-gnb1", duration_s=1.5),
    )
    lm = latency_model(replace(sc, timeline=events), COMPUTE)
    assert lm.uplink.at(6.0).delay_s == pytest.approx(0.051)
    assert not lm.uplink.at(12.5).up and not lm.downlink.at(12.5).up
    assert lm.uplink.at(13.6).up and lm.uplink.at(13.6).rate_bps == 8e6


# ---- the loop ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, object]:
    sc = load(ROOT / "scenarios" / "smoke.yaml")
    done = replay_scenario(sc, tmp_path_factory.mktemp("runs"), COMPUTE)
    folder, result, summary = done.folder, done.result, done.summary
    return folder, summary, result


def test_replay_writes_summary_and_trajectories(smoke_run) -> None:
    folder, _, _ = smoke_run
    on_disk = json.loads((folder / "summary.json").read_text())
    assert on_disk["run_id"] == folder.name
    for key in ("methods", "paper_comparison", "headline", "learner", "latency", "settings"):
        assert key in on_disk
    for m in ("vo", "dnn", "kalman", "edgeloc"):
        stats = on_disk["methods"][m]["position_m"]
        assert stats["n"] == 400 and stats["total"] > 0
        stamps, poses = read_tum(folder / f"{m}.tum")
        assert len(stamps) == 400 and poses.shape == (400, 3)
    assert [r["paper_pct"] for r in on_disk["paper_comparison"]["reductions"]] == [
        67.75,
        29.62,
        30.26,
    ]
    assert on_disk["latency"]["compute"]["source"] == "given"
    assert len(on_disk["learner"]["phases"]) == 2
    decisions = on_disk["learner"]["decisions"]
    assert len(decisions["split"]) == on_disk["learner"]["plays"] > 300  # ~one per frame
    assert np.all(np.diff(decisions["sent_s"]) > 0)


def test_default_replay_edgeloc_beats_every_baseline_and_the_learner_holds_the_best_split(
    tmp_path: Path,
) -> None:
    """90 s of default.yaml with the plausibility gate (beyond the paper, on EdgeLoc and KF).

    EdgeLoc beats VO and DNN by at least the paper's margins and the Kalman baseline (fixed
    Q/R of the scenario) by a clear margin, though below the paper's 30.26% (see the bench for
    the figures and for Kalman filters with other R). The learner: per bandwidth phase the
    split it played most is the best in hindsight, with >= 80% of the plays in the phase's
    second half (the ceiling of the paper's exploration rule is 96% for K = 3, W = 100; in the
    2 Mbit/s phase the best split leads the next by ~16 ms, a few times the std of a request's
    four jittered messages, so UCB1-normal keeps sampling the runner-up more)."""
    sc = load(ROOT / "scenarios" / "default.yaml")
    summary = replay_scenario(sc, tmp_path, COMPUTE).summary
    red = {r["versus"]: r for r in summary["paper_comparison"]["reductions"]}
    assert red["vo"]["ours_pct"] >= red["vo"]["paper_pct"]
    assert red["dnn"]["ours_pct"] >= red["dnn"]["paper_pct"]
    assert red["kalman"]["ours_pct"] >= 10.0
    for ph in summary["learner"]["phases"]:
        assert ph["chosen"] == ph["best_in_hindsight"] == ph["expected_best"]
        assert ph["share_best_second_half"] >= 0.8
    # the robust detector does not reset on every lost packet: a few resets in 90 s, not ~15
    assert len(summary["learner"]["resets"]) <= 5


def test_replay_is_deterministic(smoke_run) -> None:
    _, first, result = smoke_run
    again = run_replay(result.config, result.latency)
    second = again.summary()
    for key in ("methods", "learner", "latency", "fusion"):
        assert first[key] == second[key]


def _short_config(**changes: object) -> ReplayConfig:
    return replace(ReplayConfig(seed=7, duration_s=12.0), **changes)


def test_more_latency_means_more_error_at_the_extremes() -> None:
    from nodes.edgeloc.dataset import open_dataset
    from nodes.edgeloc.replay import InferenceCache
    from nodes.edgeloc.train import load_model

    # 90 s: over a short drive VO has not drifted and a late DNN gains nothing
    cfg = _short_config(
        duration_s=90.0, learner=replace(ReplayConfig().learner, fixed_split="conv4")
    )
    ds = open_dataset("synthetic", seed=7, duration_s=90.0)
    model = load_model()
    cache = InferenceCache(model, ds, cfg.codec)
    totals = []
    for delay in (0.01, 0.8):
        path = PathSchedule.constant(PathState(rate_bps=20e6, delay_s=delay))
        down = PathSchedule.constant(PathState(rate_bps=200e6))
        lm = LatencyModel(COMPUTE, path, down, timeout_s=3.0)
        res = run_replay(cfg, lm, ds, model, cache)
        totals.append(res.summary()["methods"]["edgeloc"]["position_m"]["total"])
    assert totals[1] > 2 * totals[0]


def test_the_inference_cache_renders_each_frame_once_and_answers_as_without_the_memo() -> None:
    """A comparison of fixed splits asks for each frame once per split: the frame is rendered
    once, kept up to `max_images`, and every answer is bit for bit the one computed from a
    fresh render."""
    from nodes.edgeloc.dataset import open_dataset
    from nodes.edgeloc.replay import InferenceCache
    from nodes.edgeloc.train import load_model

    class Counting:
        """The drive, counting its renders."""

        def __init__(self, seed: int) -> None:
            self.inner = open_dataset("synthetic", seed=seed, duration_s=2.0)
            self.renders = 0

        def image(self, i: int) -> np.ndarray:
            self.renders += 1
            return self.inner.image(i)

    model = load_model()
    memo, bare = Counting(7), Counting(7)
    kept = InferenceCache(model, memo, "fp16-zlib", max_images=30)  # type: ignore[arg-type]
    fresh = InferenceCache(model, bare, "fp16-zlib", max_images=0)  # type: ignore[arg-type]
    frames, splits = range(40), ("image", "conv3", "vehicle")
    for split in splits:  # one split after another, as compare_splits asks
        for i in frames:
            a, b = kept.answer(i, split), fresh.answer(i, split)
            assert np.array_equal(a.pose, b.pose) and a.payload == b.payload
            assert a.entropy_nats == b.entropy_nats
    assert memo.renders == 30 + 3 * 10  # the first 30 kept, the other 10 rendered per split
    assert bare.renders == 3 * 40


def test_slow_vehicle_makes_the_split_move_with_bandwidth(smoke_run) -> None:
    sc = load(ROOT / "scenarios" / "smoke.yaml")
    slow = replace(
        sc, topology=replace(sc.topology, vehicles=(replace(sc.topology.vehicles[0], cpu=0.08),))
    )
    res = run_replay(replay_config(slow), latency_model(slow, COMPUTE))
    phases = res.phase_summaries()
    # 40 Mbit/s: the raw frame; 8 Mbit/s: a deeper split (conv3 and fc are within 1 ms there)
    assert phases[0]["expected_best"] == "image"
    assert SPLITS.index(phases[1]["expected_best"]) >= SPLITS.index("conv3")
    assert phases[0]["chosen"] != phases[1]["chosen"]
    assert all(p["best_in_hindsight"] is not None for p in phases)


def test_unknown_split_and_bad_file_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown split point"):
        ReplayConfig(splits=("conv9",))
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nname: x\n")
    out = CliRunner().invoke(app, ["replay", str(bad), "--runs-dir", str(tmp_path)])
    assert out.exit_code == 2, out.output
    assert "error" in out.output and "bad.yaml" in out.output
    assert list(tmp_path.iterdir()) == [bad]  # no run folder


def test_command_prints_table_and_headline(tmp_path: Path, monkeypatch) -> None:
    import testbed.replay.path as rc

    monkeypatch.setattr(rc, "compute_profile", lambda codec, weights: COMPUTE)
    monkeypatch.setenv("COLUMNS", "200")  # one table row a line
    out = CliRunner().invoke(
        app, ["replay", str(ROOT / "scenarios" / "smoke.yaml"), "--runs-dir", str(tmp_path)]
    )
    assert out.exit_code == 0, out.output
    lines = [line.strip() for line in out.output.splitlines() if line.strip()]
    assert lines[0].split()[0] == "method"
    assert lines[-1].startswith("EdgeLoc total error")
    assert "(paper 67.75%)" in lines[-1] and "(paper 30.26%)" in lines[-1]
    assert any(line.startswith("phase 0-10 s") for line in lines)
    assert math.isfinite(float(lines[4].split()[1]))  # edgeloc's total


# ---- the request protocol, the reference compute profile, re-convergence ------------------------


def _quiet_model(exchange: Exchange, tail_s: float = 0.0) -> LatencyModel:
    compute = ComputeProfile(
        splits=("image", "vehicle"), head_core_s=(0.0, tail_s), tail_core_s=(tail_s, 0.0)
    )
    up = PathSchedule.constant(PathState(rate_bps=8e6, delay_s=0.009))
    down = PathSchedule.constant(PathState(rate_bps=200e6, delay_s=0.009))
    return LatencyModel(compute, up, down, exchange=exchange)


def test_action_handshake_adds_one_round_trip_and_the_fixed_overhead() -> None:
    rng = np.random.default_rng(0)
    plain = _quiet_model(Exchange()).timing("image", 0.0, 10_000, rng)
    action = _quiet_model(Exchange(handshakes=1, overhead_s=0.01)).timing("image", 0.0, 10_000, rng)
    small = 8.0 * wire_bytes(Exchange().handshake_payload)
    shake = small / 200e6 + 0.009 + small / 8e6 + 0.009
    assert action.latency_s - plain.latency_s == pytest.approx(shake + 0.01)
    assert action.exchange_s == pytest.approx(shake + 0.01) and plain.exchange_s == 0.0
    # the noise-free model agrees with a jitter- and loss-free request
    lm = _quiet_model(Exchange(handshakes=1, overhead_s=0.01))
    assert lm.expected_s("image", 0.0, 10_000) == pytest.approx(action.latency_s)


def test_handshake_overlaps_the_edge_compute() -> None:
    """The edge runs the goal as soon as it accepts it: a tail longer than the handshake hides
    it, a shorter one is hidden by it."""
    rng = np.random.default_rng(0)
    ex = Exchange(handshakes=1)
    long_tail = _quiet_model(ex, tail_s=0.1).timing("image", 0.0, 1000, rng)
    long_plain = _quiet_model(Exchange(), tail_s=0.1).timing("image", 0.0, 1000, rng)
    assert long_tail.latency_s == pytest.approx(long_plain.latency_s)
    with pytest.raises(ValueError, match="handshakes and overhead_s"):
        Exchange(handshakes=-1)


def test_compute_profile_json_round_trip_and_committed_reference() -> None:
    assert ComputeProfile.from_json(COMPUTE.to_json()) == COMPUTE
    ref = ComputeProfile.reference()
    assert ref is not None and ref.splits == SPLITS and ref.source.startswith("reference")
    assert all(0 < s < 0.02 for s in ref.head_core_s + ref.tail_core_s)  # a small network
    # deeper splits cost the vehicle more and the edge less
    assert ref.head_core_s[0] < ref.head_core_s[-1] and ref.tail_core_s[0] > ref.tail_core_s[-1]
    with pytest.raises(ValueError, match="predates per-call profiles"):
        ComputeProfile.from_json({"splits": ["image"], "stage_s": [], "encode_s": [0.0]})
    assert ComputeProfile.reference(ROOT / "no-such-profile.json") is None


def test_measure_reference_keeps_the_fastest_round(monkeypatch) -> None:
    rounds = iter(
        [
            replace(COMPUTE, head_core_s=tuple(2 * s for s in COMPUTE.head_core_s)),
            COMPUTE,
            replace(COMPUTE, tail_core_s=tuple(3 * s for s in COMPUTE.tail_core_s)),
        ]
    )
    monkeypatch.setattr(ComputeProfile, "measure", classmethod(lambda cls, *a, **k: next(rounds)))
    ref = ComputeProfile.measure_reference(None, np.zeros((1,)), "fp16-zlib", rounds=3)
    assert (ref.head_core_s, ref.tail_core_s) == (COMPUTE.head_core_s, COMPUTE.tail_core_s)


def test_convergence_finds_the_first_window_the_best_arm_holds() -> None:
    plays = ["a"] * 30 + ["b", "a", "b", "b", "b"] + ["b"] * 40
    at = convergence(plays, "b", window=20, share=0.8)
    assert at == 27  # plays 27-46: three a's, then one more among b's: 16 of 20 are b
    assert plays[at : at + 20].count("b") >= 16
    assert all(plays[i : i + 20].count("b") < 16 for i in range(at))
    assert convergence(["a"] * 50, "b") is None and convergence(["b"] * 5, "b") is None


def test_vehicle_picks_the_path_the_replay_models(tmp_path: Path, monkeypatch) -> None:
    # multi_vehicle_nr: av4 drives to the cell edge (MCS 5) half-way, the others do not; the
    # replay of av4 must take its path and its radio, av1's not.
    import testbed.replay.path as rc

    monkeypatch.setattr(rc, "compute_profile", lambda codec, weights: COMPUTE)
    text = (ROOT / "scenarios" / "multi_vehicle_nr.yaml").read_text()
    sc = loads(text.replace("duration: 40s", "duration: 8s").replace("at: 20s", "at: 4s"))
    av4 = replay_scenario(sc, tmp_path, COMPUTE, compare=False, vehicle="av4").summary
    av1 = replay_scenario(sc, tmp_path, COMPUTE, compare=False).summary
    assert (av4["vehicle"], av1["vehicle"]) == ("av4", "av1")
    notes = av4["settings"]["network"]["notes"]
    assert notes[0] == "vehicle av4: path av4-gnb1 + gnb1-core1"
    rates = [p["uplink_rate_bps"] for p in av4["learner"]["phases"]]
    assert rates[1] < rates[0] and av1["learner"]["phases"][1]["uplink_rate_bps"] == rates[0]
    with pytest.raises(BadInput, match="no EdgeLoc vehicle 'av9'"):
        replay_scenario(sc, tmp_path, COMPUTE, compare=False, vehicle="av9")
    out = CliRunner().invoke(
        app,
        ["replay", str(ROOT / "scenarios" / "smoke.yaml"), "--vehicle", "av9",
         "--runs-dir", str(tmp_path)],
    )  # fmt: skip
    assert out.exit_code == 2 and "av9" in out.output, out.output


@pytest.mark.parametrize("split", ["conv3", "vehicle"])
def test_the_confidence_weight_weights_each_answer_by_the_dnns_own_entropy(split: str) -> None:
    """The replay hands the fuser each answer's place entropy, computed where the last stage
    ran (the edge from the decoded activation, the vehicle from its own `fc`): every fused
    answer's weight is the plain run's times `confidence_weight` of that entropy."""
    from nodes.edgeloc.dataset import open_dataset
    from nodes.edgeloc.fusion import ConfidenceWeight, confidence_weight
    from nodes.edgeloc.replay import InferenceCache
    from nodes.edgeloc.train import load_model

    plain = _short_config(robust_c=None, learner=replace(ReplayConfig().learner, fixed_split=split))
    weight = ConfidenceWeight(per_nat=1.9, reference_nats=0.98)
    ds = open_dataset("synthetic", seed=7, duration_s=12.0)
    model = load_model()
    cache = InferenceCache(model, ds, plain.codec)
    path = PathSchedule.constant(PathState(rate_bps=20e6, delay_s=0.02))
    lm = LatencyModel(
        COMPUTE, path, PathSchedule.constant(PathState(rate_bps=200e6)), timeout_s=3.0
    )
    runs = [run_replay(c, lm, ds, model, cache) for c in (plain, replace(plain, confidence=weight))]
    pairs = [(a, b) for a, b in zip(*(r.plays for r in runs), strict=True) if a.weight and b.weight]
    assert len(pairs) > 50
    factors = []
    for a, b in pairs:
        entropy = cache.answer(a.frame, split).entropy_nats
        assert entropy is not None and entropy >= 0
        factors.append(confidence_weight(entropy, weight))
        assert b.weight == pytest.approx(a.weight * factors[-1], rel=1e-9)
    assert min(factors) < 0.5 < max(factors) == 1.0  # some answers are doubted, most are not
