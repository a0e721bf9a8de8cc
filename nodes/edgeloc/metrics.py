"""Localization error metrics, the paper's headline comparison, and TUM trajectory files.

Errors are per frame between an estimated and a ground-truth trajectory given as (N, 3) SE(2)
arrays on the same frames: position error is the Euclidean distance in metres (evo's APE on the
translation part with no alignment), heading error the absolute wrapped yaw difference in
degrees. The paper reports the *total* position error over a run; we report it with the usual
summary statistics.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from nodes.edgeloc import geometry

# Paper §6.3 (Oxford RobotCar): total position error over the run.
PAPER_TOTALS: dict[str, float] = {
    "edgeloc": 2676.35,
    "kalman": 3837.65,
    "dnn": 3802.57,
    "vo": 8298.58,
}
# The paper's printed reductions of EdgeLoc against each baseline, in percent. They follow
# from the totals (1 − edgeloc/other) to the printed 2 decimals; the abstract's "29.95 %" for
# the DNN is inconsistent with its own totals (29.62 %), which is the figure used here.
PAPER_REDUCTIONS_PCT: dict[str, float] = {"vo": 67.75, "dnn": 29.62, "kalman": 30.26}
METHODS = ("edgeloc", "kalman", "dnn", "vo")


def _trajectories(est: object, gt: object) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    e, g = np.asarray(est, dtype=np.float64), np.asarray(gt, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] != 3 or g.ndim != 2 or g.shape[1] != 3:
        raise ValueError(
            f"trajectories must be (N, 3) arrays of [x, y, yaw], got {e.shape} and {g.shape}"
        )
    if e.shape != g.shape:
        raise ValueError(f"estimate has {len(e)} frames but ground truth has {len(g)}")
    return e, g


def position_errors(est: object, gt: object) -> NDArray[np.float64]:
    """Per-frame Euclidean position error in metres."""
    e, g = _trajectories(est, gt)
    return np.hypot(e[:, 0] - g[:, 0], e[:, 1] - g[:, 1])


def heading_errors_deg(est: object, gt: object) -> NDArray[np.float64]:
    """Per-frame absolute heading error in degrees, wrapped (never more than 180)."""
    e, g = _trajectories(est, gt)
    return np.abs(np.degrees(geometry.wrap(e[:, 2] - g[:, 2])))


@dataclass(frozen=True)
class ErrorStats:
    """Summary of one error series: total (the paper's figure), mean, median, RMSE, p95, max."""

    n: int
    total: float
    mean: float
    median: float
    rmse: float
    p95: float  # numpy's default linear-interpolation percentile
    max: float

    @classmethod
    def of(cls, errors: object) -> ErrorStats:
        x = np.asarray(errors, dtype=np.float64).ravel()
        if x.size == 0:
            raise ValueError("no frames to compute error statistics over")
        if not np.isfinite(x).all():
            raise ValueError("errors contain NaN or infinite values")
        return cls(
            n=int(x.size),
            total=float(np.sum(x)),
            mean=float(np.mean(x)),
            median=float(np.median(x)),
            rmse=float(np.sqrt(np.mean(x * x))),
            p95=float(np.percentile(x, 95)),
            max=float(np.max(x)),
        )

    def to_dict(self) -> dict[str, float | int]:
        return asdict(self)


@dataclass(frozen=True)
class MethodTotal:
    """One method's total position error, the paper's beside ours (None when not run)."""

    method: str
    paper: float
    ours: float | None


@dataclass(frozen=True)
class Reduction:
    """EdgeLoc's error reduction against one baseline, 1 − edgeloc/other, in percent."""

    versus: str
    paper_pct: float
    ours_pct: float | None


@dataclass(frozen=True)
class PaperComparison:
    totals: tuple[MethodTotal, ...]
    reductions: tuple[Reduction, ...]

    def to_dict(self) -> dict[str, object]:
        return {
            "totals": [asdict(t) for t in self.totals],
            "reductions": [asdict(r) for r in self.reductions],
        }


def reduction_pct(edgeloc: float, other: float) -> float:
    """1 − edgeloc/other, in percent."""
    if not other > 0:
        raise ValueError(f"a baseline's total error must be > 0 to compare against, got {other}")
    return 100.0 * (1.0 - edgeloc / other)


def paper_comparison(totals: Mapping[str, float]) -> PaperComparison:
    """The paper's four totals and three reductions beside ours.

    `totals` maps method name (edgeloc, kalman, dnn, vo) to our total position error; missing
    methods show as None, and the reductions need ours for edgeloc and the baseline.
    """
    unknown = sorted(set(totals) - set(METHODS))
    if unknown:
        raise ValueError(
            f"unknown method(s) {', '.join(unknown)}; expected some of: {', '.join(METHODS)}"
        )
    ours = {m: float(v) for m, v in totals.items()}
    for m, v in ours.items():
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"total error of {m} must be a finite number >= 0, got {v!r}")
    rows = tuple(MethodTotal(m, PAPER_TOTALS[m], ours.get(m)) for m in METHODS)
    reds = []
    for other in ("vo", "dnn", "kalman"):
        mine = None
        if "edgeloc" in ours and ours.get(other, 0.0) > 0:
            mine = reduction_pct(ours["edgeloc"], ours[other])
        reds.append(Reduction(other, PAPER_REDUCTIONS_PCT[other], mine))
    return PaperComparison(rows, tuple(reds))


# ---- TUM trajectory files ---------------------------------------------------------------------


def write_tum(path: Path | str, stamps: object, poses: object) -> None:
    """Write `timestamp x y z qx qy qz qw` lines (z = 0, rotation about z by yaw)."""
    t = np.asarray(stamps, dtype=np.float64).ravel()
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"poses must be an (N, 3) array of [x, y, yaw], got shape {p.shape}")
    if len(t) != len(p):
        raise ValueError(f"{len(t)} timestamps but {len(p)} poses")
    if not (np.isfinite(t).all() and np.isfinite(p).all()):
        raise ValueError("timestamps and poses must be finite")
    half = p[:, 2] / 2.0
    with open(path, "w", encoding="utf-8") as f:
        f.write("# timestamp x y z qx qy qz qw\n")
        rows = zip(
            t.tolist(), p.tolist(), np.sin(half).tolist(), np.cos(half).tolist(), strict=True
        )
        for ti, (x, y, _), qz, qw in rows:
            # repr() of a Python float round-trips it exactly, so files lose no precision.
            f.write(f"{ti!r} {x!r} {y!r} 0.0 0.0 0.0 {qz!r} {qw!r}\n")


def read_tum(path: Path | str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Read a TUM file into (stamps (N,), SE(2) poses (N, 3)); yaw from the quaternion."""
    rows = []
    with open(path, encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            fields = text.replace(",", " ").split()
            if len(fields) != 8:
                raise ValueError(
                    f"{path}:{lineno}: expected 8 values (timestamp x y z qx qy qz qw), "
                    f"got {len(fields)}"
                )
            try:
                rows.append([float(v) for v in fields])
            except ValueError:
                raise ValueError(f"{path}:{lineno}: not a number in {text!r}") from None
    if not rows:
        raise ValueError(f"{path}: no poses in the file")
    a = np.array(rows)
    qx, qy, qz, qw = a[:, 4], a[:, 5], a[:, 6], a[:, 7]
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return a[:, 0], np.stack([a[:, 1], a[:, 2], geometry.wrap(yaw)], axis=-1)


def error_autocorrelation(errors: object, max_lag: int) -> NDArray[np.float64]:
    """Autocorrelation of (N, 2) position errors at lags 1..max_lag frames, x and y averaged.

    The DNN's errors on consecutive frames are what `ekf`'s correlation time models: a white
    DNN would give ~0 at every lag.
    """
    e = np.asarray(errors, dtype=np.float64)
    if e.ndim != 2 or e.shape[1] != 2 or len(e) <= max_lag + 1 or max_lag < 1:
        raise ValueError(f"need (N, 2) errors with N > {max_lag + 1}, got shape {e.shape}")
    e = e - e.mean(axis=0)
    var = (e * e).sum(axis=0)
    return np.array(
        [float(np.mean((e[:-k] * e[k:]).sum(axis=0) / var)) for k in range(1, max_lag + 1)]
    )


def independent_answers_per_s(interval_s: float, correlation_s: float) -> float:
    """What a stream of answers every `interval_s` is worth in independent answers per second
    when their errors have the memory exp(−dt/τ), τ = `correlation_s` (0: white).

    The mean of n such answers has the variance of n (1 − ρ) / (1 + ρ) independent ones (ρ =
    exp(−Δ/τ), n large), so the rate is tanh(Δ / 2τ) / Δ. It falls with Δ, so a faster split
    always carries more, but it saturates at 1 / 2τ: once answers come faster than the errors
    forget, a faster split adds almost nothing.
    """
    if not interval_s > 0 or correlation_s < 0:
        raise ValueError(
            f"need an interval > 0 and a correlation time >= 0, got {interval_s!r} and "
            f"{correlation_s!r} s"
        )
    if correlation_s == 0:
        return 1.0 / interval_s
    return math.tanh(interval_s / (2.0 * correlation_s)) / interval_s


def correlation_time(rho: object, frame_s: float) -> float:
    """The τ (s) whose exp(−k·frame_s/τ) fits autocorrelations `rho` at lags 1, 2, ... best
    (least squares on a log grid from 1 ms to 10 s), up to the first lag where rho <= 0.05."""
    r = np.asarray(rho, dtype=np.float64)
    cut = np.flatnonzero(r <= 0.05)
    r = r[: cut[0]] if len(cut) else r
    if len(r) == 0:
        raise ValueError("the errors are white at one frame: no correlation time to fit")
    lags = frame_s * np.arange(1, len(r) + 1)
    taus = np.geomspace(1e-3, 10.0, 2000)
    cost = ((np.exp(-lags[None, :] / taus[:, None]) - r[None, :]) ** 2).sum(axis=1)
    return float(taus[int(np.argmin(cost))])
