"""The vehicle's thread 2 (paper §4): split point, DNN head, request to the edge, learning.

Loop, as fast as answers come: take the newest camera frame not sent yet (captured at t0);
ask the learner for a split k (`AdaptiveSplitLearner`, or the scenario's fixed split); run
layers [0:k] and encode (`LocNet.head`, `codec.encode`); send a SplitInference goal to the
edge; wait for the result up to the timeout. An answer is published on `/<vehicle>/dnn_answer`
(PoseEstimate method "dnn", stamp = t0, latency_s = Δt = t_answer − t0) for the fusion node;
the learner is charged the request's own end-to-end time (loop start → answer), or the timeout
when no answer came (a lost request brings no pose), as `nodes.edgeloc.replay` does.

Also published: one SplitDecision per request (`/<vehicle>/split_decision`), one
InferenceResult per request (`/<vehicle>/inference`: split, payload, head and edge compute time,
latency, ok / timed out / error) and one DetectorEvent per update of the KL change detector
(`/<vehicle>/detector`, `reset` true on the update that reset the learner).
While no edge server has been discovered, no request is sent (counted as `no_server_s`): the
fusion node goes on with VO alone, which is the paper's fault tolerance.
"""

from __future__ import annotations

import array
import math
import threading
import time
from collections import Counter
from typing import Any

import numpy as np
import torch

from nodes.edgeloc.bandit import AdaptiveSplitLearner
from nodes.edgeloc.codec import encode
from nodes.edgeloc.detector import ChangeEvent, KLChangeDetector
from nodes.edgeloc.model import SPLITS, split_index
from nodes.edgeloc.train import load_model
from nodes.recording.layout import vehicle_topic
from nodes.ros.common import (
    READY,
    ComputeThread,
    NodeArgs,
    action_name,
    emit,
    from_stamp,
    ros_node,
    run_main,
    to_stamp,
    write_stats,
)

POLL_S = 0.005  # how often the loop looks at a pending future


class LatestFrame:
    """The newest camera frame, handed from the executor thread to the request loop."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._frame: tuple[int, float, np.ndarray] | None = None

    def put(self, frame: int, t0: float, image: np.ndarray) -> None:
        with self._cond:
            self._frame = (frame, t0, image)
            self._cond.notify_all()

    def newer_than(self, frame: int, timeout_s: float) -> tuple[int, float, np.ndarray] | None:
        with self._cond:
            self._cond.wait_for(
                lambda: self._frame is not None and self._frame[0] > frame, timeout=timeout_s
            )
            f = self._frame
            return f if f is not None and f[0] > frame else None


def _wait(future: Any, deadline: float, stop: Any) -> bool:
    """Wait for an rclpy future until `deadline` (monotonic) or a stop; True when done."""
    while not future.done():
        if stop or time.monotonic() >= deadline:
            return False
        stop.wait(POLL_S)
    return True


def decision_msg(
    vehicle: str, learner: AdaptiveSplitLearner, chosen: str, fixed: bool, frame: int, last: float
) -> Any:
    from edgeloc_interfaces.msg import SplitDecision

    stats = learner.stats()
    arms = [s.arm for s in stats]
    rule = "fixed" if fixed else ("explore" if any(math.isinf(s.index) for s in stats) else "ucb")
    return SplitDecision(
        stamp=to_stamp(time.time()),
        vehicle=vehicle,
        frame_id=frame,
        chosen=chosen,
        chosen_index=arms.index(chosen),
        rule=rule,
        arm_names=arms,
        arm_n=[s.n for s in stats],
        arm_mean=[s.mean for s in stats],
        arm_var=[s.var for s in stats],
        arm_index=[s.index for s in stats],
        last_latency_s=last,
        plays=learner.bandit.t - 1,
        plays_total=learner.bandit.total_plays,
    )


def detector_msg(
    vehicle: str,
    det: KLChangeDetector,
    arm: str,
    event: ChangeEvent | None,
    streaks: dict[str, int],
    t: float,
) -> Any:
    """The DetectorEvent of the update `det` just made for `arm` (`event`: the reset it
    confirmed, if any). `streaks` mirrors the detector's rule (KL above threshold on C updates
    in a row) from its public figures; it is cleared with the detector on a reset."""
    from edgeloc_interfaces.msg import DetectorEvent

    if event is not None:
        kl, consecutive = float(event.kl), det.consecutive
        streaks.clear()
        at_play = event.at_play
    else:
        last = det.last_kl(arm)
        kl = math.nan if last is None else float(last)
        if last is not None:  # the detector fitted both windows on this update
            streaks[arm] = streaks.get(arm, 0) + 1 if last > det.threshold else 0
        consecutive = streaks.get(arm, 0)
        at_play = det.plays
    return DetectorEvent(
        stamp=to_stamp(t),
        vehicle=vehicle,
        arm=arm,
        kl=kl,
        threshold=det.threshold,
        consecutive=consecutive,
        required=det.consecutive,
        reset=event is not None,
        at_play=at_play,
    )


def main() -> int:
    args = NodeArgs.parse(prog="inference_request")
    cfg = args.config
    lc = cfg.learner
    torch.set_num_threads(1)  # the head is small; one thread keeps the budget honest
    model = load_model(cfg.weights)
    learner = lc.build(list(cfg.splits), cfg.seed)
    from edgeloc_interfaces.action import SplitInference
    from edgeloc_interfaces.msg import DetectorEvent, PoseEstimate
    from rclpy.action import ActionClient
    from sensor_msgs.msg import Image

    latest = LatestFrame()
    # The head (and its encoding) runs on its own thread, which joins the vehicle's compute
    # cgroup: the scenario's vehicle `cpu` throttles exactly the work a slow board would do.
    compute = ComputeThread(args.compute_cgroup, name="dnn-head")
    head_s: dict[str, list[float]] = {k: [] for k in cfg.splits}
    chosen: list[list[Any]] = []  # [wall time, split, cost charged]
    lat: dict[str, list[float]] = {k: [] for k in cfg.splits}
    played: Counter[str] = Counter()
    stats: dict[str, Any] = {
        "node": "inference_request",
        "vehicle": args.vehicle,
        "edge": args.edge,
        "requests": 0,
        "answers": 0,
        "lost": 0,
        "payload_bytes": 0,
        "no_server_s": 0.0,
        "resets": [],
        "detector_updates": 0,
        "compute_budget": compute.budget,
    }
    with ros_node(f"{args.vehicle}_inference_request", record=args.record) as ros:
        node, stop = ros.node, ros.stop

        def on_image(msg: Image) -> None:
            img = np.frombuffer(bytes(msg.data), dtype=np.uint8).copy()
            img = img.reshape(msg.height, msg.width, 3)
            latest.put(int(msg.header.frame_id), from_stamp(msg.header.stamp), img)

        node.create_subscription(Image, vehicle_topic(args.vehicle, "camera"), on_image, 10)
        from edgeloc_interfaces.msg import InferenceResult, SplitDecision

        answers = ros.publisher(PoseEstimate, vehicle_topic(args.vehicle, "dnn_answer"), 50)
        decisions = ros.publisher(SplitDecision, vehicle_topic(args.vehicle, "split_decision"), 50)
        detector = ros.publisher(DetectorEvent, vehicle_topic(args.vehicle, "detector"), 50)
        outcomes = ros.publisher(InferenceResult, vehicle_topic(args.vehicle, "inference"), 50)
        streaks: dict[str, int] = {}  # per arm: updates in a row with KL above threshold
        client = ros.owns(ActionClient(node, SplitInference, action_name(args.edge)))
        emit(READY, node="inference_request", action=action_name(args.edge))
        last_frame, last_latency = -1, math.nan
        stats["start_s"] = time.time()
        while not stop:
            if not client.server_is_ready():
                stop.wait(0.1)
                stats["no_server_s"] += 0.1
                continue
            got = latest.newer_than(last_frame, timeout_s=0.2)
            if got is None:
                continue
            frame, t0, image = got
            last_frame = frame
            start = time.time()
            fixed = lc.fixed_split is not None
            split = lc.fixed_split if fixed else learner.select()
            decisions.publish(
                decision_msg(args.vehicle, learner, split, fixed, frame, last_latency)
            )
            chosen.append([round(start, 3), split, None])

            def head(split: str = split, image: np.ndarray = image) -> tuple[Any, bytes]:
                with torch.no_grad():
                    act = model.head(split, torch.from_numpy(image[None]))
                return act, encode(act, cfg.codec)

            (act, blob), took = compute.run(head)
            head_s[split].append(took)
            goal = SplitInference.Goal(vehicle=args.vehicle, frame_id=frame, split_name=split)
            goal.split_index = split_index(split)
            goal.capture_stamp = to_stamp(t0)
            goal.codec = cfg.codec
            goal.shape = array.array("i", list(act.shape))
            goal.dtype = str(act.dtype).removeprefix("torch.")
            goal.payload = array.array("B", blob)
            stats["requests"] += 1
            stats["payload_bytes"] += len(blob)
            played[split] += 1
            deadline = time.monotonic() + args.timeout_s
            pose, handle = None, None
            edge_s, error, timed_out = math.nan, "", False
            sent = client.send_goal_async(goal)
            if _wait(sent, deadline, stop):
                handle = sent.result()
                if handle is not None and handle.accepted:
                    res = handle.get_result_async()
                    if _wait(res, deadline, stop):
                        result = res.result().result
                        edge_s = result.edge_compute_s
                        if result.ok:
                            p = result.pose.pose.pose
                            yaw = 2.0 * math.atan2(p.orientation.z, p.orientation.w)
                            pose = (p.position.x, p.position.y, yaw)
                        else:
                            error = f"edge: {result.error}"
                            emit("edge-error", frame=frame, error=result.error)
                    else:
                        timed_out, error = True, "no result within the request timeout"
                else:
                    error = "goal rejected by the edge server"
            else:
                timed_out, error = True, "goal not acknowledged within the request timeout"
            t_answer = time.time()

            ok = pose is not None and not stop
            if stop:  # every request gets its outcome, this one too (not charged, not fused)
                error, timed_out = "node stopped before the answer was used", False
            outcomes.publish(
                InferenceResult(
                    stamp=to_stamp(t_answer),
                    vehicle=args.vehicle,
                    frame_id=frame,
                    split=split,
                    split_index=goal.split_index,
                    payload_bytes=len(blob),
                    head_s=took,
                    edge_compute_s=float(edge_s),
                    latency_s=t_answer - t0 if ok else math.nan,
                    ok=ok,
                    timed_out=timed_out and not ok,
                    error=error,
                )
            )
            if stop:
                break
            if pose is None:
                stats["lost"] += 1
                cost = args.timeout_s
                if handle is not None and handle.accepted:
                    handle.cancel_goal_async()  # the edge may still hold it
            else:
                stats["answers"] += 1
                cost = t_answer - start
                last_latency = cost
                lat[split].append(cost)
                answers.publish(
                    PoseEstimate(
                        stamp=to_stamp(t0),
                        vehicle=args.vehicle,
                        method="dnn",
                        x=float(pose[0]),
                        y=float(pose[1]),
                        yaw=math.atan2(math.sin(pose[2]), math.cos(pose[2])),
                        latency_s=t_answer - t0,
                        frame_id=frame,
                    )
                )
            chosen[-1][2] = round(cost, 4)
            if fixed:
                continue
            event = learner.update(split, cost)
            if learner.detector is not None:
                # One DetectorEvent per detector update (a few per second), resets flagged.
                detector.publish(
                    detector_msg(args.vehicle, learner.detector, split, event, streaks, t_answer)
                )
                stats["detector_updates"] += 1
            if event is not None:
                stats["resets"].append({"t": t_answer, "arm": event.arm, "kl": event.kl})
                emit("reset", arm=event.arm, kl=event.kl)
    compute.close()
    stats["end_s"] = time.time()
    # Every decision [wall time, split, cost], so a reader can see which split each phase preferred.
    stats["decisions"] = chosen
    stats["head_s"] = {
        k: {"n": len(v), "mean": float(np.mean(v)), "p50": float(np.median(v)), "max": max(v)}
        for k, v in head_s.items()
        if v
    }
    stats["split_plays"] = {k: played[k] for k in cfg.splits}
    stats["mean_latency_s"] = {k: (float(np.mean(v)) if v else None) for k, v in lat.items()}
    stats["splits_known"] = list(SPLITS)
    stats["recorded"] = ros.recorded
    write_stats(args.stats, stats)
    return 0


if __name__ == "__main__":
    run_main(main)
