"""Latency-aware pose fusion with time-zone revision (paper §3–§4), and the DNN-hold baseline.

Thread 1 (real time) calls `on_vo` with each visual-odometry pose L_beta(t) and gets the fused
pose L_r(t), dead-reckoned with the VO motion since the previous frame. Thread 2 (non-real time)
calls `on_dnn` when a DNN answer L_alpha(t0) for a frame captured at t0 arrives at t_now: the
answer is moved to the time of the latest VO frame with the VO motion since t0 (time-zone
revision) and blended into L_r with the weight u = 1 − Λ(t_now − t0).

BEYOND THE PAPER (optional, `robust_c`): an uncertainty term from the answers themselves. The
paper's u depends on the latency only, so an answer that lands 8 m away from where the fused
pose and its VO say the car is pulls as hard as one that agrees with them. With `robust_c = c`
the weight is multiplied by the Cauchy weight 1 / (1 + (r / (c·s))²) of the answer's innovation
r (its distance from L_r, after revision), where s is the median innovation of the last
`ROBUST_HISTORY` answers: an answer as far off as the recent typical one keeps ~1/(1 + 1/c²)
of its weight, one ten times as far keeps ~c²/100. It reads nothing the vehicle does not have.
`robust_c = None` is the paper's bare form.

BEYOND THE PAPER, with `robust_c` (`robust_centre_s = W`): r is measured from the answers' mean
innovation over the last W seconds, in the fused pose's frame, instead of from the fused pose.
Where the VO drifts, the fused pose lags the truth between answers and every answer lands off
in the same direction; measured from L_r, those answers look like outliers and the Cauchy
weight shrinks the very corrections the drift needs. Measured from the recent mean, an answer is
an outlier only when it is unlike the recent answers. The pull itself is unchanged (u still
depends on latency only), so a faster split still corrects the lag sooner.

AN ABLATION, NOT A FUSION TO USE (`pull_every_s`): the paper's u is per answer, so a split that
answers twice as often pulls the fused pose twice as hard per second. With `pull_every_s = P`
each answer's u becomes `per_second_weight(u, gap, P)`, the weight that pulls as hard over the
gap since the previous answer as u does once every P seconds. It separates what an answer's
age costs from what the answer rate buys (`tests/bench/bench_splits.py --fusion per-second`).

BEYOND THE PAPER (`workload.fusion.confidence`): an uncertainty term from the DNN itself.
Its place classifier's entropy H (`model.place_entropy`) rises with its error: on held-out
drives the median error grows ~exp(b·H) (`train.entropy_calibration`). With
`confidence = ConfidenceWeight(per_nat, reference_nats)` each answer's u is multiplied by
`confidence_weight`, min(1, exp(−per_nat·(H − H_ref))): an answer less sure than the typical
one pulls as much less as its error variance is larger. The weight is read from the
calibration beside the DNN's weights (`ConfidenceWeight.read`); the edge computes H with the
pose (the vehicle, for the `vehicle` split) and the answer carries it to the fusion.

Every pose is an SE(2) numpy array [x, y, yaw] (see `geometry`). All times are seconds on the
vehicle's clock.

What the centring measures (`RecentInnovation`): tests/test_fusion.py checks it against the
closed form of the lag on a straight drive whose VO runs 3% long, with exact answers: the lag
after each blend settles at e* = (1 - w u) d / (w u), d the drift between answers and w the
robust weight (0.8 uncentred, above 0.9 centred). Over 48 drives (`python
tests/bench/bench_premise.py --fusion centred`) it trades premise for reductions: the Kalman
reduction on 35 of 48 drives against 29 (median below Kalman on drives with VO off by 2% or
more: 4.2% -> 13.7%), but the learned run ahead of every fixed split on 22 against 28, and
image -> conv3 at 0-30 s undecided. It stays off by default: the option for a study of accuracy
against the baselines; the default keeps more of the premise.

What the confidence weight measures: on held-out drives the surest tenth of the answers has a
median error of 1.19 m, the least sure tenth 7.70 m, 45% of them more than 10 m off (`python
tests/bench/bench_splits.py --fusion confidence` prints it as section 0b, tests/test_model.py
checks the trend). The committed calibration is min(1, exp(-1.91 (H - 0.98 nats))), the median
answer's error variance over this answer's (weights/confidence.json; `python -m
nodes.edgeloc.train --calibrate --out DIR` fits it for other weights, and a scenario whose
weights have none is refused at the field). tests/test_confidence_root.py recomputes every
recorded answer's entropy from the recorded camera frame. Over 48 drives (`bench_premise.py
--fusion confidence`) the learner pays (ahead of every fixed split on 38 of 48 against 28, +8.9
+- 3.3% against conv3) and the reductions pay for it (Kalman reduction on 25 of 48 against 29;
-9.5% median where the VO drifts most): a doubted answer pulls less, so extra answers add less
noise, but the pull is weaker on average and the drift's lag is corrected later, the centred
weight's trade-off run the other way.

What the per-second ablation found: rescaling each answer's u to the gap since the previous one,
u' = 1 - (1 - u)^(gap / 100 ms), puts the three splits' totals within 2-6% of each other on four
of seeds 1-4 and 7 (`python tests/bench/bench_splits.py --fusion per-second`), strictly monotone
in 3 of 15 seed-phases against 8: 75-227 ms of age, revised with VO, costs little; a faster
split is more accurate only because its answers come more often and each pulls as hard as a
slower split's, which buys accuracy only when the answers' errors are independent.
"""

from __future__ import annotations

import bisect
import json
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nodes.edgeloc import geometry
from nodes.edgeloc.errors import EdgeLocError
from nodes.edgeloc.geometry import Pose
from nodes.edgeloc.robust import median


def as_pose(value: object, name: str = "pose") -> Pose:
    """`value` as a float64 [x, y, yaw] array, or a ValueError naming `name`."""
    try:
        p = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be [x, y, yaw] numbers, got {value!r}") from None
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"{name} must be 3 finite numbers [x, y, yaw], got {value!r}")
    return p


def time_zone_revision(l_alpha_t0: Pose, l_beta_t0: Pose, l_beta_t: Pose) -> Pose:
    """L_alpha'(t) = L_alpha(t0) ⊕ (L_beta(t0)^-1 ⊕ L_beta(t)): the DNN pose moved from t0 to t."""
    return geometry.compose(l_alpha_t0, geometry.between(l_beta_t0, l_beta_t))


def latency_weight(dt: float, k_s: float, dt0: float) -> float:
    """u = 1 − Λ with Λ = 1 / (1 + exp(−k_s (Δt − Δt0))): the DNN pose's weight after Δt s.

    Computed as the logistic of −k_s (Δt − Δt0) in the branch that cannot overflow.
    """
    z = -k_s * (dt - dt0)
    if z >= 0:
        return 1.0 / (1.0 + math.exp(-z))
    e = math.exp(z)
    return e / (1.0 + e)


def per_second_weight(u: float, gap_s: float, pull_every_s: float) -> float:
    """u' = 1 − (1 − u)^(gap / P): the blend weight that leaves as much of the old pose after
    `gap_s` as u once every P = `pull_every_s` seconds, whatever the answer rate.

    Two blends `gap_s` apart with u' leave what one with u' for 2·`gap_s` does (the pull per
    second is the answer rate's no longer); `gap_s` = P gives u back.
    """
    if not (0.0 <= u <= 1.0 and gap_s >= 0.0 and pull_every_s > 0.0):
        raise ValueError(
            f"need 0 <= u <= 1, gap >= 0 s and P > 0 s, got {u!r}, {gap_s!r}, {pull_every_s!r}"
        )
    return 1.0 - (1.0 - u) ** (gap_s / pull_every_s)


@dataclass(frozen=True)
class ConfidenceWeight:
    """How the DNN's entropy scales an answer's weight: exp(−`per_nat`·(H − `reference_nats`)),
    capped at 1. Fitted by `train.entropy_calibration` (per_nat = 2·b: a variance ratio)."""

    per_nat: float
    reference_nats: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.per_nat) and self.per_nat >= 0):
            raise ValueError(f"confidence per_nat must be a number >= 0, got {self.per_nat!r}")
        if not (math.isfinite(self.reference_nats) and self.reference_nats >= 0):
            raise ValueError(
                f"confidence reference entropy must be >= 0 nats, got {self.reference_nats!r}"
            )

    @classmethod
    def read(cls, path: Path) -> ConfidenceWeight:
        """The weight in a calibration file beside the DNN's weights (`CONFIDENCE_FILE`, which
        `python -m nodes.edgeloc.train --calibrate` writes)."""
        try:
            data = json.loads(path.read_text())
            return cls(float(data["per_nat"]), float(data["reference_nats"]))
        except FileNotFoundError:
            raise ConfidenceMissing(
                f"no confidence calibration at {path}: run `python -m nodes.edgeloc.train "
                f"--calibrate --out {path.parent}` for those weights"
            ) from None
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ConfidenceMissing(
                f"{path} is not a confidence calibration ({e}): run `python -m "
                f"nodes.edgeloc.train --calibrate --out {path.parent}`"
            ) from e


class ConfidenceMissing(EdgeLocError, ValueError):
    """The DNN's weights have no (readable) confidence calibration beside them."""


def confidence_weight(entropy_nats: float, weight: ConfidenceWeight) -> float:
    """min(1, exp(−per_nat·(H − H_ref))): 1 for an answer at least as sure as the reference."""
    if not (math.isfinite(entropy_nats) and entropy_nats >= 0):
        raise ValueError(f"an answer's entropy must be >= 0 nats, got {entropy_nats!r}")
    return min(1.0, math.exp(-weight.per_nat * (entropy_nats - weight.reference_nats)))


class VoHistory:
    """The VO poses of the last `span_s` seconds, so a late DNN answer can find L_beta(t0).

    Between two stamps the pose is interpolated (position linearly, yaw on the shorter arc);
    after the newest stamp it is the newest pose (the frame at t0 has not been odometered yet);
    before the oldest kept stamp it is unknown (None).
    """

    def __init__(self, span_s: float = 10.0) -> None:
        if not (span_s > 0 and math.isfinite(span_s)):
            raise ValueError(f"VO history span must be a positive number of seconds: {span_s!r}")
        self.span_s = float(span_s)
        self._stamps: list[float] = []
        self._poses: list[Pose] = []

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, t: float, pose: Pose) -> None:
        if not math.isfinite(t):
            raise ValueError(f"VO stamp must be a finite number of seconds, got {t!r}")
        if self._stamps and t <= self._stamps[-1]:
            raise ValueError(f"VO stamps must increase: got t={t!r} after t={self._stamps[-1]!r}")
        self._stamps.append(float(t))
        self._poses.append(pose)
        # Keep one pose older than the span so that t - span_s can still be interpolated.
        cut = bisect.bisect_left(self._stamps, t - self.span_s) - 1
        if cut > 0:
            del self._stamps[:cut]
            del self._poses[:cut]

    def latest(self) -> tuple[float, Pose] | None:
        return (self._stamps[-1], self._poses[-1]) if self._stamps else None

    def at(self, t: float) -> Pose | None:
        if not self._stamps or t < self._stamps[0]:
            return None
        if t >= self._stamps[-1]:
            return self._poses[-1]
        j = bisect.bisect_right(self._stamps, t)  # stamps[j-1] <= t < stamps[j]
        t_a, t_b = self._stamps[j - 1], self._stamps[j]
        return geometry.interpolate(self._poses[j - 1], self._poses[j], (t - t_a) / (t_b - t_a))


@dataclass(frozen=True)
class FusionUpdate:
    """What one DNN answer did: the revised DNN pose, its weight u, its latency and the result."""

    revised: Pose
    weight: float
    latency_s: float
    fused: Pose


def check_times(t0: float, t_now: float) -> tuple[float, float]:
    t0, t_now = float(t0), float(t_now)
    if not (math.isfinite(t0) and math.isfinite(t_now)):
        raise ValueError(f"DNN times must be finite, got t0={t0!r}, t_now={t_now!r}")
    if t_now < t0:
        raise ValueError(f"DNN answer arrived before its frame: t_now={t_now!r} < t0={t0!r}")
    return t0, t_now


ROBUST_HISTORY = 50  # answers whose median innovation is the robust scale s
ROBUST_MIN = 5  # answers before s is trusted (until then each answer is its own scale)


class InnovationScale:
    """The median innovation of the last `history` answers: the robust scale s of `robust_c`."""

    def __init__(self, history: int = ROBUST_HISTORY, minimum: int = ROBUST_MIN) -> None:
        self.history, self.minimum = history, minimum
        self._seen: list[float] = []

    def weight(self, innovation: float, c: float) -> float:
        """Cauchy weight of `innovation` against the scale before it; then remember it."""
        seen = self._seen
        s = median(seen) if len(seen) >= self.minimum else innovation
        seen.append(innovation)
        del seen[: -self.history]
        if s <= 1e-9:
            return 1.0
        return 1.0 / (1.0 + (innovation / (c * s)) ** 2)


class RecentInnovation:
    """The exponentially weighted mean of the innovations of the last `window_s` seconds, each a
    2-vector in the fused pose's frame (along-track, cross-track): the lag that the VO's drift
    has built up, which `robust_centre_s` measures each answer from."""

    def __init__(self, window_s: float) -> None:
        if not (math.isfinite(window_s) and window_s > 0):
            raise ValueError(f"fusion robust centre window must be > 0 s, got {window_s!r}")
        self.window_s = float(window_s)
        self.mean = np.zeros(2)
        self._last_s: float | None = None

    def add(self, innovation: np.ndarray, t: float) -> None:
        # The first answer is the whole mean; later ones count by the time since the last.
        last, self._last_s = self._last_s, t
        a = 1.0 if last is None else 1.0 - math.exp(-max(t - last, 0.0) / self.window_s)
        self.mean = (1.0 - a) * self.mean + a * innovation


class EdgeLocFuser:
    """Holds the fused pose L_r; VO frames dead-reckon it, DNN answers pull it back (§4.2).

    L_r starts at `initial`, or at the first VO pose when `initial` is None (the VO frame is then
    taken as the world frame). A DNN answer is dropped (None) when no VO pose is known at its
    capture time t0 (before the first VO frame or older than `history_s`). Both entry points
    take a lock: the ROS node calls them from its real-time and its inference threads.
    `robust_c` (beyond the paper, see the module doc) scales u by the answer's Cauchy weight;
    `robust_centre_s` (beyond the paper, needs `robust_c`) measures the Cauchy weight's r from
    the recent answers' mean innovation; `pull_every_s` (an ablation, see the module doc) makes
    the pull per second rate-free; `confidence` (beyond the paper) scales u by the answer's entropy.
    """

    def __init__(
        self,
        k_s: float,
        dt0_s: float,
        history_s: float = 10.0,
        initial: Pose | None = None,
        robust_c: float | None = None,
        pull_every_s: float | None = None,
        robust_centre_s: float | None = None,
        confidence: ConfidenceWeight | None = None,
    ) -> None:
        if not (math.isfinite(k_s) and k_s > 0):
            raise ValueError(f"fusion k_s must be a positive number (1/s), got {k_s!r}")
        if not math.isfinite(dt0_s):
            raise ValueError(f"fusion dt0 must be a finite number of seconds, got {dt0_s!r}")
        if robust_c is not None and not (math.isfinite(robust_c) and robust_c > 0):
            raise ValueError(f"fusion robust c must be a positive number, got {robust_c!r}")
        self.k_s = float(k_s)
        self.dt0_s = float(dt0_s)
        self.robust_c = None if robust_c is None else float(robust_c)
        if pull_every_s is not None and not (math.isfinite(pull_every_s) and pull_every_s > 0):
            raise ValueError(f"fusion pull_every_s must be > 0 s, got {pull_every_s!r}")
        self.pull_every_s = None if pull_every_s is None else float(pull_every_s)
        self._last_answer_s: float | None = None
        self._scale = InnovationScale()
        if robust_centre_s is not None and robust_c is None:
            raise ValueError("fusion robust_centre_s centres the robust weight: it needs robust_c")
        self._recent = None if robust_centre_s is None else RecentInnovation(robust_centre_s)
        self.confidence = confidence
        self._vo = VoHistory(history_s)
        self._pose: Pose | None = None if initial is None else as_pose(initial, "initial pose")
        self._lock = threading.Lock()
        self.dropped = 0  # DNN answers that could not be revised
        self.last_update: FusionUpdate | None = None

    @property
    def pose(self) -> Pose | None:
        with self._lock:
            return None if self._pose is None else self._pose.copy()

    def on_vo(self, l_beta_t: Pose, t: float) -> Pose:
        """Thread 1: L_r(t) = L_r(t−1) ⊕ (L_beta(t−1)^-1 ⊕ L_beta(t)); returns L_r(t)."""
        l_beta_t = as_pose(l_beta_t, "VO pose")
        with self._lock:
            prev = self._vo.latest()
            self._vo.add(float(t), l_beta_t)
            if self._pose is None:
                self._pose = l_beta_t.copy()
            elif prev is not None:
                self._pose = geometry.compose(self._pose, geometry.between(prev[1], l_beta_t))
            return self._pose.copy()

    def on_dnn(
        self, l_alpha_t0: Pose, t0: float, t_now: float, entropy_nats: float | None = None
    ) -> Pose | None:
        """Thread 2: revise L_alpha(t0) to the latest VO frame and fuse with u(t_now − t0).
        `entropy_nats`, the DNN's doubt about this answer, counts only with `confidence`."""
        l_alpha_t0 = as_pose(l_alpha_t0, "DNN pose")
        t0, t_now = check_times(t0, t_now)
        with self._lock:
            l_beta_t0 = self._vo.at(t0)
            latest = self._vo.latest()
            if l_beta_t0 is None or latest is None or self._pose is None:
                self.dropped += 1
                return None
            revised = time_zone_revision(l_alpha_t0, l_beta_t0, latest[1])
            u = latency_weight(t_now - t0, self.k_s, self.dt0_s)
            if self.pull_every_s is not None:
                # The first answer has no gap: it pulls as the paper's does.
                last, self._last_answer_s = self._last_answer_s, t_now
                gap = self.pull_every_s if last is None else max(t_now - last, 0.0)
                u = per_second_weight(u, gap, self.pull_every_s)
            if self.robust_c is not None:
                # In the fused pose's frame: [along-track, cross-track].
                innovation = geometry.between(self._pose, revised)[:2]
                centre = np.zeros(2)
                if self._recent is not None:
                    centre = self._recent.mean
                    self._recent.add(innovation, t_now)
                r = float(np.hypot(*(innovation - centre)))
                u *= self._scale.weight(r, self.robust_c)
            if self.confidence is not None and entropy_nats is not None:
                u *= confidence_weight(entropy_nats, self.confidence)
            # L_r = u·L_alpha' + (1 − u)·L_r, yaw on the circle.
            self._pose = geometry.interpolate(self._pose, revised, u)
            self.last_update = FusionUpdate(revised, u, t_now - t0, self._pose.copy())
            return self._pose.copy()


class DnnHold:
    """Baseline "DNN alone": the latest DNN pose, held until the next one arrives.

    This is what the paper compares against (no VO at all). With `revise=True` the held pose is
    instead moved to each VO frame by time-zone revision (EdgeLoc with u = 1), an ablation.
    Before the first DNN answer the pose is None.
    """

    def __init__(self, revise: bool = False, history_s: float = 10.0) -> None:
        self.revise = revise
        self._vo = VoHistory(history_s)
        self._held: tuple[Pose, Pose] | None = None  # (L_alpha(t0), L_beta(t0))
        self._pose: Pose | None = None
        self._lock = threading.Lock()
        self.dropped = 0

    @property
    def pose(self) -> Pose | None:
        with self._lock:
            return None if self._pose is None else self._pose.copy()

    def on_vo(self, l_beta_t: Pose, t: float) -> Pose | None:
        l_beta_t = as_pose(l_beta_t, "VO pose")
        with self._lock:
            if self.revise:
                self._vo.add(float(t), l_beta_t)
                if self._held is not None:
                    self._pose = time_zone_revision(self._held[0], self._held[1], l_beta_t)
            return None if self._pose is None else self._pose.copy()

    def on_dnn(self, l_alpha_t0: Pose, t0: float, t_now: float) -> Pose | None:
        l_alpha_t0 = as_pose(l_alpha_t0, "DNN pose")
        t0, t_now = check_times(t0, t_now)
        with self._lock:
            if not self.revise:
                self._pose = l_alpha_t0.copy()
                return self._pose.copy()
            l_beta_t0, latest = self._vo.at(t0), self._vo.latest()
            if l_beta_t0 is None or latest is None:
                self.dropped += 1
                return None
            self._held = (l_alpha_t0, l_beta_t0)
            self._pose = time_zone_revision(l_alpha_t0, l_beta_t0, latest[1])
            return self._pose.copy()
