"""KL change detector: the closed form against numeric integration, and the C-consecutive rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nodes.edgeloc.detector import KLChangeDetector, kl_gaussian

integrate = pytest.importorskip("scipy.integrate", reason="scipy is needed: pip install scipy")
stats = pytest.importorskip("scipy.stats", reason="scipy is needed: pip install scipy")


@pytest.mark.parametrize(
    ("mu1", "s1", "mu2", "s2"),
    [(0.0, 1.0, 0.0, 1.0), (0.0, 1.0, 1.0, 1.0), (0.05, 0.004, 0.06, 0.01), (3.0, 2.0, -1.0, 0.5)],
)
def test_closed_form_equals_numeric_integral(mu1: float, s1: float, mu2: float, s2: float) -> None:
    p1, p2 = stats.norm(mu1, s1), stats.norm(mu2, s2)

    def integrand(x: float) -> float:
        # p1 ln(p1/p2) with log densities, so the tails do not underflow to 0 · inf.
        return math.exp(p1.logpdf(x)) * (p1.logpdf(x) - p2.logpdf(x))

    numeric, _ = integrate.quad(integrand, mu1 - 40 * s1, mu1 + 40 * s1, limit=200)
    assert kl_gaussian(mu1, s1, mu2, s2) == pytest.approx(numeric, rel=1e-7, abs=1e-10)


def test_kl_is_asymmetric_and_rejects_zero_sigma() -> None:
    assert kl_gaussian(0, 1, 0, 3) != pytest.approx(kl_gaussian(0, 3, 0, 1))
    with pytest.raises(ValueError, match="standard deviations"):
        kl_gaussian(0, 0, 0, 1)


def _feed(det: KLChangeDetector, arm: str, values: np.ndarray):
    return [det.update(arm, float(v)) for v in values]


def test_step_change_is_reported_after_c_consecutive_exceedances() -> None:
    rng = np.random.default_rng(0)
    before = rng.normal(0.050, 0.002, 20)
    after = rng.normal(0.080, 0.002, 20)
    fired_at = {}
    for c in (1, 3):
        det = KLChangeDetector(window=10, threshold=1.0, consecutive=c)
        out = _feed(det, "s1", np.concatenate([before, after]))
        events = [e for e in out if e is not None]
        assert len(events) == 1 and events[0].arm == "s1" and events[0].kl > 1.0
        fired_at[c] = events[0].at_play
    # The shift is 15 sigma: the first post-change sample already exceeds; C=3 needs 2 more.
    assert fired_at[1] == 21
    assert fired_at[3] == fired_at[1] + 2


def test_stationary_costs_do_not_fire() -> None:
    det = KLChangeDetector(window=10, threshold=1.0, consecutive=3)
    # A slow sinusoidal wobble of 1 % around 50 ms, no change of distribution.
    values = 0.050 * (1 + 0.01 * np.sin(np.arange(500) * 0.7))
    assert not any(_feed(det, "s1", values))
    assert det.last_kl("s1") is not None and det.last_kl("s1") < 1.0


def test_arms_are_watched_separately_and_history_clears_on_event() -> None:
    det = KLChangeDetector(window=5, threshold=1.0, consecutive=2)
    fired = None
    for i in range(30):
        assert det.update("steady", 0.040 + 0.0005 * (i % 2)) is None
        fired = det.update("moving", (0.040 if i < 15 else 0.060) + 0.0005 * (i % 2))
        if fired is not None:
            break
    assert fired is not None and fired.arm == "moving" and fired.at_play == det.plays
    assert det.plays < 60
    # the event cleared every arm's history, the steady one's too ...
    assert det.last_kl("steady") is None and det.last_kl("moving") is None
    # ... which needs 2 windows of new costs before it is compared again
    for i in range(2 * det.window - 1):
        det.update("steady", 0.040 + 0.0005 * (i % 2))
    assert det.last_kl("steady") is None
    det.update("steady", 0.040)
    assert det.last_kl("steady") is not None


def test_variance_floor_keeps_constant_windows_finite() -> None:
    det = KLChangeDetector(window=4, threshold=1.0, consecutive=1)
    assert not any(_feed(det, "a", np.full(12, 0.05)))  # identical constants: KL 0, no error
    assert det.last_kl("a") == pytest.approx(0.0)
    # Constant windows 2 % apart: the floor is 1 % of the mean, so KL = (0.02/0.01)²/2 ≈ 2.
    latest, previous = np.full(4, 0.051), np.full(4, 0.050)
    floor = 0.01 * 0.051
    assert det.divergence(latest, previous) == pytest.approx((0.001 / floor) ** 2 / 2)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"window": 1}, "window must be an integer >= 2"),
        ({"threshold": 0.0}, "positive number"),
        ({"consecutive": 0}, "consecutive must be an integer >= 1"),
        ({"min_std": 0.0}, "variance floor"),
    ],
)
def test_bad_parameters_are_named(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        KLChangeDetector(**kwargs)


def test_bad_cost_is_named() -> None:
    with pytest.raises(ValueError, match="finite"):
        KLChangeDetector().update("a", math.inf)
