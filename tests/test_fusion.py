"""Time-zone revision, the latency weight, the EdgeLoc fuser and the DNN-hold baseline."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from nodes.edgeloc import geometry
from nodes.edgeloc.fusion import (
    ConfidenceWeight,
    DnnHold,
    EdgeLocFuser,
    VoHistory,
    confidence_weight,
    latency_weight,
    per_second_weight,
    time_zone_revision,
)


def _drive(n: int, seed: int = 0) -> np.ndarray:
    """A ground-truth SE(2) trajectory of n frames with random turns."""
    rng = np.random.default_rng(seed)
    poses = [geometry.pose(2.0, -1.0, 0.3)]
    for _ in range(n - 1):
        step = np.array([rng.uniform(0.5, 1.5), rng.normal(0, 0.05), rng.normal(0, 0.1)])
        poses.append(geometry.compose(poses[-1], step))
    return np.array(poses)


def test_revision_of_an_exact_dnn_pose_is_the_true_current_pose() -> None:
    gt = _drive(30)
    offset = geometry.pose(-7.0, 4.0, 2.5)  # VO lives in its own frame
    vo = geometry.compose(np.broadcast_to(offset, gt.shape), gt)
    for t0, t in [(3, 10), (0, 29), (12, 12), (20, 27)]:
        revised = time_zone_revision(gt[t0], vo[t0], vo[t])
        np.testing.assert_allclose(revised[:2], gt[t][:2], atol=1e-9)
        assert abs(geometry.wrap(revised[2] - gt[t][2])) < 1e-9


def test_latency_weight_is_the_papers_sigmoid_and_never_overflows() -> None:
    k, dt0 = 20.0, 0.25
    for dt in (0.0, 0.1, 0.25, 0.4, 1.0):
        assert latency_weight(dt, k, dt0) == pytest.approx(1 - 1 / (1 + math.exp(-k * (dt - dt0))))
    assert latency_weight(dt0, k, dt0) == 0.5
    assert latency_weight(1e6, k, dt0) == 0.0
    assert latency_weight(-1e6, k, dt0) == 1.0
    us = [latency_weight(dt, k, dt0) for dt in np.linspace(0, 1, 50)]
    assert (np.diff(us) < 0).all()  # later answers weigh less


def test_vo_only_dead_reckoning_follows_vo_motion_from_the_initial_pose() -> None:
    gt = _drive(40, seed=1)
    vo = geometry.compose(np.broadcast_to(geometry.pose(5, 5, 1.0), gt.shape), gt)
    fuser = EdgeLocFuser(k_s=20.0, dt0_s=0.25, initial=gt[0])
    out = np.array([fuser.on_vo(p, 0.05 * i) for i, p in enumerate(vo)])
    np.testing.assert_allclose(out[:, :2], gt[:, :2], atol=1e-9)
    np.testing.assert_allclose(geometry.wrap(out[:, 2] - gt[:, 2]), 0.0, atol=1e-9)
    no_initial = EdgeLocFuser(k_s=20.0, dt0_s=0.25)
    assert np.allclose(no_initial.on_vo(vo[0], 0.0), vo[0])  # VO frame taken as world frame


def test_dnn_answer_pulls_the_fused_pose_by_u_after_revision() -> None:
    gt = _drive(20, seed=2)
    drift = geometry.pose(0.5, -0.3, 0.02)  # VO has drifted from the start
    vo = geometry.compose(np.broadcast_to(drift, gt.shape), gt)
    k, dt0 = 20.0, 0.25
    fuser = EdgeLocFuser(k_s=k, dt0_s=dt0, initial=vo[0])
    for i in range(20):
        fuser.on_vo(vo[i], 0.05 * i)
    before = fuser.pose
    t0, t_now = 0.05 * 12, 0.05 * 19 + 0.01
    fused = fuser.on_dnn(gt[12], t0, t_now)  # an exact DNN answer for frame 12
    u = latency_weight(t_now - t0, k, dt0)
    upd = fuser.last_update
    assert upd is not None and upd.weight == pytest.approx(u)
    np.testing.assert_allclose(upd.revised[:2], gt[19][:2], atol=1e-9)
    np.testing.assert_allclose(fused, geometry.interpolate(before, gt[19], u), atol=1e-12)
    # The fused pose moved towards the truth by the fraction u.
    err_before = np.hypot(*(before[:2] - gt[19][:2]))
    err_after = np.hypot(*(fused[:2] - gt[19][:2]))
    assert err_after == pytest.approx((1 - u) * err_before, rel=1e-9)


def test_a_per_second_weight_pulls_as_hard_per_second_whatever_the_gap() -> None:
    """Its closed form: two blends g apart leave what one blend for 2g leaves, a gap of P gives
    u back, no gap pulls nothing."""
    for u in (0.0, 0.047, 0.5, 1.0):
        for g in (0.0, 0.03, 0.1, 0.37):
            once = per_second_weight(u, 2 * g, 0.1)
            twice = per_second_weight(u, g, 0.1)
            assert (1 - twice) ** 2 == pytest.approx(1 - once, abs=1e-12)
        assert per_second_weight(u, 0.1, 0.1) == pytest.approx(u)
        assert per_second_weight(u, 0.0, 0.1) == 0.0
    for bad in ((1.2, 0.1, 0.1), (0.5, -0.1, 0.1), (0.5, 0.1, 0.0)):
        with pytest.raises(ValueError, match="need 0 <= u <= 1"):
            per_second_weight(*bad)


@pytest.mark.parametrize("every_s", [0.05, 0.1, 0.2])
def test_with_pull_every_s_answers_twice_as_often_pull_no_harder_per_second(
    every_s: float,
) -> None:
    """A standing car whose fused pose is 2 m off, and n answers of the truth, `every_s` apart
    with 100 ms of latency. With P = 0.1 s the first answer pulls by u (it has no gap before
    it) and each later one as u does once every P, so the error kept is
    (1 − u)^(1 + (n − 1)·every_s/P): the time the answers span, not their number. The paper's
    per-answer u keeps (1 − u)^n."""
    k, dt0, latency, pull = 2.0, -1.4, 0.1, 0.1
    u = latency_weight(latency, k, dt0)
    truth = geometry.pose(0.0, 0.0, 0.0)
    n = round(1.0 / every_s)
    kept = {}
    for p in (pull, None):
        fuser = EdgeLocFuser(k, dt0, initial=geometry.pose(2.0, 0.0, 0.0), pull_every_s=p)
        fuser.on_vo(truth, -1.0)
        for i in range(1, n + 1):
            fuser.on_vo(truth, i * every_s)
            assert fuser.on_dnn(truth, i * every_s - latency, i * every_s) is not None
        pose = fuser.pose
        assert pose is not None
        kept[p] = float(np.hypot(*pose[:2])) / 2.0
    assert kept[pull] == pytest.approx((1 - u) ** (1 + (n - 1) * every_s / pull), rel=1e-9)
    assert kept[None] == pytest.approx((1 - u) ** n, rel=1e-9)
    with pytest.raises(ValueError, match="pull_every_s must be > 0"):
        EdgeLocFuser(k, dt0, pull_every_s=0.0)


def test_revision_interpolates_vo_between_stamps() -> None:
    hist = VoHistory(span_s=10.0)
    hist.add(1.0, geometry.pose(0, 0, 0.2))
    hist.add(2.0, geometry.pose(10, 0, 0.4))
    np.testing.assert_allclose(hist.at(1.25), [2.5, 0.0, 0.25])
    np.testing.assert_allclose(hist.at(5.0), [10, 0, 0.4])  # after the newest: the newest
    assert hist.at(0.5) is None


def test_history_is_bounded_by_time() -> None:
    hist = VoHistory(span_s=1.0)
    for i in range(200):
        hist.add(0.05 * i, geometry.pose(i, 0, 0))
    assert len(hist) <= 22  # 1 s at 20 Hz plus the one pose older than the span
    assert hist.at(0.05 * 199 - 1.0) is not None
    assert hist.at(0.05 * 199 - 1.2) is None


def test_unrevisable_dnn_answers_are_dropped_and_counted() -> None:
    fuser = EdgeLocFuser(k_s=20.0, dt0_s=0.25, history_s=1.0)
    assert fuser.on_dnn(geometry.pose(0, 0, 0), 0.0, 0.1) is None  # no VO yet
    for i in range(100):
        fuser.on_vo(geometry.pose(0.1 * i, 0, 0), 0.05 * i)
    assert fuser.on_dnn(geometry.pose(0, 0, 0), 0.5, 5.0) is None  # t0 older than the history
    assert fuser.dropped == 2


def test_orientation_is_fused_on_the_circle() -> None:
    fuser = EdgeLocFuser(k_s=1e-9, dt0_s=0.0, initial=geometry.pose(0, 0, 3.1))  # u = 0.5
    fuser.on_vo(geometry.pose(0, 0, 0), 0.0)
    fused = fuser.on_dnn(geometry.pose(0, 0, -3.1), 0.0, 0.0)
    assert fused is not None and abs(abs(fused[2]) - math.pi) < 1e-6  # not 0


def test_bad_inputs_are_named() -> None:
    fuser = EdgeLocFuser(k_s=20.0, dt0_s=0.25)
    fuser.on_vo([0, 0, 0], 1.0)
    with pytest.raises(ValueError, match=r"VO pose must be 3 finite numbers"):
        fuser.on_vo([0, 0], 2.0)
    with pytest.raises(ValueError, match="VO stamps must increase"):
        fuser.on_vo([0, 0, 0], 1.0)
    with pytest.raises(ValueError, match="arrived before its frame"):
        fuser.on_dnn([0, 0, 0], 2.0, 1.0)
    with pytest.raises(ValueError, match="k_s must be a positive"):
        EdgeLocFuser(k_s=0.0, dt0_s=0.25)


def test_two_threads_can_feed_the_fuser() -> None:
    fuser = EdgeLocFuser(k_s=20.0, dt0_s=0.25)
    errors: list[BaseException] = []
    fuser.on_vo(geometry.pose(0, 0, 0), 0.0)

    def vo_thread() -> None:
        try:
            for i in range(1, 2000):
                fuser.on_vo(geometry.pose(0.01 * i, 0, 0.001 * i), 0.001 * i)
        except BaseException as exc:  # reported below, not swallowed
            errors.append(exc)

    def dnn_thread() -> None:
        try:
            for i in range(500):
                fuser.on_dnn(geometry.pose(0.04 * i, 0.1, 0.004 * i), 0.004 * i, 0.004 * i + 0.02)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=vo_thread), threading.Thread(target=dnn_thread)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors
    assert np.isfinite(fuser.pose).all()


def test_dnn_hold_holds_the_latest_answer_or_revises_it() -> None:
    gt = _drive(10, seed=3)
    held = DnnHold()
    revised = DnnHold(revise=True)
    for i in range(10):
        assert held.on_vo(gt[i], 0.1 * i) is None  # nothing to hold before a DNN answer
        revised.on_vo(gt[i], 0.1 * i)
    held.on_dnn(gt[2], 0.2, 0.95)
    revised.on_dnn(gt[2], 0.2, 0.95)
    np.testing.assert_allclose(held.pose, gt[2])  # the paper's "DNN alone": held, not moved
    np.testing.assert_allclose(revised.pose, gt[9], atol=1e-9)  # moved to the latest frame
    extra = geometry.compose(gt[9], geometry.pose(1.0, 0.0, 0.1))
    np.testing.assert_allclose(held.on_vo(extra, 1.0), gt[2])
    np.testing.assert_allclose(revised.on_vo(extra, 1.0), extra, atol=1e-9)


def test_the_rate_free_pull_is_named_an_ablation_and_is_for_the_papers_weight_only() -> None:
    from nodes.edgeloc.settings import ReplayConfig

    cfg = ReplayConfig(pull_every_s=0.1)
    assert "AN ABLATION" in cfg.describe_fusion()
    fuser = cfg.build_fuser()
    assert isinstance(fuser, EdgeLocFuser) and fuser.pull_every_s == 0.1
    assert ReplayConfig().build_fuser().pull_every_s is None  # type: ignore[union-attr]
    with pytest.raises(ValueError, match="not for the EKF"):
        ReplayConfig(fusion_method="ekf", pull_every_s=0.1)


def _lagging_drive(
    fuser: EdgeLocFuser, seconds: float, noise_m: float = 0.0, seed: int = 0
) -> tuple[float, float]:
    """A straight drive at 10 m/s on heading 0.7 rad, VO 20 Hz with its scale 3% long, and an
    answer every other frame: ground truth (plus white noise of `noise_m` per axis) at zero
    latency. Returns the along-track error just after the last answer, and the time."""
    rng = np.random.default_rng(seed)
    heading, v, dt, scale = 0.7, 10.0, 0.05, 1.03
    along = np.array([math.cos(heading), math.sin(heading)])
    err = 0.0
    t = 0.0
    for i in range(int(seconds / dt)):
        t = i * dt
        vo = np.array([*(scale * v * t * along), heading])
        fused = fuser.on_vo(vo, t)
        if i % 2 == 0:
            gt = np.array([*(v * t * along), heading])
            answer = gt + np.array([*rng.normal(0.0, noise_m, 2), 0.0])
            fused = fuser.on_dnn(answer, t, t)
            err = float((fused[:2] - gt[:2]) @ along)
    return err, t


def test_a_centred_robust_weight_corrects_a_drift_lag_as_the_bare_weight_does() -> None:
    """The oracle: with a VO that runs long by d = 3% x 10 m/s x 0.1 s per answer and exact
    answers, the lag just after each blend settles at e* = (1 - w u) d / (w u), w the answer's
    robust weight. Every answer is off by the same e* + d, so the uncentred Cauchy weight is
    1 / (1 + 1/c^2) = 0.8 (it shrinks the correction the drift needs). Centred on the recent
    mean innovation, each answer is measured by how far the lag still changes, which shrinks
    geometrically, and so does s, the median of the last 50 such: w settles above 0.9, not at
    1, and the lag near the bare form's."""
    k, dt0, c = 2.0, -1.4, 2.0
    u, d = latency_weight(0.0, k, dt0), 0.03 * 10.0 * 0.1

    def lag(w: float) -> float:
        return (1 - w * u) * d / (w * u)

    start = geometry.pose(0.0, 0.0, 0.7)
    bare, _ = _lagging_drive(EdgeLocFuser(k, dt0, initial=start), 60.0)
    plain, _ = _lagging_drive(EdgeLocFuser(k, dt0, initial=start, robust_c=c), 60.0)
    centred, _ = _lagging_drive(
        EdgeLocFuser(k, dt0, initial=start, robust_c=c, robust_centre_s=2.0), 60.0
    )
    assert bare == pytest.approx(lag(1.0), rel=1e-3)
    assert plain == pytest.approx(lag(1 / (1 + 1 / c**2)), rel=1e-3)
    w_centred = d / ((centred + d) * u)  # e* solved for w
    assert 0.9 < w_centred <= 1.0
    assert plain > 1.15 * centred


def test_a_centred_robust_weight_still_shrinks_an_answer_unlike_the_recent_ones() -> None:
    """After 30 s of the drift above with 1-m answers, one answer 40 m off cross-track: the
    bare weight moves the fused pose by u x 40 m across; centred on the (along-track) lag, the
    Cauchy weight still cuts that by more than 20 times."""
    k, dt0, c = 2.0, -1.4, 2.0
    moved = {}
    for name, kw in (("bare", {}), ("centred", {"robust_c": c, "robust_centre_s": 2.0})):
        fuser = EdgeLocFuser(k, dt0, initial=geometry.pose(0.0, 0.0, 0.7), **kw)  # type: ignore[arg-type]
        _, t = _lagging_drive(fuser, 30.0, noise_m=1.0)
        before = fuser.pose
        assert before is not None
        outlier = geometry.compose(before, geometry.pose(0.0, 40.0, 0.0))
        after = fuser.on_dnn(outlier, t, t)
        assert after is not None
        moved[name] = geometry.between(before, after)[1]
    assert moved["bare"] == pytest.approx(latency_weight(0.0, k, dt0) * 40.0, rel=1e-6)
    assert moved["centred"] < moved["bare"] / 20


def test_between_puts_a_point_along_and_across_the_heading() -> None:
    """The frame convention of the centred weight's innovations (`RecentInnovation` averages
    `geometry.between(fused, answer)`): x along the heading, y to its left."""
    pose = geometry.pose(1.0, 2.0, math.pi / 2)  # facing +y
    np.testing.assert_allclose(geometry.between(pose, geometry.pose(1.0, 5.0, 0.0))[:2], [3, 0],
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(geometry.between(pose, geometry.pose(-1.0, 2.0, 0.0))[:2], [0, 2],
                               atol=1e-12)  # fmt: skip


def test_a_centred_robust_weight_needs_a_robust_weight_and_a_window() -> None:
    with pytest.raises(ValueError, match="needs robust_c"):
        EdgeLocFuser(2.0, -1.4, robust_centre_s=2.0)
    with pytest.raises(ValueError, match="window must be > 0 s"):
        EdgeLocFuser(2.0, -1.4, robust_c=2.0, robust_centre_s=0.0)
    from nodes.edgeloc.settings import ReplayConfig

    with pytest.raises(ValueError, match="needs robust_c and fusion_method 'paper'"):
        ReplayConfig(fusion_method="ekf", robust_centre_s=2.0)


def test_the_confidence_weight_scales_u_by_the_error_variance_of_a_less_sure_answer() -> None:
    """Against the closed form: an answer H nats less sure than the reference keeps
    exp(−per_nat·(H − H_ref)) of its u; one at least as sure keeps all of it; without an
    entropy (answers that are not the DNN's) or without the weight, nothing changes."""
    weight = ConfidenceWeight(per_nat=1.9, reference_nats=1.0)
    assert confidence_weight(0.4, weight) == 1.0
    assert confidence_weight(1.0, weight) == pytest.approx(1.0)
    assert confidence_weight(2.5, weight) == pytest.approx(math.exp(-1.9 * 1.5))
    gt = _drive(20, seed=4)
    t0, t_now = 0.05 * 12, 0.05 * 19
    u = latency_weight(t_now - t0, 2.0, -1.4)
    for fuser, entropy, expected in (
        (EdgeLocFuser(2.0, -1.4, confidence=weight), 2.5, u * math.exp(-1.9 * 1.5)),
        (EdgeLocFuser(2.0, -1.4, confidence=weight), 0.4, u),
        (EdgeLocFuser(2.0, -1.4, confidence=weight), None, u),
        (EdgeLocFuser(2.0, -1.4), 2.5, u),
    ):
        for i in range(20):
            fuser.on_vo(gt[i] + np.array([0.3, 0.0, 0.0]), 0.05 * i)
        fuser.on_dnn(gt[12], t0, t_now, entropy_nats=entropy)
        assert fuser.last_update is not None
        assert fuser.last_update.weight == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError, match=">= 0 nats"):
        confidence_weight(-0.1, weight)
    with pytest.raises(ValueError, match="per_nat"):
        ConfidenceWeight(per_nat=math.nan, reference_nats=1.0)


def test_the_confidence_weight_is_named_beyond_the_paper_and_is_for_the_papers_weight_only() -> (
    None
):
    from nodes.edgeloc.settings import ReplayConfig, config_from_dict, config_to_dict

    weight = ConfidenceWeight(1.9, 0.98)
    cfg = ReplayConfig(confidence=weight)
    assert "entropy" in cfg.describe_fusion() and "BEYOND THE PAPER" in cfg.describe_fusion()
    assert cfg.build_fuser().confidence == weight  # type: ignore[union-attr]
    assert config_from_dict(config_to_dict(cfg)) == cfg
    assert "bare form" not in ReplayConfig(robust_c=None, confidence=weight).describe_fusion()
    with pytest.raises(ValueError, match="not for the EKF"):
        ReplayConfig(fusion_method="ekf", confidence=weight)
