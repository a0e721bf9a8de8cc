"""A scenario's EdgeLoc workload as the plain settings that the ROS nodes and the replay share
(`nodes.edgeloc.settings.ReplayConfig`).

Kept apart from `testbed.replay` so that what needs only the settings imports no torch: the
orchestrator of `testbed run` writes them for its nodes (`testbed.supervisor`) and never runs
the DNN. Importing torch there as the nodes started cost ~2 s and ~200,000 objects, with full
passes of the garbage collector of up to ~100 ms meanwhile (`make bench BENCH=orchestrator_gc`
prints both ways).
"""

from __future__ import annotations

from nodes.edgeloc.fusion import ConfidenceWeight
from nodes.edgeloc.gate import GateSettings
from nodes.edgeloc.settings import (
    KalmanSettings,
    LearnerSettings,
    ReplayConfig,
    confidence_file,
)
from testbed.scenario.model import Scenario, from_route

DEFAULT_GATE = GateSettings()  # beyond the paper; see nodes.edgeloc.gate


def replay_config(scenario: Scenario, gate: GateSettings | None = DEFAULT_GATE) -> ReplayConfig:
    """The plain replay settings of a scenario's workload."""
    w = scenario.workload
    lr = w.learner
    # Phases: between timeline events, and where cross-traffic starts or stops.
    # The channel's radio changes (`testbed.mobility`, several a second) and its handovers
    # are not phases.
    edges = [e.at_s for e in scenario.timeline if not from_route(e)]
    edges += [t for f in scenario.traffic for t in (f.start_s, f.stop_s) if t is not None]
    times = sorted({0.0, *(t for t in edges if t < scenario.duration_s)})
    return ReplayConfig(
        name=scenario.name,
        seed=scenario.seed,
        duration_s=scenario.duration_s,
        rate_hz=w.rate_hz,
        dataset=str(w.dataset),
        corruption=w.corruption,
        codec=w.codec,
        weights=None if w.weights is None else str(w.weights),
        splits=tuple(w.splits) if w.splits else ReplayConfig().splits,
        learner=LearnerSettings(
            window=lr.window,
            cost=lr.cost,
            fixed_split=lr.fixed_split,
            detector=lr.detector,
            kl_threshold=lr.kl_threshold,
            consecutive=lr.consecutive,
            detector_window=lr.detector_window,
        ),
        k_s=w.fusion.k_s,
        dt0_s=w.fusion.dt0_s,
        robust_c=w.fusion.robust_c,
        robust_centre_s=w.fusion.robust_centre_s,
        fusion_method=w.fusion.method,
        dnn_correlation_s=w.fusion.correlation_s,
        confidence=(
            ConfidenceWeight.read(confidence_file(w.weights)) if w.fusion.confidence else None
        ),
        kalman=KalmanSettings(w.kalman.q_pos, w.kalman.q_yaw, w.kalman.r_pos, w.kalman.r_yaw),
        gate=gate,
        phases=tuple(times),
    )


__all__ = ["DEFAULT_GATE", "replay_config"]
