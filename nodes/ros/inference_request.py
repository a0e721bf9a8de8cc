"""The vehicle's thread 2 (paper §4): split point, DNN head, request to the edge, learning.

Loop, as fast as answers come: take the newest camera frame not sent yet (captured at t0);
ask the learner for a split k (`AdaptiveSplitLearner`, or the scenario's fixed split); run
layers [0:k] and encode (`LocNet.head`, `codec.encode`); send a SplitInference goal to the
edge; wait for the result up to the timeout. An answer is published on `/<vehicle>/dnn_answer`
(PoseEstimate method "dnn", stamp = t0, latency_s = Δt = t_answer − t0, entropy_nats the DNN's
doubt: the edge's, or for the vehicle split the vehicle's own) for the fusion node;
the learner is charged the request's own end-to-end time (loop start → answer), or the timeout
when no answer came (a lost request brings no pose), as `nodes.edgeloc.replay` does.

Also published: one SplitDecision per request (`/<vehicle>/split_decision`), one
InferenceResult per request (`/<vehicle>/inference`: split, payload, head and edge compute time,
latency, ok / timed out / error) and one DetectorEvent per update of the KL change detector
(`/<vehicle>/detector`, `reset` true on the update that reset the learner).
While no edge server has been discovered, no request is sent (counted as `no_server_s`): the
fusion node goes on with VO alone, which is the paper's fault tolerance.

`RequestLoop` (ROS-free) holds what the loop decides and counts: the learner and its change
detector, the split of each request, the cost each request is charged, and the statistics the
node writes at exit; `main` only wires the camera topic, the action client and the publishers
to it.
"""

from __future__ import annotations

import array
import math
import threading
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from nodes.edgeloc.bandit import AdaptiveSplitLearner
from nodes.edgeloc.codec import encode
from nodes.edgeloc.detector import ChangeEvent, KLChangeDetector
from nodes.edgeloc.model import IMAGE_SHAPE, SPLITS, split_index
from nodes.edgeloc.settings import ReplayConfig
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
from nodes.ros.serving import ServingEdge

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


def goal_msg(
    vehicle: str, frame: int, split: str, t0: float, codec: str, act: Any, blob: bytes
) -> Any:
    """The SplitInference goal of one request: the head's output `act`, encoded as `blob`."""
    from edgeloc_interfaces.action import SplitInference

    goal = SplitInference.Goal(vehicle=vehicle, frame_id=frame, split_name=split)
    goal.split_index = split_index(split)
    goal.capture_stamp = to_stamp(t0)
    goal.codec = codec
    goal.shape = array.array("i", list(act.shape))
    goal.dtype = str(act.dtype).removeprefix("torch.")
    goal.payload = array.array("B", blob)
    return goal


def answer_msg(
    vehicle: str,
    frame: int,
    t0: float,
    pose: tuple[float, float, float],
    t_answer: float,
    entropy_nats: float,
) -> Any:
    """The edge's pose for the frame captured at `t0`, for the fusion node (stamp = t0), with
    the DNN's place entropy (from the edge, or the vehicle's own for the vehicle split)."""
    from edgeloc_interfaces.msg import PoseEstimate

    return PoseEstimate(
        stamp=to_stamp(t0),
        vehicle=vehicle,
        method="dnn",
        x=float(pose[0]),
        y=float(pose[1]),
        yaw=math.atan2(math.sin(pose[2]), math.cos(pose[2])),
        latency_s=t_answer - t0,
        frame_id=frame,
        entropy_nats=float(entropy_nats),
    )


class RequestLoop:
    """Thread 2's decisions and bookkeeping, without ROS: which split each request plays, what
    it is charged, and the counters the node writes at exit (`stats`).

    Per request: `choose` (before the head runs), `sent` (the goal goes out), then, once the
    answer came or the timeout passed, `charge` and, unless the split is fixed, `learn`.
    """

    def __init__(
        self,
        cfg: ReplayConfig,
        vehicle: str,
        edge: str,
        timeout_s: float,
        compute_budget: dict[str, Any],
    ) -> None:
        self.cfg, self.timeout_s = cfg, timeout_s
        self.fixed_split = cfg.learner.fixed_split
        self.learner = cfg.learner.build(list(cfg.splits), cfg.seed)
        self.head_s: dict[str, list[float]] = {k: [] for k in cfg.splits}
        self.chosen: list[list[Any]] = []  # [wall time, split, cost charged]
        self.lat: dict[str, list[float]] = {k: [] for k in cfg.splits}
        self.played: Counter[str] = Counter()
        self.streaks: dict[str, int] = {}  # per arm: updates in a row with KL above threshold
        self.last_latency = math.nan  # the last answered request's cost, for SplitDecision
        self.stats: dict[str, Any] = {
            "node": "inference_request",
            "vehicle": vehicle,
            "edge": edge,
            "requests": 0,
            "answers": 0,
            "lost": 0,
            "payload_bytes": 0,
            "no_server_s": 0.0,
            "resets": [],
            "detector_updates": 0,
            "compute_budget": compute_budget,
        }

    @property
    def fixed(self) -> bool:
        """The scenario plays one split (a baseline): the learner is never charged."""
        return self.fixed_split is not None

    def no_server(self, waited_s: float) -> None:
        self.stats["no_server_s"] += waited_s

    def choose(self, start: float) -> str:
        """The split of the request that starts at `start` (wall clock)."""
        split = self.fixed_split if self.fixed_split is not None else self.learner.select()
        self.chosen.append([round(start, 3), split, None])
        return split

    def sent(self, split: str, head_s: float, payload_bytes: int) -> None:
        """The head ran for `head_s` and a goal of `payload_bytes` went to the edge."""
        self.head_s[split].append(head_s)
        self.stats["requests"] += 1
        self.stats["payload_bytes"] += payload_bytes
        self.played[split] += 1

    def charge(self, split: str, start: float, answered: bool, t_answer: float) -> float:
        """The cost of the request: its own end-to-end time when answered, else the timeout
        (a lost request brings no pose), as `nodes.edgeloc.replay` charges it."""
        if not answered:
            self.stats["lost"] += 1
            cost = self.timeout_s
        else:
            self.stats["answers"] += 1
            cost = t_answer - start
            self.last_latency = cost
            self.lat[split].append(cost)
        self.chosen[-1][2] = round(cost, 4)
        return cost

    def learn(self, split: str, cost: float, t_answer: float) -> ChangeEvent | None:
        """Charge the learner; the change the detector confirmed (the learner was reset), if
        any. `stats` counts the detector updates and keeps every reset."""
        event = self.learner.update(split, cost)
        if self.learner.detector is not None:
            self.stats["detector_updates"] += 1
        if event is not None:
            self.stats["resets"].append({"t": t_answer, "arm": event.arm, "kl": event.kl})
        return event

    def summary(self, start_s: float, end_s: float, recorded: Any) -> dict[str, Any]:
        """The node's statistics at exit."""
        stats = self.stats
        stats["start_s"] = start_s
        stats["end_s"] = end_s
        # Every decision [wall time, split, cost], so a reader can see which split each phase
        # preferred.
        stats["decisions"] = self.chosen
        stats["head_s"] = {
            k: {"n": len(v), "mean": float(np.mean(v)), "p50": float(np.median(v)), "max": max(v)}
            for k, v in self.head_s.items()
            if v
        }
        stats["split_plays"] = {k: self.played[k] for k in self.cfg.splits}
        stats["mean_latency_s"] = {
            k: (float(np.mean(v)) if v else None) for k, v in self.lat.items()
        }
        stats["splits_known"] = list(SPLITS)
        stats["recorded"] = recorded
        return stats


def _ask(
    client: Any, goal: Any, deadline: float, stop: Any, frame: int
) -> tuple[tuple[float, float, float] | None, Any, float, float, str, bool]:
    """Send `goal` and wait for its result until `deadline`: (pose or None, goal handle or
    None, edge compute time, the edge's place entropy, error text, whether the request timed
    out)."""
    pose, handle = None, None
    edge_s, entropy, error, timed_out = math.nan, math.nan, "", False
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
                    entropy = result.entropy_nats
                else:
                    error = f"edge: {result.error}"
                    emit("edge-error", frame=frame, error=result.error)
            else:
                timed_out, error = True, "no result within the request timeout"
        else:
            error = "goal rejected by the edge server"
    else:
        timed_out, error = True, "goal not acknowledged within the request timeout"
    return pose, handle, edge_s, entropy, error, timed_out


def main(argv: Sequence[str] | None = None) -> int:
    args = NodeArgs.parse(argv, prog="inference_request")
    cfg = args.config
    torch.set_num_threads(1)  # the head is small; one thread keeps the budget honest
    model = load_model(cfg.weights)
    from edgeloc_interfaces.action import SplitInference
    from edgeloc_interfaces.msg import DetectorEvent, PoseEstimate
    from rclpy.action import ActionClient
    from sensor_msgs.msg import Image

    latest = LatestFrame()

    # The head (and its encoding) runs on its own thread, which joins the vehicle's compute
    # cgroup: the scenario's vehicle `cpu` throttles exactly the work a slow board would do.
    def warmup() -> None:
        blank = torch.zeros((1, *IMAGE_SHAPE), dtype=torch.uint8)
        with torch.no_grad():
            for split in cfg.splits:
                encode(model.vehicle_side(split, blank)[0], cfg.codec)

    compute = ComputeThread(args.compute_cgroup, name="dnn-head", warmup=warmup)
    loop = RequestLoop(cfg, args.vehicle, args.edge, args.timeout_s, compute.budget)
    learner = loop.learner
    with ros_node(f"{args.vehicle}_inference_request", record=args.record, events=True) as ros:
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
        # One client per edge server the vehicle may ask: with `edge: follow`, the serving
        # cell's (read from its own default route, `nodes.ros.serving`), else `--edge`'s.
        serving = ServingEdge(args.edge, args.edges)
        clients = {
            edge: ros.owns(ActionClient(node, SplitInference, action_name(edge, args.vehicle)))
            for edge in dict.fromkeys([args.edge, *args.edges.values()])
        }
        emit(READY, node="inference_request", action=action_name(args.edge, args.vehicle))
        last_frame = -1
        start_s = time.time()
        while not stop:
            edge = serving.now()
            client = clients[edge]
            if not client.server_is_ready():
                stop.wait(0.1)
                loop.no_server(0.1)
                continue
            got = latest.newer_than(last_frame, timeout_s=0.2)
            if got is None:
                continue
            frame, t0, image = got
            last_frame = frame
            start = time.time()
            split = loop.choose(start)
            decisions.publish(
                decision_msg(args.vehicle, learner, split, loop.fixed, frame, loop.last_latency)
            )

            def head(split: str = split, image: np.ndarray = image) -> tuple[Any, bytes, Any]:
                with torch.no_grad():
                    act, entropy = model.vehicle_side(split, torch.from_numpy(image[None]))
                return act, encode(act, cfg.codec), entropy

            (act, blob, own_entropy), took = compute.run(head)
            goal = goal_msg(args.vehicle, frame, split, t0, cfg.codec, act, blob)
            loop.sent(split, took, len(blob))
            deadline = time.monotonic() + args.timeout_s
            pose, handle, edge_s, entropy, error, timed_out = _ask(
                client, goal, deadline, stop, frame
            )
            if own_entropy is not None:  # the vehicle split: the logits never left the vehicle
                entropy = float(own_entropy[0])
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
                    edge=edge,
                )
            )
            if stop:
                break
            cost = loop.charge(split, start, pose is not None, t_answer)
            if pose is None:
                if handle is not None and handle.accepted:
                    handle.cancel_goal_async()  # the edge may still hold it
            else:
                answers.publish(answer_msg(args.vehicle, frame, t0, pose, t_answer, entropy))
            if loop.fixed:
                continue
            event = loop.learn(split, cost, t_answer)
            if learner.detector is not None:
                # One DetectorEvent per detector update (a few per second), resets flagged.
                detector.publish(
                    detector_msg(
                        args.vehicle, learner.detector, split, event, loop.streaks, t_answer
                    )
                )
            if event is not None:
                emit("reset", arm=event.arm, kl=event.kl)
    compute.close()
    write_stats(args.stats, loop.summary(start_s, time.time(), ros.recorded))
    return 0


if __name__ == "__main__":
    run_main(main)
