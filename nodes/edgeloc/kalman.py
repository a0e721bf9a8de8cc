"""Kalman-filter baseline (paper §4.1): predict with the VO increment, correct with L_alpha.

It is a linear KF on the state [x, y, yaw] with F = I, B = I, H = I and fixed, diagonal Q and R:

- predict: the VO increment L_beta(t−1)^-1 ⊕ L_beta(t) is in the vehicle frame; rotated into the
  world frame by the current estimate's yaw it becomes the control u, and x ← x + u, P ← P + Q;
- update: innovation y = z − x with its yaw component wrapped to [−π, π), S = P + R,
  K = P S⁻¹, x ← x + K y (yaw wrapped), P ← (I − K) P.

This is the paper's textbook filter (DNN answers are used as measurements when they arrive, not
revised to the current frame), so it can be cross-checked against `filterpy.kalman.KalmanFilter`.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numpy.typing import NDArray

from nodes.edgeloc import geometry
from nodes.edgeloc.fusion import as_pose
from nodes.edgeloc.geometry import Pose


def world_increment(heading: float, body_step: Pose) -> NDArray[np.float64]:
    """A body-frame step [dx, dy, dyaw] expressed in the world frame at `heading`."""
    c, s = math.cos(heading), math.sin(heading)
    dx, dy, dyaw = body_step
    return np.array([c * dx - s * dy, s * dx + c * dy, dyaw], dtype=np.float64)


class KalmanBaseline:
    """Fuses VO and DNN poses with a fixed-noise Kalman filter (the paper's KF baseline).

    `q_pos`, `q_yaw` are process-noise variances per VO step (m², rad²); `r_pos`, `r_yaw` the
    DNN measurement variances. The state starts at `initial` (or the first VO pose) with
    covariance `p0` (default 0: the start pose is taken as known, as for the EdgeLoc fuser).
    """

    def __init__(
        self,
        q_pos: float,
        q_yaw: float,
        r_pos: float,
        r_yaw: float,
        initial: Pose | None = None,
        p0: NDArray[np.float64] | None = None,
    ) -> None:
        for name, v in (("q_pos", q_pos), ("q_yaw", q_yaw), ("r_pos", r_pos), ("r_yaw", r_yaw)):
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"Kalman {name} must be a variance >= 0, got {v!r}")
        if not (r_pos > 0 and r_yaw > 0):
            raise ValueError("Kalman r_pos and r_yaw must be > 0 (the DNN is never exact)")
        self.Q = np.diag([q_pos, q_pos, q_yaw]).astype(np.float64)
        self.R = np.diag([r_pos, r_pos, r_yaw]).astype(np.float64)
        self.x: Pose | None = None if initial is None else as_pose(initial, "initial pose")
        if p0 is None:
            self.P = np.zeros((3, 3))
        else:
            self.P = np.array(p0, dtype=np.float64)
            if self.P.shape != (3, 3) or not np.isfinite(self.P).all():
                raise ValueError(f"p0 must be a finite 3x3 covariance, got shape {self.P.shape}")
        self._last_vo: Pose | None = None
        self._lock = threading.Lock()

    @property
    def pose(self) -> Pose | None:
        with self._lock:
            return None if self.x is None else self.x.copy()

    # ---- the two estimator entry points, as EdgeLocFuser has them ---------------------------

    def on_vo(self, l_beta_t: Pose, t: float) -> Pose:
        """Predict with the VO motion since the previous frame; returns the prior state."""
        l_beta_t = as_pose(l_beta_t, "VO pose")
        with self._lock:
            if self._last_vo is None:
                if self.x is None:
                    self.x = l_beta_t.copy()
            else:
                assert self.x is not None
                step = geometry.between(self._last_vo, l_beta_t)
                self._predict(world_increment(float(self.x[2]), step))
            self._last_vo = l_beta_t
            return self.x.copy()

    def on_dnn(self, l_alpha_t0: Pose, t0: float, t_now: float) -> Pose | None:
        """Correct with the DNN pose as a measurement (None before the first VO frame)."""
        z = as_pose(l_alpha_t0, "DNN pose")
        with self._lock:
            if self.x is None:
                return None
            self._update(z)
            return self.x.copy()

    # ---- the linear filter ------------------------------------------------------------------

    def predict(self, u_world: NDArray[np.float64]) -> Pose:
        """x ← x + u, P ← P + Q, with a world-frame control u (low level, for tests)."""
        with self._lock:
            if self.x is None:
                raise ValueError("the filter has no state yet: give `initial` or a VO pose first")
            self._predict(np.asarray(u_world, dtype=np.float64))
            return self.x.copy()

    def update(self, z: Pose) -> Pose:
        """Correct with measurement z = [x, y, yaw] (low level, for tests)."""
        z = as_pose(z, "measurement")
        with self._lock:
            if self.x is None:
                raise ValueError("the filter has no state yet: give `initial` or a VO pose first")
            self._update(z)
            return self.x.copy()

    def _predict(self, u: NDArray[np.float64]) -> None:
        x = self.x + u
        x[2] = geometry.wrap(x[2])
        self.x = x
        self.P = self.P + self.Q

    def _update(self, z: Pose) -> None:
        y = z - self.x
        y[2] = geometry.wrap(y[2])  # the short way round, not through ±π
        S = self.P + self.R
        K = np.linalg.solve(S.T, self.P.T).T  # P S⁻¹ without forming the inverse
        x = self.x + K @ y
        x[2] = geometry.wrap(x[2])
        self.x = x
        self.P = (np.eye(3) - K) @ self.P
