"""The premise across drives (`nodes.edgeloc.premise`): the mean effect against scipy's t-test,
the learned run's gains, and the VO's scale error against a trace scaled by a known factor."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from nodes.edgeloc.compare import PhaseFigures, PolicyRow, SplitComparison
from nodes.edgeloc.premise import (
    learned_effects,
    pair_effects,
    path_scale_error,
)

BOUNDS = ((0.0, 30.0), (30.0, 60.0))


def _row(policy: str, phases: list[tuple[float, list[float]]]) -> PolicyRow:
    """phases: (mean latency s, block errors m) per phase."""
    figures = tuple(PhaseFigures(float(np.mean(b)), lat, lat, 10, tuple(b)) for lat, b in phases)
    return PolicyRow(policy, float(sum(sum(b) for _, b in phases)), figures)


def _drive(
    splits: dict[str, list[tuple[float, list[float]]]], learned_total: float = 1.0
) -> SplitComparison:
    fixed = {k: _row(f"fixed:{k}", v) for k, v in splits.items()}
    learned = PolicyRow("learned", learned_total, ())
    return SplitComparison(BOUNDS, learned, fixed, None, None, "model", {})


def test_pairs_follow_the_pooled_latency_order_and_the_mean_matches_scipys_t_test() -> None:
    rng = np.random.default_rng(1)
    drives = []
    for _ in range(8):
        e = rng.normal(0, 0.02, size=6)
        drives.append(
            _drive({  # phase 1: fast image; phase 2: image is slowest
                "image": [(0.07, [1.0 + e[0]] * 3), (0.22, [1.3 + e[1]] * 3)],
                "conv3": [(0.12, [1.1 + e[2]] * 3), (0.13, [1.0 + e[3]] * 3)],
                "vehicle": [(0.15, [1.2 + e[4]] * 3), (0.15, [1.1 + e[5]] * 3)],
            })
        )  # fmt: skip
    effects = pair_effects(drives)
    assert [(e.phase, e.faster, e.slower) for e in effects] == [
        (0, "image", "conv3"), (0, "conv3", "vehicle"),
        (1, "conv3", "vehicle"), (1, "vehicle", "image"),
    ]  # fmt: skip
    for e in effects:
        ci = scipy.stats.ttest_1samp(e.per_drive, 0.0).confidence_interval(0.95)
        assert e.mean == pytest.approx((ci.low + ci.high) / 2)
        assert e.ci == pytest.approx((ci.high - ci.low) / 2)
        assert e.verdict == "holds" and e.ahead == 8
    reversed_ = pair_effects([_drive({"a": [(0.1, [2.0, 2.0])] * 2, "b": [(0.2, [1.0, 1.0])] * 2})
                              for _ in range(3)])  # fmt: skip
    assert reversed_[0].verdict == "reversed" and reversed_[0].ahead == 0
    with pytest.raises(ValueError, match="share their phases"):
        pair_effects([drives[0], _drive({"image": [(0.1, [1.0])] * 2})])


def test_learned_against_each_fixed_split_is_the_relative_gain() -> None:
    drives = [
        _drive({"a": [(0.1, [t])] * 2, "b": [(0.2, [t + 0.5])] * 2}, learned_total=1.8 * t)
        for t in (1.0, 2.0, 3.0)
    ]
    by = {e.split: e for e in learned_effects(drives)}
    assert by["a"].per_drive == pytest.approx([1 / 0.9 - 1] * 3)
    assert by["b"].per_drive == pytest.approx([3.0 / 1.8 - 1, 5.0 / 3.6 - 1, 7.0 / 5.4 - 1])
    assert by["a"].verdict == "holds" and by["b"].verdict == "undecided"  # 3 drives, wide
    worse = [_drive({"a": [(0.1, [t])] * 2}, learned_total=2.2 * t) for t in (1.0, 2.0, 3.0)]
    assert learned_effects(worse)[0].verdict == "reversed"


def test_the_vos_scale_error_is_its_path_length_over_ground_truths() -> None:
    """A VO trace that is ground truth scaled by 1.03 and turned has a scale error of 0.03; a
    world-frame offset or a yaw bias alone changes no path length."""
    t = np.linspace(0, 20, 401)
    gt = np.stack([10 * t, 5 * np.sin(t / 3), t / 3], axis=1)
    turn = np.array([[np.cos(0.4), -np.sin(0.4)], [np.sin(0.4), np.cos(0.4)]])
    vo = gt.copy()
    vo[:, :2] = 1.03 * gt[:, :2] @ turn.T + [3.0, -2.0]
    vo[:, 2] += 0.2
    assert path_scale_error(gt, vo) == pytest.approx(0.03, abs=1e-12)
    assert path_scale_error(gt, gt) == 0.0
    with pytest.raises(ValueError, match="does not move"):
        path_scale_error(np.zeros((5, 3)), gt[:5])
    with pytest.raises(ValueError, match="pose arrays"):
        path_scale_error(gt, gt[:10])
