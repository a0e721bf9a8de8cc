"""Planar poses (SE(2)): `x, y` in metres, `yaw` in radians, as numpy arrays of shape (3,).

The paper composes poses with ⊕ and ⊖; these are the SE(2) versions every algorithm shares.
Arrays of shape (N, 3) are accepted where noted, so trajectories need no Python loops.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Pose = NDArray[np.float64]


def wrap(angle: NDArray[np.float64] | float) -> NDArray[np.float64] | float:
    """Angle(s) wrapped into [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


def pose(x: float, y: float, yaw: float) -> Pose:
    return np.array([x, y, float(wrap(yaw))], dtype=np.float64)


def compose(a: Pose, b: Pose) -> Pose:
    """a ⊕ b: apply `b` expressed in `a`'s frame. Works row-wise on (N, 3)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: Pose) -> Pose:
    """a^-1, so that compose(a, inverse(a)) is the identity."""
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
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    xy = (1 - u) * a[..., :2] + u * b[..., :2]
    dyaw = wrap(b[..., 2] - a[..., 2])
    return np.concatenate([xy, np.asarray(wrap(a[..., 2] + u * dyaw))[..., None]], axis=-1)
