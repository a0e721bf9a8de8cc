"""SE(2) geometry: one pose at a time (Python floats) gives the same bits as the array path."""

from __future__ import annotations

import numpy as np
import pytest

from nodes.edgeloc import geometry as se2


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-500, 500, (n, 3))
    p[:, 2] = rng.uniform(-12, 12, n)  # yaws beyond a turn each way: wrap has work
    p[:10, 2] = [np.pi, -np.pi, 0.0, -0.0, 2 * np.pi, 3 * np.pi, 1e-17, -1e-17, 7.0, -7.0]
    return p


@pytest.mark.parametrize("op", ["compose", "between"])
def test_a_single_pose_is_the_array_paths_answer_bit_for_bit(op: str) -> None:
    a, b = _poses(5000, 1), _poses(5000, 2)
    fn = getattr(se2, op)
    rows = fn(a, b)  # (N, 3): the array path
    for i in range(len(a)):
        assert np.array_equal(fn(a[i], b[i]), rows[i]), (op, a[i], b[i])


def test_inverse_and_interpolate_single_poses_match_the_array_path() -> None:
    a, b = _poses(5000, 3), _poses(5000, 4)
    inv = se2.inverse(a)
    us = np.random.default_rng(5).uniform(0, 1, len(a))
    for i in range(len(a)):
        assert np.array_equal(se2.inverse(a[i]), inv[i])
        row = se2.interpolate(a[i : i + 1], b[i : i + 1], float(us[i]))[0]
        assert np.array_equal(se2.interpolate(a[i], b[i], float(us[i])), row)


def test_compose_with_the_inverse_is_the_identity() -> None:
    a = _poses(200, 6)
    for p in a:
        assert np.allclose(se2.compose(p, se2.inverse(p)), 0.0, atol=1e-9)
    wrapped = se2.wrap(a[:, 2])
    assert np.all((wrapped >= -np.pi) & (wrapped < np.pi))
