"""BEYOND THE PAPER: a delayed-measurement EKF as EdgeLoc's fusion (`fusion.method: ekf`).

The paper blends each DNN answer into the fused pose with a weight that depends on its latency
only, u = 1 − Λ(Δt). Measured on the default scenario (`python tests/bench/run.py staleness`),
that weight is what makes the error depend on the latency: tuned for ~150 ms, it follows the
DNN's noise when answers come faster and lets VO drift run away when they come slower. This
filter weighs each answer by what it is worth instead:

- the state is [x, y, yaw, c, b]: the pose, a correction c of the VO's scale (true step =
  c · VO step) and the VO's yaw-rate bias b (true turn = VO turn − b·dt). Both are what makes
  dead reckoning drift, so an answer that disagrees with the VO teaches the filter the drift,
  not only the pose;
- each VO frame predicts the state with the VO step (an EKF: the step is rotated by the
  estimated yaw), adding the VO's noise (`EkfNoise`);
- a DNN answer L_alpha(t0) is a measurement of the pose at its capture time t0, not at now:
  the filter goes back to its state at the VO frame of t0, corrects it there with the Kalman
  gain, and replays the VO frames since t0 (rollback and replay). That is the exact answer for
  a late measurement, the role the paper's time-zone revision plays; the answer's age costs
  what the VO noise accumulated since t0 costs, not a fixed curve;
- `robust_c` as in `fusion`: the answer's measurement noise is divided by its Cauchy weight
  1 / (1 + (r / (c·s))²), r its innovation distance and s the median of the recent ones, so
  a look-alike-street mistake barely moves the estimate;
- `correlation_s` (optional): the DNN's errors are not white. Frames 50 ms apart see nearly
  the same street, so their answers are wrong in nearly the same way (`python tests/bench/run.py
  splits` prints the committed DNN's error autocorrelation: about 0.5 one frame apart, 0.2
  four frames apart, 0 after 0.5 s). A filter that takes every answer as independent trusts a
  split that answers twice as often twice as much, although its extra answers repeat what it
  already heard. With `correlation_s = τ` the answer's R is inflated by (1 + ρ) / (1 − ρ),
  ρ = exp(−Δ/τ), Δ the time between its capture and the previous answer's: the variance of the
  mean of two samples with correlation ρ, so a pair of answers close together carries about
  the information of one, and answers far apart keep their own.

Thread 2 is sequential, so answers arrive in capture order and a replay from t0 never drops an
earlier correction. Same entry points as `fusion.EdgeLocFuser` (`on_vo`, `on_dnn`, `pose`,
`dropped`, `last_update`), so the replay and the ROS fusion node take either;
`FusionUpdate.weight` is the filter's position gain for the answer (mean of K_xx and K_yy),
the counterpart of u.
"""

from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from nodes.edgeloc import geometry
from nodes.edgeloc.fusion import FusionUpdate, InnovationScale, as_pose, check_times
from nodes.edgeloc.geometry import Pose

F64 = NDArray[np.float64]
_H = np.hstack([np.eye(3), np.zeros((3, 2))])  # an answer measures x, y and yaw


@dataclass(frozen=True)
class EkfNoise:
    """The noise the filter assumes (standard deviations).

    The VO terms are of the order of `world.VoNoise` (the synthetic drive's VO); a recorded
    drive's VO would need its own. `r_pos`/`r_yaw` are the DNN's per-axis measurement
    variances (m², rad²): the scenario passes the Kalman baseline's R, the same belief about
    the DNN for both filters.
    """

    trans_per_sqrt_m: float = 0.02  # VO position noise, m per sqrt(m) travelled
    yaw_per_sqrt_s: float = 1e-3  # VO heading noise, rad per sqrt(s)
    bias_walk_per_sqrt_s: float = 3e-4  # yaw-rate bias random walk, rad/s per sqrt(s)
    scale_std: float = 0.03  # prior std of the VO scale correction c around 1
    bias_std: float = 1e-3  # prior std of the yaw-rate bias b, rad/s
    r_pos: float = 4.0
    r_yaw: float = 0.01

    def __post_init__(self) -> None:
        for name in ("trans_per_sqrt_m", "yaw_per_sqrt_s", "bias_walk_per_sqrt_s",
                     "scale_std", "bias_std"):  # fmt: skip
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"EKF noise {name} must be a number >= 0, got {v!r}")
        for name in ("r_pos", "r_yaw"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"EKF {name} must be a variance > 0, got {v!r}")


def predict(x: F64, p: F64, vo_a: Pose, vo_b: Pose, dt: float, noise: EkfNoise) -> tuple[F64, F64]:
    """The state and covariance one VO frame on: the step vo_a → vo_b over `dt` seconds."""
    dx, dy, dyaw = geometry.between(vo_a, vo_b)
    px, py, yaw, c, b = x
    cs, sn = math.cos(yaw), math.sin(yaw)
    wx, wy = cs * dx - sn * dy, sn * dx + cs * dy  # the VO step in the world frame
    nxt = np.array([px + c * wx, py + c * wy, geometry.wrap(yaw + dyaw - b * dt), c, b])
    f = np.eye(5)
    f[0, 2], f[1, 2] = -c * wy, c * wx
    f[0, 3], f[1, 3] = wx, wy
    f[2, 4] = -dt
    q_pos = noise.trans_per_sqrt_m**2 * math.hypot(dx, dy)
    q_yaw = noise.yaw_per_sqrt_s**2 * dt
    q = np.diag([q_pos, q_pos, q_yaw, 0.0, noise.bias_walk_per_sqrt_s**2 * dt])
    return nxt, f @ p @ f.T + q


def correct(x: F64, p: F64, z: Pose, r: F64) -> tuple[F64, F64, F64]:
    """The state and covariance after the pose measurement z with noise r; and the gain."""
    y = z - x[:3]
    y[2] = geometry.wrap(y[2])
    s = _H @ p @ _H.T + r
    k = np.linalg.solve(s, _H @ p).T  # P Hᵀ S⁻¹ (S and P symmetric)
    out = x + k @ y
    out[2] = geometry.wrap(out[2])
    i_kh = np.eye(5) - k @ _H
    # Joseph form: stays symmetric and positive through thousands of replays.
    return out, i_kh @ p @ i_kh.T + k @ r @ k.T, k


#: The largest factor R is inflated by: answers of one frame are ~independent of nothing else.
MAX_INFLATION = 50.0


def correlation_inflation(gap_s: float, correlation_s: float) -> float:
    """(1 + ρ) / (1 − ρ), ρ = exp(−gap/τ): R's factor for an answer `gap_s` after the last."""
    rho = math.exp(-max(gap_s, 0.0) / correlation_s)
    return min((1.0 + rho) / max(1.0 - rho, 1e-9), MAX_INFLATION)


class DelayedEkf:
    """EdgeLoc's fused pose from a delayed-measurement EKF (see the module doc).

    It keeps its posterior at every VO frame of the last `history_s` seconds; an answer whose
    t0 is older than that, or before the first VO frame, is dropped (None), as the paper's
    fuser drops one it cannot revise.
    """

    def __init__(
        self,
        noise: EkfNoise | None = None,
        robust_c: float | None = None,
        history_s: float = 10.0,
        initial: Pose | None = None,
        correlation_s: float | None = None,
    ) -> None:
        if robust_c is not None and not (math.isfinite(robust_c) and robust_c > 0):
            raise ValueError(f"fusion robust c must be a positive number, got {robust_c!r}")
        if correlation_s is not None and not (math.isfinite(correlation_s) and correlation_s > 0):
            raise ValueError(
                f"DNN error correlation time must be a positive number of seconds, "
                f"got {correlation_s!r}"
            )
        if not (history_s > 0 and math.isfinite(history_s)):
            raise ValueError(f"EKF history must be a positive number of seconds: {history_s!r}")
        self.noise = noise or EkfNoise()
        self.robust_c = robust_c
        self.correlation_s = correlation_s
        self._t0_prev: float | None = None  # capture time of the previous answer
        self.history_s = float(history_s)
        self._initial = None if initial is None else as_pose(initial, "initial pose")
        self._r = np.diag([self.noise.r_pos, self.noise.r_pos, self.noise.r_yaw])
        self._scale = InnovationScale()
        # Per VO frame: stamp, VO pose, posterior state and covariance.
        self._t: list[float] = []
        self._vo: list[Pose] = []
        self._x: list[F64] = []
        self._p: list[F64] = []
        self._lock = threading.Lock()
        self.dropped = 0
        self.last_update: FusionUpdate | None = None

    @property
    def pose(self) -> Pose | None:
        with self._lock:
            return self._x[-1][:3].copy() if self._x else None

    def _inflation(self, t0: float) -> float:
        """R's factor for an answer captured at t0 (1 without `correlation_s`); remembers t0."""
        prev, self._t0_prev = self._t0_prev, t0
        if self.correlation_s is None or prev is None:
            return 1.0
        return correlation_inflation(t0 - prev, self.correlation_s)

    @property
    def drift(self) -> tuple[float, float] | None:
        """The current estimate of (VO scale correction c, yaw-rate bias b in rad/s)."""
        with self._lock:
            return (float(self._x[-1][3]), float(self._x[-1][4])) if self._x else None

    def on_vo(self, l_beta_t: Pose, t: float) -> Pose:
        """Thread 1: predict with the VO step since the previous frame; returns the pose."""
        vo = as_pose(l_beta_t, "VO pose")
        t = float(t)
        with self._lock:
            if not self._t:
                start = vo if self._initial is None else self._initial
                x = np.array([*start, 1.0, 0.0])
                n = self.noise
                p = np.diag([0.0, 0.0, 0.0, n.scale_std**2, n.bias_std**2])
            else:
                if not (math.isfinite(t) and t > self._t[-1]):
                    raise ValueError(f"VO stamps must increase: got t={t!r} after {self._t[-1]!r}")
                x, p = predict(self._x[-1], self._p[-1], self._vo[-1], vo, t - self._t[-1],
                               self.noise)  # fmt: skip
            self._t.append(t)
            self._vo.append(vo)
            self._x.append(x)
            self._p.append(p)
            # Keep one frame older than the span so that an answer of t - history_s has one.
            cut = bisect.bisect_left(self._t, t - self.history_s) - 1
            if cut > 0:
                for kept in (self._t, self._vo, self._x, self._p):
                    del kept[:cut]
            return x[:3].copy()

    def on_dnn(
        self, l_alpha_t0: Pose, t0: float, t_now: float, entropy_nats: float | None = None
    ) -> Pose | None:
        """Thread 2: correct the state at t0's VO frame with the answer, replay up to now.
        `entropy_nats` is taken as `EdgeLocFuser.on_dnn` takes it, so a caller feeds either
        fuser alike; the EKF weighs each answer by R (the confidence weight is the paper
        fusion's, and `ReplayConfig` refuses it with the EKF)."""
        z = as_pose(l_alpha_t0, "DNN pose")
        t0, t_now = check_times(t0, t_now)
        with self._lock:
            if not self._t or t0 < self._t[0]:
                self.dropped += 1
                return None
            # The frame at or just before t0 (a replay's t0 is a frame stamp; a node's
            # answer for a frame not yet odometered lands on the newest frame).
            j = bisect.bisect_right(self._t, t0 + 1e-9) - 1
            x, p = self._x[j], self._p[j]
            weight = 1.0
            if self.robust_c is not None:
                innovation = float(np.hypot(*(z[:2] - x[:2])))
                weight = self._scale.weight(innovation, self.robust_c)
            r = self._r / max(weight, 1e-6) * self._inflation(t0)
            x, p, k = correct(x, p, z, r)
            self._x[j], self._p[j] = x, p
            for i in range(j + 1, len(self._t)):
                self._x[i], self._p[i] = predict(
                    self._x[i - 1], self._p[i - 1], self._vo[i - 1], self._vo[i],
                    self._t[i] - self._t[i - 1], self.noise,
                )  # fmt: skip
            fused = self._x[-1][:3].copy()
            gain = 0.5 * float(k[0, 0] + k[1, 1])
            self.last_update = FusionUpdate(z, gain, t_now - t0, fused.copy())
            return fused
