"""The vehicle's thread 1 (paper §4): every VO frame, publish each method's pose, never waiting
on the network.

Inputs: `/<vehicle>/vo` (L_beta at the frame rate) and `/<vehicle>/dnn_answer` (L_alpha(t0)
with its capture stamp and the DNN's place entropy, from the inference node, whenever one
arrives; the entropy counts only with the settings' confidence weight); `/<vehicle>/gt` only
to score at exit. Output: `/<vehicle>/pose`, one PoseEstimate per method per frame (vo, dnn,
kalman, edgeloc). Both callbacks run on one executor thread, so an answer is applied between
two frames, as in the replay; a missing edge only means no answer arrives.

`VehicleEstimators` (ROS-free) composes the algorithm objects exactly as
`nodes.edgeloc.replay.Replay` does: EdgeLocFuser, KalmanBaseline, DnnHold (the DNN-alone
baseline shows VO until the first answer), and one plausibility gate per DNN-taking estimator
(beyond the paper, off when the settings say `gate: null`).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from nodes.edgeloc.fusion import DnnHold, VoHistory, time_zone_revision
from nodes.edgeloc.gate import PlausibilityGate
from nodes.edgeloc.kalman import KalmanBaseline
from nodes.edgeloc.metrics import position_errors
from nodes.edgeloc.settings import ReplayConfig
from nodes.recording.layout import vehicle_topic
from nodes.ros.common import (
    READY,
    NodeArgs,
    emit,
    from_stamp,
    ros_node,
    run_main,
    write_stats,
)

METHODS = ("vo", "dnn", "kalman", "edgeloc")


class VehicleEstimators:
    """Every estimator of one vehicle, fed VO frames and DNN answers in arrival order."""

    def __init__(self, cfg: ReplayConfig) -> None:
        kc = cfg.kalman
        self.fuser = cfg.build_fuser()
        self.kalman = KalmanBaseline(kc.q_pos, kc.q_yaw, kc.r_pos, kc.r_yaw)
        self.hold = DnnHold()
        self.vo_hist = VoHistory()
        self.gates = (
            {"edgeloc": PlausibilityGate(cfg.gate), "kalman": PlausibilityGate(cfg.gate)}
            if cfg.gate is not None
            else {}
        )
        self.odometer = 0.0
        self._last_vo: np.ndarray | None = None
        self.applied = 0
        self.gated: Counter[str] = Counter()
        self.weight_sum = 0.0  # of the u applied, for their mean (no per-answer list)
        self.last_answer_age: float = math.nan
        # With the confidence weight: answers that came without the DNN's entropy (fused with
        # the latency weight alone); none are expected.
        self.confidence = cfg.confidence  # ReplayConfig allows it only with the paper fuser
        self.without_entropy = 0

    def on_vo(self, vo: np.ndarray, t: float) -> dict[str, np.ndarray]:
        """One frame of thread 1: each method's pose at `t`."""
        vo = np.asarray(vo, dtype=np.float64)
        if self._last_vo is not None:
            self.odometer += float(np.hypot(*(vo[:2] - self._last_vo[:2])))
        self._last_vo = vo
        self.vo_hist.add(t, vo)
        held = self.hold.on_vo(vo, t)
        return {
            "vo": vo,
            "dnn": vo if held is None else held,
            "kalman": self.kalman.on_vo(vo, t),
            "edgeloc": self.fuser.on_vo(vo, t),
        }

    def _admit(self, name: str, pose_t0: np.ndarray, t0: float, est: np.ndarray | None) -> bool:
        gate = self.gates.get(name)
        latest = self.vo_hist.latest()
        vo_t0 = self.vo_hist.at(t0)
        if gate is None or est is None or latest is None or vo_t0 is None:
            return True
        candidate = time_zone_revision(pose_t0, vo_t0, latest[1])
        return gate.admit(candidate, est, latest[1], self.odometer)

    def on_dnn(
        self, pose_t0: np.ndarray, t0: float, t_now: float, entropy_nats: float = math.nan
    ) -> float | None:
        """A DNN answer for capture time `t0` arrived at `t_now`, with the DNN's place entropy
        (NaN: unknown): the EdgeLoc weight u applied (None when the fuser did not take it)."""
        pose_t0 = np.asarray(pose_t0, dtype=np.float64)
        self.hold.on_dnn(pose_t0, t0, t_now)
        weight = None
        doubt = entropy_nats if math.isfinite(entropy_nats) else None
        if doubt is None and self.confidence is not None:
            self.without_entropy += 1
        if self._admit("edgeloc", pose_t0, t0, self.fuser.pose):
            if self.fuser.on_dnn(pose_t0, t0, t_now, doubt) is not None:
                weight = self.fuser.last_update.weight  # type: ignore[union-attr]
                self.weight_sum += weight
                self.applied += 1
        else:
            self.gated["edgeloc"] += 1
        if self._admit("kalman", pose_t0, t0, self.kalman.pose):
            self.kalman.on_dnn(pose_t0, t0, t_now)
        else:
            self.gated["kalman"] += 1
        self.last_answer_age = t_now - t0
        return weight


class Scoreboard:
    """Each method's running position error against the ground truth, matched by frame id.

    Poses and ground truth of a frame come on different topics, in either order; what has not
    met its match waits, but only for the latest `pending` frames, so memory stays flat however
    long the run (storing every pose cost ~20 kB/s, +18% RSS in a 10-minute soak).
    """

    def __init__(self, pending: int = 200) -> None:
        self.pending = pending
        self._poses: dict[int, dict[str, np.ndarray]] = {}  # frame -> method -> pose, no gt yet
        self._gt: dict[int, np.ndarray] = {}  # the latest frames' ground truth
        self.frames: Counter[str] = Counter()
        self.total_m: dict[str, float] = dict.fromkeys(METHODS, 0.0)

    def pose(self, method: str, frame: int, p: np.ndarray) -> None:
        gt = self._gt.get(frame)
        if gt is not None:
            self._score(method, p, gt)
            return
        self._poses.setdefault(frame, {})[method] = p
        _keep_latest(self._poses, self.pending)

    def truth(self, frame: int, gt: np.ndarray) -> None:
        for method, p in self._poses.pop(frame, {}).items():
            self._score(method, p, gt)
        self._gt[frame] = gt
        _keep_latest(self._gt, self.pending)

    def _score(self, method: str, p: np.ndarray, gt: np.ndarray) -> None:
        self.frames[method] += 1
        self.total_m[method] = self.total_m.get(method, 0.0) + float(
            position_errors(p[None], gt[None])[0]
        )

    def errors(self) -> dict[str, dict[str, float | int | None]]:
        out: dict[str, dict[str, float | int | None]] = {}
        for m in self.total_m:
            n = self.frames[m]
            total = self.total_m[m] if n else None
            out[m] = {"frames": n, "total_m": total, "mean_m": None if not n else total / n}
        return out


def _keep_latest(by_frame: dict[int, Any], n: int) -> None:
    """Drop the oldest entries (insertion order) beyond `n`."""
    while len(by_frame) > n:
        del by_frame[next(iter(by_frame))]


def main(argv: Sequence[str] | None = None) -> int:
    args = NodeArgs.parse(argv, prog="fusion_node")
    est = VehicleEstimators(args.config)
    board = Scoreboard()
    from edgeloc_interfaces.msg import PoseEstimate

    published: Counter[str] = Counter()
    stats: dict[str, Any] = {"node": "fusion_node", "vehicle": args.vehicle, "answers": 0}
    with ros_node(f"{args.vehicle}_fusion", record=args.record, events=True) as ros:
        node = ros.node
        out = ros.publisher(PoseEstimate, vehicle_topic(args.vehicle, "pose"), 100)
        first: list[float] = []
        per_second: list[int] = []

        def on_vo(msg: PoseEstimate) -> None:
            t = from_stamp(msg.stamp)
            if not first:
                first.append(time.time())
            poses = est.on_vo(np.array([msg.x, msg.y, msg.yaw]), t)
            for method, p in poses.items():
                age = est.last_answer_age if method in ("dnn", "kalman", "edgeloc") else math.nan
                out.publish(
                    PoseEstimate(
                        stamp=msg.stamp,
                        vehicle=args.vehicle,
                        method=method,
                        x=float(p[0]),
                        y=float(p[1]),
                        yaw=float(p[2]),
                        latency_s=float(age),
                        frame_id=msg.frame_id,
                        entropy_nats=math.nan,  # estimates, not answers
                    )
                )
                published[method] += 1
                board.pose(method, msg.frame_id, np.array(p, dtype=np.float64))
            now = time.time()
            stats["last_pose_s"] = now
            second = int(now - first[0])
            per_second.extend([0] * (second + 1 - len(per_second)))
            per_second[second] += 1  # fused poses per wall second: the real-time thread's pace

        def on_answer(msg: PoseEstimate) -> None:
            stats["answers"] += 1
            est.on_dnn(
                np.array([msg.x, msg.y, msg.yaw]),
                from_stamp(msg.stamp),
                time.time(),
                msg.entropy_nats,
            )

        def on_gt(msg: PoseEstimate) -> None:
            board.truth(msg.frame_id, np.array([msg.x, msg.y, msg.yaw]))

        node.create_subscription(PoseEstimate, vehicle_topic(args.vehicle, "vo"), on_vo, 50)
        node.create_subscription(
            PoseEstimate, vehicle_topic(args.vehicle, "dnn_answer"), on_answer, 50
        )
        node.create_subscription(PoseEstimate, vehicle_topic(args.vehicle, "gt"), on_gt, 50)
        emit(READY, node="fusion_node")
        ros.stop.wait(1e9)
        stats["first_pose_s"] = first[0] if first else None
    stats["published"] = dict(published)
    stats["recorded"] = ros.recorded
    stats["frames_per_second"] = per_second
    stats["applied_edgeloc"] = est.applied
    stats["gated"] = dict(est.gated)
    stats["mean_weight_u"] = est.weight_sum / est.applied if est.applied else None
    stats["confidence"] = None if est.confidence is None else asdict(est.confidence)
    stats["answers_without_entropy"] = est.without_entropy
    stats["errors"] = board.errors()
    write_stats(args.stats, stats)
    return 0


if __name__ == "__main__":
    run_main(main)
