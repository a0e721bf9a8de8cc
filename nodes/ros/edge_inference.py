"""The edge server's RSU inference (paper §4): layers [k:] of the split DNN for each request.

Serves the SplitInference action `/<edge>/<vehicle>/split_inference` of every vehicle it
serves (`--serve`; one action each, `nodes.ros.common.action_name`): decodes the activation
(`codec.decode`, self-describing blob), runs `LocNet.edge_side(split)` and answers L_alpha(t0)
with the goal's capture stamp and the DNN's place entropy (its doubt, for the fusion's
confidence weight; NaN for the vehicle split, where the vehicle reads it). A goal that cannot be
decoded or names an unknown split is answered with ok = false and the reason (never a crash of
the server).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

import torch

from nodes.edgeloc.codec import CodecError, decode, encode
from nodes.edgeloc.model import IMAGE_SHAPE, split_index, to_pose
from nodes.edgeloc.train import load_model
from nodes.ros.common import (
    READY,
    ComputeThread,
    NodeArgs,
    action_name,
    emit,
    ros_node,
    run_main,
    write_stats,
)

RESULT_TIMEOUT_S = 1  # seconds a finished goal's result is kept for the client


def main(argv: Sequence[str] | None = None) -> int:
    args = NodeArgs.parse(argv, prog="edge_inference")
    if not args.serve:
        raise ValueError("edge_inference: --serve names no vehicle (av1,av2,...)")
    torch.set_num_threads(1)
    model = load_model(args.config.weights)
    from edgeloc_interfaces.action import SplitInference
    from rclpy.action import ActionServer

    stats: dict[str, Any] = {"node": "edge_inference", "edge": args.edge, "goals": 0, "ok": 0}
    per_vehicle: Counter[str] = Counter()
    compute: list[float] = []
    payload_bytes = [0]

    # The tail runs on one thread that joins the core's compute cgroup (the scenario's
    # core_cpu), so only the DNN stage is budgeted, not the action server's executor.
    def warmup() -> None:  # every split's tail once, from the head's output on a blank frame
        blank = torch.zeros((1, *IMAGE_SHAPE), dtype=torch.uint8)
        codec = args.config.codec
        with torch.no_grad():
            for split in args.config.splits:
                model.edge_side(split, decode(encode(model.head(split, blank), codec)))

    tail_thread = ComputeThread(args.compute_cgroup, name="dnn-tail", warmup=warmup)
    tail_s: list[float] = []
    stats["compute_budget"] = tail_thread.budget

    with ros_node(f"{args.edge}_edge_inference") as ros:
        node = ros.node

        def execute(handle: Any) -> Any:
            received = node.get_clock().now().to_msg()
            start = time.perf_counter()
            goal = handle.request
            stats["goals"] += 1
            per_vehicle[goal.vehicle] += 1
            blob = bytes(goal.payload)
            payload_bytes[0] += len(blob)
            result = SplitInference.Result(
                frame_id=goal.frame_id, split_index=goal.split_index, entropy_nats=math.nan
            )
            try:
                if split_index(goal.split_name) != goal.split_index:
                    raise ValueError(f"split {goal.split_name!r} is not index {goal.split_index}")

                def tail() -> tuple[list[float], float]:
                    with torch.no_grad():
                        out, entropy = model.edge_side(goal.split_name, decode(blob))
                    doubt = math.nan if entropy is None else float(entropy[0])
                    return to_pose(out)[0].tolist(), doubt

                (pose, result.entropy_nats), took = tail_thread.run(tail)
                tail_s.append(took)
                result.ok = True
                stats["ok"] += 1
                p = result.pose
                p.header.stamp = goal.capture_stamp
                p.header.frame_id = "map"
                p.pose.pose.position.x = float(pose[0])
                p.pose.pose.position.y = float(pose[1])
                p.pose.pose.orientation.z = math.sin(pose[2] / 2.0)
                p.pose.pose.orientation.w = math.cos(pose[2] / 2.0)
            except (CodecError, ValueError, RuntimeError) as err:
                result.ok, result.error = False, str(err)
                emit("bad-goal", frame=goal.frame_id, error=str(err))
            handle.succeed()
            result.edge_compute_s = time.perf_counter() - start
            compute.append(result.edge_compute_s)
            result.edge_receive_stamp = received
            result.edge_send_stamp = node.get_clock().now().to_msg()
            return result

        # Results are fetched right after they are ready; keeping them for rclpy's default
        # 900 s would make every goal-status message list every goal of the run (its size,
        # and so the downlink bytes per request, would grow with the run's length).
        # One action per vehicle (`action_name`), all served by this node and its executor.
        actions = [action_name(args.edge, v) for v in args.serve]
        for name in actions:
            ros.owns(
                ActionServer(node, SplitInference, name, execute, result_timeout=RESULT_TIMEOUT_S)
            )
        emit(READY, node="edge_inference", actions=actions)
        ros.stop.wait(1e9)
    tail_thread.close()
    stats["per_vehicle"] = dict(per_vehicle)
    stats["mean_tail_s"] = sum(tail_s) / len(tail_s) if tail_s else None
    stats["payload_bytes"] = payload_bytes[0]
    stats["mean_compute_s"] = sum(compute) / len(compute) if compute else None
    write_stats(args.stats, stats)
    return 0


if __name__ == "__main__":
    run_main(main)
