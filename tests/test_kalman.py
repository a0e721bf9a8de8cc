"""The Kalman baseline equals filterpy's KalmanFilter given the same controls and measurements."""

from __future__ import annotations

import numpy as np
import pytest

from nodes.edgeloc import geometry
from nodes.edgeloc.kalman import KalmanBaseline, world_increment

filterpy_kalman = pytest.importorskip(
    "filterpy.kalman", reason="filterpy is needed for the cross-check: pip install filterpy"
)

Q_POS, Q_YAW, R_POS, R_YAW = 0.01, 0.0005, 4.0, 0.01


def test_equals_filterpy_over_random_steps() -> None:
    rng = np.random.default_rng(11)
    start = geometry.pose(3.0, -2.0, 3.0)  # near ±π so wrapping is exercised
    ours = KalmanBaseline(Q_POS, Q_YAW, R_POS, R_YAW, initial=start)
    ref = filterpy_kalman.KalmanFilter(dim_x=3, dim_z=3)
    ref.x = start.copy()
    ref.F = np.eye(3)
    ref.H = np.eye(3)
    ref.B = np.eye(3)
    ref.P = np.zeros((3, 3))
    ref.Q = np.diag([Q_POS, Q_POS, Q_YAW])
    ref.R = np.diag([R_POS, R_POS, R_YAW])

    vo = geometry.pose(0.0, 0.0, 0.0)
    ours.on_vo(vo, 0.0)
    updates = 0
    for step in range(1, 400):
        body = np.array([rng.uniform(0.2, 1.5), rng.normal(0, 0.05), rng.normal(0, 0.08)])
        vo = geometry.compose(vo, body)
        # filterpy gets the same world-frame control, rotated by its own current yaw.
        ref.predict(u=world_increment(float(ref.x[2]), body))
        ours.on_vo(vo, 0.05 * step)
        if step % 4 == 0:
            z = geometry.pose(*(ours.x[:2] + rng.normal(0, 2.0, 2)), ours.x[2] + rng.normal(0, 0.3))
            # filterpy does not wrap the innovation: give it z on the same branch as its state.
            z_ref = z.copy()
            z_ref[2] = ref.x[2] + geometry.wrap(z[2] - ref.x[2])
            ref.update(z_ref)
            ours.on_dnn(z, 0.05 * step - 0.2, 0.05 * step)
            updates += 1
        np.testing.assert_allclose(ours.x[:2], ref.x[:2], rtol=0, atol=1e-9)
        assert abs(geometry.wrap(ours.x[2] - ref.x[2])) < 1e-9
        np.testing.assert_allclose(ours.P, ref.P, rtol=0, atol=1e-9)
    assert updates == 99
    assert -np.pi <= ours.x[2] < np.pi


def test_without_dnn_it_dead_reckons_and_covariance_grows_by_q() -> None:
    rng = np.random.default_rng(2)
    kf = KalmanBaseline(Q_POS, Q_YAW, R_POS, R_YAW)
    vo = [geometry.pose(1.0, 2.0, 0.5)]
    for _ in range(50):
        vo.append(geometry.compose(vo[-1], [rng.uniform(0, 1), 0.0, rng.normal(0, 0.1)]))
    out = np.array([kf.on_vo(p, 0.05 * i) for i, p in enumerate(vo)])
    np.testing.assert_allclose(out[:, :2], np.array(vo)[:, :2], atol=1e-9)
    np.testing.assert_allclose(kf.P, 50 * np.diag([Q_POS, Q_POS, Q_YAW]), atol=1e-12)


def test_update_moves_towards_the_measurement_by_the_kalman_gain() -> None:
    kf = KalmanBaseline(1.0, 0.1, 1.0, 0.1, initial=geometry.pose(0, 0, 0), p0=np.eye(3))
    x = kf.update(geometry.pose(2.0, -4.0, 0.2))
    # Position: P = R = 1, gain 1/2. Yaw: P = 1, R = 0.1, gain 1/1.1.
    np.testing.assert_allclose(x, [1.0, -2.0, 0.2 / 1.1], atol=1e-12)
    np.testing.assert_allclose(kf.P, np.diag([0.5, 0.5, 0.1 / 1.1]), atol=1e-12)


@pytest.mark.parametrize(
    ("args", "message"),
    [((-1.0, 0.1, 1.0, 0.1), "q_pos must be a variance"), ((0.1, 0.1, 0.0, 0.1), "must be > 0")],
)
def test_bad_noise_is_named(args: tuple[float, ...], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        KalmanBaseline(*args)


def test_dnn_before_any_vo_is_ignored() -> None:
    assert KalmanBaseline(Q_POS, Q_YAW, R_POS, R_YAW).on_dnn([0, 0, 0], 0.0, 0.1) is None
