"""The scenario library (`scenarios/*.yaml`): every file validates, matches the shipped JSON
Schema, and replays offline in a shortened form; the scenarios that exist to show one thing are
checked for that thing (no root needed; the real runs are in test_scenario_library_root.py).

Shortened: `testbed.sweep.shorten` cuts a scenario to a few seconds and scales its timeline
with it, so every phase, outage and shift is still played, briefly.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from netem.traces import load_trace
from nodes.edgeloc.geometry import wrap
from nodes.edgeloc.metrics import position_errors
from nodes.edgeloc.replay import ReplayResult, run_replay
from testbed.errors import BadInput
from testbed.replay import latency_model, replay_config
from testbed.scenario import json_schema, load
from testbed.scenario.model import OutageEvent, Scenario, TraceEvent
from testbed.sweep import load_tree, read_tree, shorten

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"
LIBRARY = sorted(SCENARIOS.glob("*.yaml"))
#: The library issue #7 asks for; more files are welcome (and tested the same way).
REQUIRED = {
    "smoke",
    "default",
    "latency_sweep",
    "kalman_vs_edgeloc",
    "handover_outage",
    "trace_driven",
    "multi_vehicle",
}
#: Length of the shortened replays (s): long enough for a few plays in every phase.
SHORT_S = {"latency_sweep": 8.0, "kalman_vs_edgeloc": 12.0, "handover_outage": 10.0}
DEFAULT_SHORT_S = 6.0


def _ids(paths: list[Path]) -> list[str]:
    return [p.stem for p in paths]


@functools.cache
def shortened(name: str, seconds: float) -> Scenario:
    file = SCENARIOS / f"{name}.yaml"
    return load_tree(shorten(read_tree(file), seconds), file, f"shortened to {seconds:g}s")


@functools.cache
def replayed(name: str, vehicle: str | None = None) -> tuple[Scenario, ReplayResult]:
    """The scenario shortened and replayed for one vehicle (cached: several tests read it)."""
    scenario = shortened(name, SHORT_S.get(name, DEFAULT_SHORT_S))
    result = run_replay(replay_config(scenario), latency_model(scenario, vehicle=vehicle))
    return scenario, result


def test_the_library_has_the_scenarios_of_issue_7() -> None:
    assert {p.stem for p in LIBRARY} >= REQUIRED, sorted(p.stem for p in LIBRARY)


@pytest.mark.parametrize("file", LIBRARY, ids=_ids(LIBRARY))
def test_every_scenario_validates(file: Path) -> None:
    scenario = load(file)
    # One name per scenario: run folders and reports say which file ran.
    assert scenario.name == file.stem


def test_validate_accepts_the_whole_library() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "testbed.cli", "validate", *map(str, LIBRARY)],
        cwd=REPO,
        capture_output=True,
        text=True,
        env={"CI": "1", "PATH": "/usr/bin:/bin"},
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.count(": valid (") == len(LIBRARY), r.stdout


def test_the_shipped_schema_is_what_testbed_schema_prints() -> None:
    shipped = json.loads((SCENARIOS / "scenario.schema.json").read_text())
    assert shipped == json_schema(), "regenerate: testbed schema > scenarios/scenario.schema.json"


@pytest.mark.parametrize("file", LIBRARY, ids=_ids(LIBRARY))
def test_every_scenario_points_editors_at_the_schema_and_satisfies_it(file: Path) -> None:
    import jsonschema

    first = file.read_text().splitlines()[0]
    assert first == "# yaml-language-server: $schema=scenario.schema.json", first
    jsonschema.Draft202012Validator(json_schema()).validate(yaml.safe_load(file.read_text()))


@pytest.mark.parametrize("file", LIBRARY, ids=_ids(LIBRARY))
def test_every_scenario_is_commented_for_authors(file: Path) -> None:
    """A header that says what the scenario shows, before the first key."""
    lines = file.read_text().splitlines()
    first_key = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    words = " ".join(line.lstrip("# ") for line in lines[1:first_key]).split()
    assert len(words) >= 15, f"{file.name}: say what the scenario is for in its header"


def test_the_shipped_trace_is_what_make_traces_writes() -> None:
    r = subprocess.run(
        [sys.executable, str(SCENARIOS / "traces" / "make_traces.py"), "--check"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr


# ---- every scenario replays ------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("file", LIBRARY, ids=_ids(LIBRARY))
def test_every_scenario_replays_shortened(file: Path) -> None:
    vehicles = [v.name for v in load(file).edgeloc_vehicles()]
    if not vehicles:  # workload: none: apps and traffic only, nothing the replay models
        with pytest.raises(BadInput, match="workload: none"):
            replayed(file.stem)
        return
    for vehicle in vehicles:
        scenario, result = replayed(file.stem, vehicle)
        n = round(scenario.duration_s * scenario.workload.rate_hz)
        assert len(result.timestamps) == n
        for method, poses in result.poses.items():
            assert poses.shape == (n, 3) and np.isfinite(poses).all(), method
        answered = [p for p in result.plays if not p.lost]
        assert len(answered) >= 5, (file.stem, vehicle, len(result.plays))
        summary = result.summary()
        assert summary["methods"]["edgeloc"]["position_m"]["total"] > 0  # type: ignore[index]
        assert len(summary["learner"]["phases"]) >= 1  # type: ignore[index]


# ---- what each scenario is for -----------------------------------------------------------------


def _phases(scenario: Scenario) -> list[tuple[float, float]]:
    bounds = [*sorted({0.0, *(e.at_s for e in scenario.timeline)}), scenario.duration_s]
    return [(a, b) for a, b in itertools.pairwise(bounds) if b > a]


@pytest.mark.slow
def test_latency_sweep_latency_rises_and_the_fusion_weight_falls_phase_by_phase() -> None:
    scenario, result = replayed("latency_sweep")
    phases = _phases(scenario)
    assert len(phases) == 4
    delta, weight = [], []
    for a, b in phases:
        plays = [p for p in result.plays if a <= p.sent_s < b and not p.lost]
        assert len(plays) >= 3, (a, b, len(plays))
        delta.append(float(np.mean([p.delta_s for p in plays])))
        # An answer the fusion did not apply (gated) gave EdgeLoc nothing: weight 0.
        weight.append(float(np.mean([p.weight or 0.0 for p in plays])))
    print(f"\nmean Δt per phase (ms): {[round(1000 * d, 1) for d in delta]}; mean u: {weight}")
    assert all(b > a for a, b in itertools.pairwise(delta)), delta
    assert all(b <= a for a, b in itertools.pairwise(weight)), weight
    assert weight[-1] < 0.1 * weight[0], weight
    # The last rung (100 ms each way) costs at least the extra round trip over the first (4 ms).
    assert delta[-1] - delta[0] > 2 * (0.100 - 0.004) * 0.9, delta


@pytest.mark.slow
def test_kalman_vs_edgeloc_edgeloc_discounts_late_answers_the_kalman_filter_does_not() -> None:
    """The difference the scenario is about: both get the same answers; in the late phase
    EdgeLoc's fusion weight u collapses with Δt while the Kalman filter fuses every answer as
    if it were current. (Which of the two is more accurate then depends on the fusion slope and
    the VO drift; the test prints the errors, the report shows them.)"""
    scenario, result = replayed("kalman_vs_edgeloc")
    good, late, _after = _phases(scenario)
    plays = {
        name: [p for p in result.plays if a <= p.sent_s < b and not p.lost]
        for name, (a, b) in (("good", good), ("late", late))
    }
    delta = {k: float(np.mean([p.delta_s for p in v])) for k, v in plays.items()}
    u = {k: float(np.mean([p.weight or 0.0 for p in v])) for k, v in plays.items()}
    t = result.timestamps
    err = {
        m: [
            round(float(position_errors(result.poses[m], result.gt)[(t >= a) & (t < b)].mean()), 2)
            for a, b in (good, late)
        ]
        for m in ("vo", "kalman", "edgeloc")
    }
    print(f"\nmean Δt {delta}; mean u {u}; mean error good, late phase (m) {err}")
    assert min(len(v) for v in plays.values()) >= 5, {k: len(v) for k, v in plays.items()}
    assert delta["late"] > delta["good"] + 0.15, delta  # the late phase is late
    assert u["late"] < 0.1 * u["good"], u  # EdgeLoc discounts late answers ...
    fused_by_kalman = sum(not p.gated_kalman for p in plays["late"]) / len(plays["late"])
    assert fused_by_kalman >= 0.8, fused_by_kalman  # ... the Kalman filter takes them as they are


@pytest.mark.slow
def test_handover_outage_no_answers_during_outages_and_fused_poses_dead_reckon() -> None:
    scenario, result = replayed("handover_outage")
    outages = [e for e in scenario.timeline if isinstance(e, OutageEvent)]
    assert len(outages) == 2
    # A reply already on the wire when the link drops still lands (as in the relay, whose
    # outage stops packets entering the link): allow one path delay plus jitter.
    in_flight_s = 0.030
    answers = np.array([p.answer_s for p in result.plays if not p.lost])
    t, vo, fused = result.timestamps, result.poses["vo"], result.poses["edgeloc"]
    for o in outages:
        start, end = o.at_s + in_flight_s, o.at_s + o.duration_s
        assert not ((answers >= start) & (answers < end)).any(), (o, answers)
        waiting = [p for p in result.plays if p.sent_s < end and (p.lost or p.answer_s > start)]
        assert waiting, f"no request was in flight during the outage at {o.at_s:g} s"
        # Frames inside the outage: the fused pose moves exactly as VO (no answer to fuse).
        frames = [i for i in range(1, len(t)) if start <= t[i - 1] and t[i] < end]
        assert len(frames) >= 0.8 * (end - start) * scenario.workload.rate_hz - 2, frames
        for i in frames:
            step_vo = np.hypot(*(vo[i, :2] - vo[i - 1, :2]))
            step_fused = np.hypot(*(fused[i, :2] - fused[i - 1, :2]))
            assert step_fused == pytest.approx(step_vo, abs=1e-9), i
            turn_vo = wrap(vo[i, 2] - vo[i - 1, 2])
            turn_fused = wrap(fused[i, 2] - fused[i - 1, 2])
            assert turn_fused == pytest.approx(turn_vo, abs=1e-9), i
    # And after the first outage, answers come back and are fused again.
    first_end = outages[0].at_s + outages[0].duration_s
    assert ((answers > first_end) & (answers < outages[1].at_s)).sum() >= 3


@pytest.mark.slow
def test_trace_driven_uplink_rate_follows_the_trace() -> None:
    scenario, result = replayed("trace_driven")
    (event,) = [e for e in scenario.timeline if isinstance(e, TraceEvent)]
    assert event.path == (SCENARIOS / "traces" / "5g-uplink-drive.csv").resolve()
    trace = load_trace(event.path)
    times = [s for s, _ in trace.steps]

    def trace_rate(t: float) -> float:
        u = math.fmod(t - event.at_s, trace.duration_s)
        return trace.steps[int(np.searchsorted(times, u + 1e-12, side="right")) - 1][1]

    seen = [(p.sent_s, p.uplink_rate_bps) for p in result.plays]
    assert len(seen) >= 10
    for sent, rate in seen:
        assert rate == pytest.approx(trace_rate(sent), rel=1e-9), sent
    # The run saw the trace move: several different rates over a few seconds.
    assert len({round(r) for _, r in seen}) >= 5, seen


@pytest.mark.slow
def test_multi_vehicle_each_vehicle_has_its_own_path_and_a_shape_hits_only_its_target() -> None:
    scenario, av1 = replayed("multi_vehicle", "av1")
    _, av2 = replayed("multi_vehicle", "av2")
    assert [v.name for v in scenario.topology.vehicles] == ["av1", "av2"]
    assert {v.gnb for v in scenario.topology.vehicles} == {"gnb1"}
    (shape_at,) = [e.at_s for e in scenario.timeline]
    # Both vehicles' uplinks run through the 20 Mbit/s backhaul (the bottleneck hop) ...
    assert {p.uplink_rate_bps for p in av1.plays} == {20e6}
    assert {p.uplink_rate_bps for p in av2.plays if p.sent_s < shape_at} == {20e6}
    # ... until av2 alone is capped to 2 Mbit/s.
    assert {p.uplink_rate_bps for p in av2.plays if p.sent_s >= shape_at} == {2e6}
    # av2 is farther from the gNB (12 ms instead of 8 ms each way): its answers take longer.
    lat1 = np.mean([p.latency_s for p in av1.plays if p.sent_s < shape_at and not p.lost])
    lat2 = np.mean([p.latency_s for p in av2.plays if p.sent_s < shape_at and not p.lost])
    assert lat2 > lat1 + 0.004, (lat1, lat2)


def test_multi_vehicle_the_capped_vehicle_moves_to_a_deeper_split_and_the_other_does_not() -> None:
    """What the scenario's header promises, on the whole drive: after the cap, av2's learner
    leaves the raw frame for a split that sends less; av1, whose link is untouched, keeps it."""
    scenario = load(SCENARIOS / "multi_vehicle.yaml")
    chosen = {}
    for vehicle in ("av1", "av2"):
        result = run_replay(replay_config(scenario), latency_model(scenario, vehicle=vehicle))
        chosen[vehicle] = [p["chosen"] for p in result.summary()["learner"]["phases"]]
    assert chosen["av1"] == ["image", "image"], chosen
    assert chosen["av2"][0] == "image" and chosen["av2"][1] != "image", chosen
