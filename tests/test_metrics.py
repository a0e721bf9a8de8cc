"""Error metrics against evo's APE, the paper comparison, and TUM files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodes.edgeloc import geometry
from nodes.edgeloc.metrics import (
    PAPER_REDUCTIONS_PCT,
    PAPER_TOTALS,
    ErrorStats,
    correlation_time,
    error_autocorrelation,
    heading_errors_deg,
    independent_answers_per_s,
    paper_comparison,
    position_errors,
    read_tum,
    write_tum,
)


def _trajectories(n: int = 300, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    gt = [geometry.pose(10.0, -3.0, 1.0)]
    for _ in range(n - 1):
        gt.append(geometry.compose(gt[-1], [rng.uniform(0.5, 1.5), 0.0, rng.normal(0, 0.1)]))
    gt_a = np.array(gt)
    est = gt_a + np.column_stack([rng.normal(0, 2.0, (n, 2)), rng.normal(0, 0.2, n)])
    est[:, 2] = geometry.wrap(est[:, 2])
    stamps = 1_700_000_000.0 + 0.05 * np.arange(n)
    return stamps, est, gt_a


def test_position_error_stats_equal_evo_ape_translation(tmp_path: Path) -> None:
    evo_metrics = pytest.importorskip("evo.core.metrics", reason="evo is needed: pip install evo")
    file_interface = pytest.importorskip("evo.tools.file_interface")
    stamps, est, gt = _trajectories()
    write_tum(tmp_path / "est.tum", stamps, est)
    write_tum(tmp_path / "gt.tum", stamps, gt)
    traj_est = file_interface.read_tum_trajectory_file(str(tmp_path / "est.tum"))
    traj_ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.tum"))
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))  # no alignment: poses compared as they are
    evo_stats = ape.get_all_statistics()

    ours = ErrorStats.of(position_errors(est, gt))
    np.testing.assert_allclose(position_errors(est, gt), ape.error, rtol=0, atol=1e-9)
    assert ours.n == len(ape.error)
    assert ours.total == pytest.approx(float(np.sum(ape.error)), abs=1e-9)
    assert ours.mean == pytest.approx(evo_stats["mean"], abs=1e-9)
    assert ours.median == pytest.approx(evo_stats["median"], abs=1e-9)
    assert ours.rmse == pytest.approx(evo_stats["rmse"], abs=1e-9)
    assert ours.max == pytest.approx(evo_stats["max"], abs=1e-9)


def test_tum_round_trip_is_exact(tmp_path: Path) -> None:
    stamps, est, _ = _trajectories(50, seed=1)
    write_tum(tmp_path / "t.tum", stamps, est)
    t, p = read_tum(tmp_path / "t.tum")
    np.testing.assert_array_equal(t, stamps)
    np.testing.assert_array_equal(p[:, :2], est[:, :2])
    np.testing.assert_allclose(geometry.wrap(p[:, 2] - est[:, 2]), 0.0, atol=1e-12)


def test_bad_tum_file_names_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.tum"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 1 2 3\n")
    with pytest.raises(ValueError, match=r"bad.tum:3: expected 8 values"):
        read_tum(path)


def test_heading_error_is_wrapped_in_degrees() -> None:
    est = np.array([[0, 0, np.radians(179)], [0, 0, 0.1]])
    gt = np.array([[0, 0, np.radians(-179)], [0, 0, -0.1]])
    np.testing.assert_allclose(heading_errors_deg(est, gt), [2.0, np.degrees(0.2)], atol=1e-9)


def test_error_stats_on_known_values() -> None:
    s = ErrorStats.of([3.0, 1.0, 4.0, 2.0])
    assert (s.n, s.total, s.mean, s.median, s.max) == (4, 10.0, 2.5, 2.5, 4.0)
    assert s.rmse == pytest.approx(np.sqrt(7.5))
    assert s.p95 == pytest.approx(3.85)  # linear interpolation between 3 and 4
    with pytest.raises(ValueError, match="no frames"):
        ErrorStats.of([])


def test_mismatched_trajectories_are_named() -> None:
    with pytest.raises(ValueError, match="estimate has 2 frames but ground truth has 3"):
        position_errors(np.zeros((2, 3)), np.zeros((3, 3)))


def test_paper_reductions_follow_from_the_paper_totals() -> None:
    for other, printed in PAPER_REDUCTIONS_PCT.items():
        derived = 100 * (1 - PAPER_TOTALS["edgeloc"] / PAPER_TOTALS[other])
        assert derived == pytest.approx(printed, abs=0.005), other


def test_paper_comparison_puts_ours_beside_the_paper() -> None:
    cmp = paper_comparison({"edgeloc": 50.0, "vo": 200.0, "dnn": 80.0, "kalman": 100.0})
    totals = {t.method: (t.paper, t.ours) for t in cmp.totals}
    assert totals["edgeloc"] == (2676.35, 50.0)
    assert totals["vo"] == (8298.58, 200.0)
    reds = {r.versus: (r.paper_pct, r.ours_pct) for r in cmp.reductions}
    assert reds["vo"] == (67.75, pytest.approx(75.0))
    assert reds["dnn"] == (29.62, pytest.approx(37.5))
    assert reds["kalman"] == (30.26, pytest.approx(50.0))
    partial = paper_comparison({"edgeloc": 1.0})
    assert all(r.ours_pct is None for r in partial.reductions)
    assert partial.to_dict()["totals"][1] == {"method": "kalman", "paper": 3837.65, "ours": None}
    with pytest.raises(ValueError, match="unknown method"):
        paper_comparison({"edgeloc": 1.0, "ekf": 2.0})


def _ar1(n: int, tau_s: float, frame_s: float, seed: int) -> np.ndarray:
    """(n, 2) errors with autocorrelation exp(-lag/τ) (an AR(1) sampled every frame)."""
    rng = np.random.default_rng(seed)
    rho = np.exp(-frame_s / tau_s)
    e = np.empty((n, 2))
    e[0] = rng.normal(0, 1, 2)
    for i in range(1, n):
        e[i] = rho * e[i - 1] + np.sqrt(1 - rho**2) * rng.normal(0, 1, 2)
    return e


def test_autocorrelation_and_its_time_recover_an_ar1_process() -> None:
    frame_s = 0.05
    for tau in (0.1, 0.25):
        e = _ar1(40_000, tau, frame_s, seed=int(tau * 100))
        rho = error_autocorrelation(e, 6)
        expected = np.exp(-frame_s * np.arange(1, 7) / tau)
        np.testing.assert_allclose(rho, expected, atol=0.02)
        assert correlation_time(rho, frame_s) == pytest.approx(tau, rel=0.06)
    white = error_autocorrelation(np.random.default_rng(3).normal(size=(20_000, 2)), 4)
    assert np.all(np.abs(white) < 0.03)
    with pytest.raises(ValueError, match="white at one frame"):
        correlation_time(white, frame_s)
    with pytest.raises(ValueError, match=r"need \(N, 2\) errors"):
        error_autocorrelation(np.zeros((5, 3)), 2)


def test_independent_answers_per_s_is_what_the_mean_of_correlated_answers_is_worth() -> None:
    """The closed form against the exact variance of the mean of n answers with covariance
    ρ^|i−j| (the full matrix summed): n_eff = 1 / var(mean), per second n_eff / (n Δ)."""
    n = 1500
    lag = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    for interval, tau in ((0.07, 0.15), (0.22, 0.15), (0.05, 0.025), (0.1, 1.0)):
        var_mean = float((np.exp(-interval / tau) ** lag).sum()) / n**2
        exact = (1.0 / var_mean) / (n * interval)
        assert independent_answers_per_s(interval, tau) == pytest.approx(exact, rel=0.01)
    assert independent_answers_per_s(0.08, 0.0) == pytest.approx(12.5)
    # faster always carries more, but no more than 1 / 2τ however fast
    rates = [independent_answers_per_s(d, 0.15) for d in (0.3, 0.2, 0.1, 0.05, 0.001)]
    assert rates == sorted(rates) and rates[-1] == pytest.approx(1 / 0.3, rel=1e-4)
    for bad in ((0.0, 0.1), (0.1, -1.0)):
        with pytest.raises(ValueError, match="interval > 0"):
            independent_answers_per_s(*bad)
