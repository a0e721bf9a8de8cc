"""The delayed-measurement EKF (`fusion.method: ekf`, beyond the paper).

The oracles are not the filter's own code: the synthetic VO (`world.vo_trace`) draws its drift
from the model the filter assumes, so the filter's covariance must be consistent with its
errors (normalised estimation error squared ≈ χ² with 2 degrees of freedom, mean 2), and its
drift states must converge to the scale and bias the trace drew.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from nodes.edgeloc import geometry
from nodes.edgeloc.ekf import MAX_INFLATION, DelayedEkf, EkfNoise, correlation_inflation
from nodes.edgeloc.fusion import EdgeLocFuser
from nodes.edgeloc.settings import (
    KalmanSettings,
    ReplayConfig,
    config_from_dict,
    config_to_dict,
)
from nodes.edgeloc.world import VoNoise, vo_trace
from testbed.replay import replay_config
from testbed.scenario import load

RATE_HZ = 20.0
SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def _route(seconds: float, speed: float = 10.0) -> np.ndarray:
    """Ground truth at RATE_HZ: straight stretches and gentle turns, as a car drives."""
    n = int(seconds * RATE_HZ)
    t = np.arange(n) / RATE_HZ
    yaw_rate = 0.15 * np.sin(2 * np.pi * t / 20.0)
    poses = [geometry.pose(5.0, -3.0, 0.4)]
    for w in yaw_rate[1:]:
        poses.append(geometry.compose(poses[-1], np.array([speed / RATE_HZ, 0.0, w / RATE_HZ])))
    return np.array(poses)


def _run(
    ekf: DelayedEkf,
    gt: np.ndarray,
    vo: np.ndarray,
    answers: dict[int, np.ndarray],
    delay_frames: int,
) -> np.ndarray:
    """Feed every frame; the answer for frame j (if any) arrives just after frame
    j + `delay_frames` (0: as soon as its frame is odometered)."""
    out = np.empty_like(gt)
    for i in range(len(gt)):
        ekf.on_vo(vo[i], i / RATE_HZ)
        j = i - delay_frames
        if j in answers:
            ekf.on_dnn(answers[j], j / RATE_HZ, i / RATE_HZ)
        out[i] = ekf.pose
    return out


def _answers(
    gt: np.ndarray, every: int, sigma: float, rng: np.random.Generator, yaw_sigma: float = 0.05
) -> dict:
    return {
        i: gt[i] + np.array([*rng.normal(0, sigma, 2), rng.normal(0, yaw_sigma)])
        for i in range(every, len(gt), every)
    }


def test_without_answers_it_dead_reckons_exactly_like_the_vo() -> None:
    gt = _route(20)
    vo = vo_trace(gt, RATE_HZ, np.random.default_rng(1))
    ekf = DelayedEkf()
    out = _run(ekf, gt, vo, {}, 0)
    np.testing.assert_allclose(out[:, :2], vo[:, :2], atol=1e-9)
    assert ekf.drift == (1.0, 0.0)


def test_a_late_answer_gives_exactly_the_state_an_on_time_answer_gives() -> None:
    gt = _route(10)
    vo = vo_trace(gt, RATE_HZ, np.random.default_rng(2))
    answers = _answers(gt, 5, 1.0, np.random.default_rng(3))
    on_time, late = DelayedEkf(robust_c=2.0), DelayedEkf(robust_c=2.0)
    a = _run(on_time, gt, vo, answers, 0)
    b = _run(late, gt, vo, answers, 3)  # 150 ms late: corrected at t0, VO replayed since
    # From the frame after the last answer landed, both have seen the same information.
    np.testing.assert_allclose(a[-1], b[-1], atol=1e-9)
    np.testing.assert_allclose(on_time.drift, late.drift, atol=1e-12)


def test_covariance_is_consistent_with_its_errors_nees() -> None:
    """Mean position NEES over many drives ≈ 2 (χ², 2 dof) when the noise is the model's."""
    noise = EkfNoise(r_pos=1.0)
    nees = []
    for seed in range(48):
        rng = np.random.default_rng(100 + seed)
        gt = _route(30)
        vo = vo_trace(gt, RATE_HZ, rng, VoNoise())
        answers = _answers(gt, 4, 1.0, rng, 0.1)  # σ 1 m, 0.1 rad: R = 1 m², 0.01 rad²
        ekf = DelayedEkf(noise)
        for i in range(len(gt)):
            if i - 2 in answers:
                ekf.on_dnn(answers[i - 2], (i - 2) / RATE_HZ, i / RATE_HZ)
            ekf.on_vo(vo[i], i / RATE_HZ)
            if i > 200 and i % 20 == 0:  # after the start-up transient, every second
                x, p = ekf._x[-1], ekf._p[-1]
                e = x[:2] - gt[i, :2]
                nees.append(float(e @ np.linalg.solve(p[:2, :2], e)))
    mean = float(np.mean(nees))
    # 48 drives x 20 samples, correlated in time (1.93 measured): a band that catches a
    # covariance off by 2x either way (mean 1 or 4).
    assert 1.5 < mean < 2.6, f"mean NEES {mean:.2f}, expected ~2 for a consistent filter"


def test_it_learns_the_vo_scale_and_yaw_rate_bias_the_trace_drew() -> None:
    gt = _route(120)
    vo_noise = VoNoise(scale_bias_std=0.0, yaw_rate_bias_std=0.0, yaw_rate_walk=0.0)
    # A known 5% scale error and 0.01 rad/s heading drift on top of the trace's small noise.
    raw = vo_trace(gt, RATE_HZ, np.random.default_rng(4), vo_noise)
    steps = geometry.between(raw[:-1], raw[1:])
    steps[:, :2] *= 1.05
    steps[:, 2] += 0.01 / RATE_HZ
    vo = [raw[0]]
    for s in steps:
        vo.append(geometry.compose(vo[-1], s))
    noise = EkfNoise(scale_std=0.1, bias_std=0.02, r_pos=0.25)
    ekf = DelayedEkf(noise)
    _run(ekf, gt, np.array(vo), _answers(gt, 4, 0.5, np.random.default_rng(5)), 3)
    c, b = ekf.drift  # type: ignore[misc]
    assert c == pytest.approx(1 / 1.05, abs=0.005)
    assert b == pytest.approx(0.01, abs=0.002)


def test_it_beats_the_papers_weight_on_drifting_vo() -> None:
    errs = {"ekf": [], "paper": []}
    for seed in range(4):
        rng = np.random.default_rng(200 + seed)
        gt = _route(60)
        vo = vo_trace(gt, RATE_HZ, rng, VoNoise(scale_bias_std=0.05))
        answers = _answers(gt, 3, 1.5, rng)
        fusers = {"ekf": DelayedEkf(EkfNoise(r_pos=2.25)), "paper": EdgeLocFuser(2.0, -1.4)}
        for name, f in fusers.items():
            out = np.empty_like(gt)
            for i in range(len(gt)):
                if i - 3 in answers:
                    f.on_dnn(answers[i - 3], (i - 3) / RATE_HZ, i / RATE_HZ)
                out[i] = f.on_vo(vo[i], i / RATE_HZ)
            errs[name].append(np.hypot(*(out[:, :2] - gt[:, :2]).T).mean())
    assert np.mean(errs["ekf"]) < 0.8 * np.mean(errs["paper"]), errs


def test_the_robust_weight_shrugs_off_a_look_alike_street() -> None:
    gt = _route(20)
    vo = vo_trace(gt, RATE_HZ, np.random.default_rng(6))
    answers = _answers(gt, 4, 1.0, np.random.default_rng(7))
    answers[300] = gt[300] + np.array([25.0, -10.0, 0.0])  # 27 m off
    moved = {}
    for c in (None, 2.0):
        ekf = DelayedEkf(robust_c=c)
        before = _run(ekf, gt[:305], vo[:305], {k: v for k, v in answers.items() if k < 300}, 0)
        ekf.on_dnn(answers[300], 300 / RATE_HZ, 305 / RATE_HZ)
        moved[c] = float(np.hypot(*(ekf.pose[:2] - before[-1][:2])))  # type: ignore[index]
    assert moved[2.0] < 0.1 * moved[None], moved
    assert ekf.last_update is not None and 0 < ekf.last_update.weight < 0.01


def test_answers_it_cannot_place_are_dropped() -> None:
    ekf = DelayedEkf(history_s=1.0)
    assert ekf.on_dnn(geometry.pose(0, 0, 0), 0.0, 0.1) is None  # no VO yet
    for i in range(60):
        ekf.on_vo(geometry.pose(i * 0.5, 0, 0), i / RATE_HZ)
    assert ekf.on_dnn(geometry.pose(0, 0, 0), 0.5, 2.9) is None  # older than the history
    assert ekf.dropped == 2
    assert ekf.on_dnn(geometry.pose(28, 1, 0), 2.8, 2.95) is not None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"r_pos": 0.0}, "r_pos must be a variance > 0"),
        ({"trans_per_sqrt_m": -1.0}, "trans_per_sqrt_m must be a number >= 0"),
        ({"scale_std": math.nan}, "scale_std must be a number >= 0"),
    ],
)
def test_bad_noise_is_a_clear_error(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        EkfNoise(**kwargs)


def test_vo_stamps_must_increase() -> None:
    ekf = DelayedEkf()
    ekf.on_vo(geometry.pose(0, 0, 0), 1.0)
    with pytest.raises(ValueError, match="VO stamps must increase"):
        ekf.on_vo(geometry.pose(1, 0, 0), 1.0)


def test_the_settings_build_the_fuser_they_name() -> None:
    cfg = ReplayConfig(fusion_method="ekf", kalman=KalmanSettings(r_pos=3.0, r_yaw=0.02))
    fuser = cfg.build_fuser()
    assert isinstance(fuser, DelayedEkf)
    assert (fuser.noise.r_pos, fuser.noise.r_yaw, fuser.robust_c) == (3.0, 0.02, 2.0)
    assert isinstance(ReplayConfig().build_fuser(), EdgeLocFuser)
    with pytest.raises(ValueError, match="unknown fusion method 'kf'; known: paper, ekf"):
        ReplayConfig(fusion_method="kf")


# ---- correlated answers (`correlation_s`) -----------------------------------------------------


def test_the_inflation_is_the_variance_of_the_mean_of_correlated_pairs() -> None:
    tau = 0.2
    # ρ = exp(-gap/τ); gap = τ ln 3 gives ρ = 1/3, so (1 + ρ) / (1 − ρ) = 2
    assert correlation_inflation(tau * math.log(3), tau) == pytest.approx(2.0)
    assert correlation_inflation(10.0, tau) == pytest.approx(1.0, abs=1e-12)
    assert correlation_inflation(0.0, tau) == MAX_INFLATION
    gaps = [0.01, 0.05, 0.1, 0.2, 0.5]
    factors = [correlation_inflation(g, tau) for g in gaps]
    assert factors == sorted(factors, reverse=True)


def _ar1_answers(gt: np.ndarray, tau: float, sigma: float, rng: np.random.Generator) -> dict:
    """An answer every frame whose position error is AR(1): correlation exp(-gap/τ)."""
    rho = math.exp(-1.0 / (RATE_HZ * tau))
    e = rng.normal(0.0, sigma, 2)
    out = {}
    for i in range(len(gt)):
        e = rho * e + math.sqrt(1 - rho**2) * rng.normal(0.0, sigma, 2)
        out[i] = gt[i] + np.array([e[0], e[1], rng.normal(0.0, 0.05)])
    return out


def _nees_on_correlated_answers(correlation_s: float | None) -> float:
    nees = []
    for seed in range(16):
        rng = np.random.default_rng(300 + seed)
        gt = _route(30)
        vo = vo_trace(gt, RATE_HZ, rng, VoNoise())
        answers = _ar1_answers(gt, 0.25, 1.0, rng)
        ekf = DelayedEkf(EkfNoise(r_pos=1.0, r_yaw=0.0025), correlation_s=correlation_s)
        for i in range(len(gt)):
            ekf.on_vo(vo[i], i / RATE_HZ)
            ekf.on_dnn(answers[i], i / RATE_HZ, i / RATE_HZ)
            if i > 200 and i % 20 == 0:
                x, p = ekf._x[-1], ekf._p[-1]
                e = x[:2] - gt[i, :2]
                nees.append(float(e @ np.linalg.solve(p[:2, :2], e)))
    return float(np.mean(nees))


def test_with_the_answers_correlation_time_its_covariance_stays_honest() -> None:
    """Answers every 50 ms whose errors are correlated over 250 ms: taken as white, the filter
    believes it knows the pose far better than it does (NEES well above 2); told the
    correlation time, its confidence comes back towards what its errors are."""
    white = _nees_on_correlated_answers(None)
    told = _nees_on_correlated_answers(0.25)
    print(f"mean NEES: taken as white {white:.2f}, told the correlation {told:.2f}")
    assert white > 4.0
    assert told < 0.5 * white
    assert abs(told - 2.0) < abs(white - 2.0)


def test_an_answer_right_after_another_moves_the_estimate_less() -> None:
    gt = _route(5)
    vo = vo_trace(gt, RATE_HZ, np.random.default_rng(9), VoNoise())
    gains = {}
    for corr in (None, 0.25):
        ekf = DelayedEkf(EkfNoise(r_pos=1.0), correlation_s=corr)
        for i in range(40):
            ekf.on_vo(vo[i], i / RATE_HZ)
        ekf.on_dnn(gt[30], 30 / RATE_HZ, 39 / RATE_HZ)
        first = ekf.last_update.weight  # type: ignore[union-attr]
        ekf.on_dnn(gt[31], 31 / RATE_HZ, 39 / RATE_HZ)
        gains[corr] = (first, ekf.last_update.weight)  # type: ignore[union-attr]
    assert gains[0.25][0] == pytest.approx(gains[None][0])  # the first answer is as before
    assert gains[0.25][1] < 0.5 * gains[None][1]  # its neighbour counts for much less
    with pytest.raises(ValueError, match="correlation time must be a positive number"):
        DelayedEkf(correlation_s=0.0)


def test_the_scenario_sets_the_correlation_time(tmp_path: Path) -> None:
    text = (SCENARIOS / "default.yaml").read_text()
    assert "fusion: {k_s: 2, dt0: -1400ms, robust: 2}" in text
    file = tmp_path / "ekf.yaml"
    file.write_text(text.replace("robust: 2}", "robust: 2, method: ekf, correlation: 150ms}"))
    cfg = replay_config(load(file))
    assert cfg.dnn_correlation_s == pytest.approx(0.15)
    fuser = cfg.build_fuser()
    assert isinstance(fuser, DelayedEkf) and fuser.correlation_s == 0.15
    assert "correlated over 150 ms" in cfg.describe_fusion()
    # the nodes read it from their settings file (JSON), as a real run passes it
    again = config_from_dict(json.loads(json.dumps(config_to_dict(cfg))))
    assert again == cfg and again.build_fuser().correlation_s == 0.15  # type: ignore[union-attr]
