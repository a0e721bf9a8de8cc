"""SW-UCB1-normal: the index equals Auer et al.'s formula, the policy equals their UCB1-Normal,
and on simulated split latencies it converges and re-converges after bandwidth shifts."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from nodes.edgeloc.bandit import AdaptiveSplitLearner, SlidingWindowUCB1Normal, lead_for_good
from nodes.edgeloc.detector import KLChangeDetector


def auer_index(rewards: list[float], plays_so_far: int) -> float:
    """Auer, Cesa-Bianchi, Fischer (2002), Fig. 4, written from the paper:
    x̄_j + sqrt(16 · (q_j − n_j x̄_j²)/(n_j − 1) · ln(n − 1)/n_j), n − 1 = plays so far."""
    n_j = len(rewards)
    x_bar = sum(rewards) / n_j
    q_j = sum(r * r for r in rewards)
    return x_bar + math.sqrt(
        16.0 * (q_j - n_j * x_bar**2) / (n_j - 1) * math.log(plays_so_far) / n_j
    )


def test_index_equals_auer_textbook_formula_on_the_window() -> None:
    rng = np.random.default_rng(7)
    arms = ["a", "b", "c"]
    window = 20
    bandit = SlidingWindowUCB1Normal(arms, window=window, rng_seed=None)
    history: list[tuple[str, float]] = []  # independent record of every play
    checked = 0
    for step in range(400):
        arm = bandit.select() if step % 3 else arms[int(rng.integers(3))]  # off-policy plays too
        cost = float(rng.lognormal({"a": 0.0, "b": 0.3, "c": 0.5}[arm], 0.4))
        bandit.update(arm, cost)
        history.append((arm, cost))
        recent = history[-window:]
        per_arm = {a: [-c for b, c in recent if b == a] for a in arms}  # reward = -cost
        if any(len(r) < 2 for r in per_arm.values()):
            continue
        expected = {a: auer_index(per_arm[a], len(recent)) for a in arms}
        for s in bandit.stats():
            assert s.n == len(per_arm[s.arm])
            # Cost index = -(reward index): mean_cost - bonus.
            assert s.index == pytest.approx(-expected[s.arm], rel=1e-9, abs=1e-12)
        assert bandit.select() == max(arms, key=lambda a: expected[a])
        checked += 1
    assert checked > 300


def test_spec_written_form_uses_population_variance() -> None:
    # SPEC: mean - sqrt(16 var ln(t-1) / (n-1)) with var = q/n - mean² equals Auer's index.
    bandit = SlidingWindowUCB1Normal(["a", "b"], window=10)
    for arm, cost in [("a", 1.0), ("b", 2.0), ("a", 3.0), ("b", 2.5), ("a", 2.0)]:
        bandit.update(arm, cost)
    a = bandit.stats()[0]
    assert (a.n, a.mean, a.var) == (3, 2.0, pytest.approx(2.0 / 3.0))
    assert a.index == pytest.approx(2.0 - math.sqrt(16 * (2.0 / 3.0) * math.log(5) / 2))


def test_unwindowed_policy_equals_auer_ucb1_normal_with_forced_exploration() -> None:
    """Same reward table, same choices, play by play, as a straight reading of Fig. 4."""
    k, horizon = 3, 300
    table = np.random.default_rng(3).normal([[0.5], [0.6], [0.4]], 0.2, size=(k, horizon))
    arms = [f"s{i}" for i in range(k)]
    bandit = SlidingWindowUCB1Normal(arms, window=None, rng_seed=None, forced_exploration=True)
    rewards: list[list[float]] = [[] for _ in range(k)]
    for n in range(1, horizon + 1):
        # Reference: any arm played < max(2, ceil(8 ln n)) times first (fewest, lowest index).
        need = max(2, math.ceil(8 * math.log(n)))
        under = [j for j in range(k) if len(rewards[j]) < need]
        if under:
            ref = min(under, key=lambda j: (len(rewards[j]), j))
        else:
            ref = max(range(k), key=lambda j: (auer_index(rewards[j], n - 1), -j))
        got = bandit.select()
        assert got == arms[ref], f"play {n}"
        reward = float(table[ref, len(rewards[ref])])
        rewards[ref].append(reward)
        bandit.update(got, -reward)
    assert max(range(k), key=lambda j: len(rewards[j])) == 1  # s1 has the best mean reward


def test_every_arm_is_played_twice_first_in_order() -> None:
    bandit = SlidingWindowUCB1Normal(["x", "y", "z"], window=50, rng_seed=None)
    played = []
    for _ in range(6):
        arm = bandit.select()
        played.append(arm)
        bandit.update(arm, 1.0)
    assert played == ["x", "y", "z", "x", "y", "z"]


def test_window_forgets_old_plays_and_re_explores_a_starved_arm() -> None:
    bandit = SlidingWindowUCB1Normal(["fast", "slow"], window=10, rng_seed=None)
    for cost in (1.0, 1.1):
        bandit.update("slow", 5.0 + cost)
    for i in range(9):
        bandit.update("fast", 1.0 + 0.01 * i)
    stats = {s.arm: s for s in bandit.stats()}
    assert stats["slow"].n == 1 and stats["fast"].n == 9  # one "slow" play left the window
    assert math.isinf(stats["slow"].index)
    assert bandit.select() == "slow"  # fewer than 2 samples in the window: must be played
    assert sum(s.n for s in bandit.stats()) == 10


def test_reset_forgets_everything() -> None:
    bandit = SlidingWindowUCB1Normal(["a", "b"], window=10)
    for i in range(10):
        bandit.update("a" if i % 2 else "b", float(i))
    bandit.reset()
    assert all(s.n == 0 and math.isnan(s.mean) for s in bandit.stats())
    assert bandit.t == 1 and bandit.total_plays == 10


def test_ties_are_reproducible_per_seed_and_by_order_without_seed() -> None:
    def run(seed: int | None) -> list[str]:
        bandit = SlidingWindowUCB1Normal(["a", "b", "c", "d"], window=40, rng_seed=seed)
        out = []
        for _ in range(30):
            arm = bandit.select()
            out.append(arm)
            bandit.update(arm, 1.0)  # equal costs: every index ties
        return out

    assert run(5) == run(5)
    assert run(None)[:8] == ["a", "b", "c", "d"] * 2
    assert run(None)[8:] == ["a"] * 22  # exact ties go to the first listed arm
    assert len({tuple(run(s)) for s in range(6)}) > 1  # the seed does break ties


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"arms": []}, "at least one arm"),
        ({"arms": ["a", "a"]}, "repeated: a"),
        ({"arms": ["a", "b"], "window": 3}, "use window >= 4"),
        ({"arms": ["a", ""]}, "non-empty strings"),
    ],
)
def test_bad_construction_is_named(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        SlidingWindowUCB1Normal(**kwargs)


def test_bad_updates_are_named() -> None:
    bandit = SlidingWindowUCB1Normal(["a", "b"])
    with pytest.raises(ValueError, match="unknown arm 'c'"):
        bandit.update("c", 1.0)
    with pytest.raises(ValueError, match="finite"):
        bandit.update("a", float("nan"))
    with pytest.raises(ValueError, match="must be a number"):
        bandit.update("a", "fast")  # type: ignore[arg-type]


def test_lead_for_good_counts_plays_until_the_best_never_falls_behind() -> None:
    # b catches up with a at play 4 (2:2), then leads for good from play 5 on
    plays = ["a", "a", "b", "b", "b", "b", "a", "b"]
    assert lead_for_good(plays, "b") == (4, 0.75)
    assert lead_for_good(["b", "b", "a"], "b") == (0, 2 / 3)  # leads from the first play
    assert lead_for_good(["a", "a", "b"], "b") == (None, None)  # never leads
    assert lead_for_good(["a", "b"], "c") == (None, None)  # never played
    assert lead_for_good([], "a") == (None, None)
    assert lead_for_good(["a"], None) == (None, None)


def test_learner_resets_bandit_on_detected_change() -> None:
    det = KLChangeDetector(window=5, threshold=1.0, consecutive=2)
    learner = AdaptiveSplitLearner(["a", "b"], window=20, detector=det)
    events = [learner.update("a", 1.0 + 0.01 * (i % 3)) for i in range(10)]
    events += [learner.update("a", 3.0 + 0.01 * (i % 3)) for i in range(10)]
    fired = [e for e in events if e is not None]
    assert len(fired) == 1 and fired[0].arm == "a"
    assert learner.events == fired
    n_after = learner.stats()[0].n  # only plays after the reset remain
    assert 0 < n_after < 10


# ---- convergence on simulated split latencies (the bench's world, fewer seeds) ---------------


def _bench():
    path = Path(__file__).parent / "bench" / "bench_learner.py"
    spec = importlib.util.spec_from_file_location("bench_learner", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_learner", module)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(("detector", "detector_window"), [(False, 10), (True, 20)])
def test_learner_reconverges_within_two_windows_of_each_shift(
    detector: bool, detector_window: int
) -> None:
    bench = _bench()
    for seed in (1, 2):
        run = bench.simulate(
            seed, window=50, plays_per_phase=400, detector=detector, detector_window=detector_window
        )
        for phase in run.phases:
            assert phase.reconverge_plays is not None and phase.reconverge_plays <= 100, phase
            # The window re-plays each of the 3 other splits twice per 50 plays, so at most
            # 88 % can go to the best; UCB1-normal's wide bonus explores more on top.
            assert phase.share_after >= 0.70, phase


def test_detector_catches_every_bandwidth_shift() -> None:
    bench = _bench()
    run = bench.simulate(4, window=50, plays_per_phase=400, detector=True)
    for k in range(1, len(run.phases)):
        shift = k * 400
        assert any(shift < e.at_play <= shift + 100 for e in run.events), f"shift at {shift}"


def test_robust_detector_fit_ignores_a_lone_spike_but_sees_a_shift() -> None:
    """One retransmitted request (+200 ms) among ~30 ms costs: the MLE fit fires, median/MAD
    does not; a shift of the bulk of the costs fires both."""
    rng = np.random.default_rng(3)
    base = list(0.030 + 0.003 * rng.standard_normal(100))
    spiky = [*base[:70], 0.230, *base[71:]]
    fired = {}
    for fit in ("mle", "robust"):
        det = KLChangeDetector(window=30, threshold=1.0, consecutive=3, fit=fit)
        fired[fit] = any(det.update("image", c) is not None for c in spiky)
    assert fired == {"mle": True, "robust": False}
    shifted = base[:70] + [c + 0.008 for c in base[70:]]
    det = KLChangeDetector(window=30, threshold=1.0, consecutive=3, fit="robust")
    assert any(det.update("image", c) is not None for c in shifted)
    with pytest.raises(ValueError, match="detector fit"):
        KLChangeDetector(fit="median")


# ---- robust fit (beyond the paper; the replay's and the ROS node's learner use it) ----------


def _fill(bandit: SlidingWindowUCB1Normal, costs: dict[str, list[float]]) -> None:
    for i in range(max(len(v) for v in costs.values())):
        for arm, v in costs.items():
            if i < len(v):
                bandit.update(arm, v[i])


def test_robust_fit_ignores_one_retransmission_spike() -> None:
    """One +200 ms retransmission in the slow arm's window must not make it look promising:
    with mean/variance its index drops below the fast arm's; with median/MAD it does not."""
    rng = np.random.default_rng(3)
    fast = list(0.089 + rng.normal(0, 0.004, 40))
    slow = list(0.107 + rng.normal(0, 0.004, 6))
    slow[2] += 0.2  # one lost packet, retransmitted after Linux's minimum RTO
    picks = {}
    for fit in ("mle", "robust"):
        b = SlidingWindowUCB1Normal(["fast", "slow"], window=100, rng_seed=None, fit=fit)
        _fill(b, {"fast": fast, "slow": slow})
        picks[fit] = b.select()
    assert picks == {"mle": "slow", "robust": "fast"}


def test_robust_fit_equals_mean_and_std_for_gaussian_costs() -> None:
    rng = np.random.default_rng(5)
    costs = list(0.05 + rng.normal(0, 0.003, 2000))
    b = SlidingWindowUCB1Normal(["a", "b"], window=None, fit="robust")
    _fill(b, {"a": costs, "b": [1.0, 1.1]})
    st = b.stats()[0]
    assert st.mean == pytest.approx(np.mean(costs), abs=2e-4)
    assert math.sqrt(st.var) == pytest.approx(np.std(costs), rel=0.05)


def test_fit_is_checked_and_reaches_the_bandit() -> None:
    with pytest.raises(ValueError, match="learner fit must be one of"):
        SlidingWindowUCB1Normal(["a", "b"], fit="median")
    learner = AdaptiveSplitLearner.from_settings(["a", "b"], window=10, fit="robust")
    assert learner.bandit.fit == "robust"
    assert SlidingWindowUCB1Normal(["a", "b"]).fit == "mle"  # the paper's, by default
