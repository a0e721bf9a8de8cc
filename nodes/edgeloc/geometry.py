"""Planar poses (SE(2)): `x, y` in metres, `yaw` in radians, as numpy arrays of shape (3,).

The paper composes poses with ⊕ and ⊖; these are the SE(2) versions every algorithm shares.
Arrays of shape (N, 3) are accepted where noted, so trajectories need no Python loops.

One pose at a time (what the nodes and the replay do, every frame) goes through Python floats
and `math`: numpy's per-call overhead on three numbers was most of a replay's time. The two
paths do the same IEEE operations in the same order (`math.cos` and numpy's `cos` are the same
libm here, `%` and `np.remainder` the same floored remainder), so their answers are the same
bit for bit; tests/test_geometry.py checks that on random poses.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

Pose = NDArray[np.float64]

_PI, _TAU = math.pi, 2 * math.pi


def wrap(angle: NDArray[np.float64] | float) -> NDArray[np.float64] | float:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def _wrap1(angle: float) -> float:
    return (angle + _PI) % _TAU - _PI


def _one(p: object) -> tuple[float, float, float] | None:
    """(x, y, yaw) as floats if `p` is a single pose, else None (the array path)."""
    if isinstance(p, np.ndarray) and p.shape == (3,):
        x, y, yaw = p.tolist()
        return float(x), float(y), float(yaw)
    return None


def pose(x: float, y: float, yaw: float) -> Pose:
    return np.array([x, y, float(wrap(yaw))], dtype=np.float64)


def compose(a: Pose, b: Pose) -> Pose:
    """a ⊕ b: apply `b` expressed in `a`'s frame. Works row-wise on (N, 3)."""
    one_a, one_b = _one(a), _one(b)
    if one_a is not None and one_b is not None:
        (ax, ay, ath), (bx, by, bth) = one_a, one_b
        c, s = math.cos(ath), math.sin(ath)
        return np.array([ax + c * bx - s * by, ay + s * bx + c * by, _wrap1(ath + bth)])
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: Pose) -> Pose:
    """a^-1, so that compose(a, inverse(a)) is the identity."""
    one = _one(a)
    if one is not None:
        ax, ay, ath = one
        c, s = math.cos(ath), math.sin(ath)
        return np.array([-c * ax - s * ay, s * ax - c * ay, _wrap1(-ath)])
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap(-a[..., 2])], axis=-1)


def between(a: Pose, b: Pose) -> Pose:
    """a^-1 ⊕ b: the motion from `a` to `b`, in `a`'s frame."""
    return compose(inverse(a), b)


def interpolate(a: Pose, b: Pose, u: float) -> Pose:
    """(1-u)·a + u·b for position, the shorter arc for yaw (SLERP on the circle)."""
    one_a, one_b = _one(a), _one(b)
    if one_a is not None and one_b is not None and isinstance(u, float | int):
        (ax, ay, ath), (bx, by, bth) = one_a, one_b
        v = 1 - u
        dyaw = _wrap1(bth - ath)
        return np.array([v * ax + u * bx, v * ay + u * by, _wrap1(ath + u * dyaw)])
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    xy = (1 - u) * a[..., :2] + u * b[..., :2]
    dyaw = wrap(b[..., 2] - a[..., 2])
    return np.concatenate([xy, np.asarray(wrap(a[..., 2] + u * dyaw))[..., None]], axis=-1)
