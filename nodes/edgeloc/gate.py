"""Plausibility gate for DNN poses — an addition BEYOND the paper, off unless configured.

The paper's fusion blends every DNN answer with the weight u(Δt). A pose-regressing DNN on
look-alike streets sometimes answers with a confident wrong place (tens to hundreds of metres
off); with u ≈ 1 at low latency such an answer teleports the fused pose. The gate rejects an
answer whose innovation — its distance from the estimator's own current pose, after the answer
has been moved to now by time-zone revision — exceeds a radius that grows with the distance
the vehicle has driven (by its own VO) since the last accepted answer, because the estimate
itself drifts with VO between fixes.

It uses only what the vehicle has (its estimate, its VO, the DNN answer), never ground truth,
and it is applied in the same way, with the same settings, to every estimator that takes DNN
answers (EdgeLoc fusion and the Kalman baseline), each with its own gate instance.

Recovery: if the estimate itself went wrong, every correct answer would be rejected for ever.
So when `recover_after` rejected answers in a row agree with each other (each within `radius_m`
of the previous one moved to now with VO), the gate accepts: a consistent story told that many
times is taken over the estimate. It must exceed the longest run of consistent outliers the
DNN produces (about 2.5 s on the look-alike blocks of the synthetic town, hence 3 s at 20 Hz).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from nodes.edgeloc import geometry
from nodes.edgeloc.geometry import Pose


@dataclass(frozen=True)
class GateSettings:
    """Radius at a fresh fix (m), its growth per metre driven since, and the recovery count."""

    radius_m: float = 10.0
    growth_per_m: float = 0.05
    recover_after: int = 60

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius_m) and self.radius_m > 0):
            raise ValueError(f"gate radius must be > 0 m, got {self.radius_m!r}")
        if not (math.isfinite(self.growth_per_m) and self.growth_per_m >= 0):
            raise ValueError(f"gate growth must be >= 0 m/m, got {self.growth_per_m!r}")
        if self.recover_after < 1:
            raise ValueError(f"gate recover_after must be >= 1, got {self.recover_after!r}")

    def to_dict(self) -> dict[str, float | int]:
        return asdict(self)


class PlausibilityGate:
    """Admits or rejects DNN answers for one estimator; counts what it did."""

    def __init__(self, settings: GateSettings) -> None:
        self.settings = settings
        self._odo_at_fix = 0.0
        self._streak = 0
        self._last_reject: tuple[Pose, Pose] | None = None  # (candidate, VO pose then)
        self.accepted = 0
        self.rejected = 0
        self.recoveries = 0

    def radius(self, odometer_m: float) -> float:
        s = self.settings
        return s.radius_m + s.growth_per_m * max(odometer_m - self._odo_at_fix, 0.0)

    def admit(self, candidate: Pose, estimate: Pose, vo_now: Pose, odometer_m: float) -> bool:
        """`candidate`: the DNN pose revised to now; `estimate`: the estimator's pose now;
        `vo_now`: the latest VO pose; `odometer_m`: VO distance driven since the start."""
        innovation = float(np.hypot(*(candidate[:2] - estimate[:2])))
        if innovation <= self.radius(odometer_m):
            return self._accept(odometer_m)
        # rejected: does it agree with the previous rejected answer, moved to now with VO?
        agrees = False
        if self._last_reject is not None:
            prev, vo_then = self._last_reject
            moved = geometry.compose(prev, geometry.between(vo_then, vo_now))
            agrees = float(np.hypot(*(candidate[:2] - moved[:2]))) <= self.settings.radius_m
        self._streak = self._streak + 1 if agrees else 1
        self._last_reject = (np.asarray(candidate, dtype=np.float64).copy(), vo_now.copy())
        if self._streak >= self.settings.recover_after:
            self.recoveries += 1
            return self._accept(odometer_m)
        self.rejected += 1
        return False

    def _accept(self, odometer_m: float) -> bool:
        self._odo_at_fix = odometer_m
        self._streak = 0
        self._last_reject = None
        self.accepted += 1
        return True

    def counts(self) -> dict[str, int]:
        return {
            "accepted": self.accepted,
            "rejected": self.rejected,
            "recoveries": self.recoveries,
        }
