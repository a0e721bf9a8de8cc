"""The inference node's loop without ROS (`nodes.ros.inference_request.RequestLoop`): the split
each request plays, what a request is charged (its own time, or the timeout when no answer
came), the learner and its change detector, and the statistics the node writes at exit."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from nodes.edgeloc.settings import LearnerSettings, ReplayConfig
from nodes.ros.inference_request import RequestLoop

REPO = Path(__file__).resolve().parents[1]
SPLITS = ("image", "conv3", "vehicle")
#: Bytes each split sends and seconds of head compute on the vehicle: the raw image is the
#: largest payload with no head, the whole network on the vehicle sends almost nothing.
PAYLOAD = {"image": 150_000, "conv3": 40_000, "vehicle": 200}
HEAD_S = {"image": 0.001, "conv3": 0.025, "vehicle": 0.060}
EDGE_S = 0.004


def _loop(**learner: object) -> RequestLoop:
    cfg = ReplayConfig(splits=SPLITS, seed=3, learner=LearnerSettings(**learner))  # type: ignore[arg-type]
    return RequestLoop(cfg, "av1", "core1", timeout_s=1.0, compute_budget={"joined": False})


def _play(loop: RequestLoop, now: float, bandwidth_bps: float, rng: np.random.Generator) -> str:
    """One request over a link of `bandwidth_bps`, answered: head, upload, edge, a little noise."""
    split = loop.choose(now)
    loop.sent(split, HEAD_S[split], PAYLOAD[split])
    took = HEAD_S[split] + 8 * PAYLOAD[split] / bandwidth_bps + EDGE_S
    t_answer = now + took * (1 + 0.05 * rng.standard_normal())
    cost = loop.charge(split, now, True, t_answer)
    loop.learn(split, cost, t_answer)
    return split


def test_a_drop_in_bandwidth_moves_the_learner_to_another_split() -> None:
    loop = _loop()
    rng = np.random.default_rng(0)
    now, fast, slow = 1000.0, [], []
    for _ in range(300):
        fast.append(_play(loop, now, 100e6, rng))
        now += 0.05
    drop = now
    for _ in range(300):
        slow.append(_play(loop, now, 5e6, rng))
        now += 0.05
    # 100 Mbit/s: sending the raw image is fastest; 5 Mbit/s: it takes 240 ms, the vehicle's
    # own 60 ms wins.
    assert Counter(fast[-100:]).most_common(1)[0][0] == "image"
    assert Counter(slow[-100:]).most_common(1)[0][0] == "vehicle"
    # The change detector sees the image arm slow down and resets the learner within 2 s.
    after = [r for r in loop.stats["resets"] if r["t"] >= drop]
    assert after and after[0]["t"] < drop + 2.0 and after[0]["arm"] == "image"
    assert loop.stats["detector_updates"] == 600
    stats = loop.summary(1000.0, now, recorded=None)
    assert stats["requests"] == stats["answers"] == 600 and stats["lost"] == 0
    assert sum(stats["split_plays"].values()) == 600
    assert stats["payload_bytes"] == sum(PAYLOAD[s] for s in fast + slow)
    assert [d[1] for d in stats["decisions"]] == fast + slow
    assert set(stats["head_s"]) == set(fast + slow)


def test_a_timed_out_request_is_counted_lost_and_charged_the_timeout() -> None:
    loop = _loop(detector=False)
    split = loop.choose(10.0)
    loop.sent(split, 0.002, 1234)
    cost = loop.charge(split, 10.0, False, 11.3)
    assert cost == 1.0  # the timeout, not the 1.3 s until the loop gave up
    loop.learn(split, cost, 11.3)
    assert (loop.stats["lost"], loop.stats["answers"], loop.stats["requests"]) == (1, 0, 1)
    assert loop.chosen == [[10.0, split, 1.0]]
    assert np.isnan(loop.last_latency)  # a lost request is no latency of the decision topic
    arm = next(s for s in loop.learner.stats() if s.arm == split)
    assert (arm.n, arm.mean) == (1, 1.0)
    assert loop.stats["detector_updates"] == 0
    answered = loop.choose(12.0)
    loop.sent(answered, 0.002, 99)
    assert loop.charge(answered, 12.0, True, 12.25) == pytest.approx(0.25)
    assert loop.last_latency == pytest.approx(0.25)
    stats = loop.summary(10.0, 13.0, recorded=None)
    assert stats["mean_latency_s"][answered] == pytest.approx(0.25)
    assert stats["payload_bytes"] == 1234 + 99


def test_a_fixed_split_is_played_every_time() -> None:
    loop = _loop(fixed_split="conv3")
    assert loop.fixed
    assert [loop.choose(float(t)) for t in range(5)] == ["conv3"] * 5
    assert all(s.n == 0 for s in loop.learner.stats())


def test_the_loop_needs_no_ros() -> None:
    code = "import sys, nodes.ros.inference_request; assert 'rclpy' not in sys.modules"
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
