"""The vehicle's sensors: camera frames, visual odometry and ground truth at the workload rate.

Thread 1's input (paper §4): frame i of the dataset is published at `start + i / rate` with
that wall-clock instant as its capture stamp t0, on
- `/<vehicle>/camera` (sensor_msgs/Image, rgb8; `header.frame_id` is the frame number),
- `/<vehicle>/vo` (PoseEstimate, method "vo": L_beta(t)),
- `/<vehicle>/gt` (PoseEstimate, method "gt": for scoring only; no estimator reads it).
The dataset is the scenario's (synthetic world with its seed, or a recorded folder), opened
with `DATASET_MARGIN_S` more seconds than the run lasts; with `--frames` a synthetic drive's
images come from the frames the run rendered ahead (`nodes.edgeloc.frames`). Publishing
starts once the fusion and inference nodes subscribe (or after 20 s), so no frame is lost to
discovery; in a run, at the run's common start (`nodes.ros.start`: frame 0 at the timeline's
0 s, every vehicle together).
"""

from __future__ import annotations

import array
import time
from collections.abc import Sequence

import numpy as np

from nodes.edgeloc.dataset import SyntheticDataset, open_dataset
from nodes.edgeloc.frames import Frames, FramesKey
from nodes.recording.layout import vehicle_topic
from nodes.ros.common import (
    DATASET_MARGIN_S,
    READY,
    NodeArgs,
    emit,
    ros_node,
    run_main,
    to_stamp,
    write_stats,
)
from nodes.ros.start import MATCHED, wait_start

WAIT_FOR_SUBSCRIBERS_S = 20.0
#: How long a matched sensor waits for the run's start time (`nodes.ros.start`).
START_TIMEOUT_S = 120.0


def pose_msg(vehicle: str, method: str, pose: np.ndarray, t: float, frame: int) -> object:
    from edgeloc_interfaces.msg import PoseEstimate

    return PoseEstimate(
        stamp=to_stamp(t),
        vehicle=vehicle,
        method=method,
        x=float(pose[0]),
        y=float(pose[1]),
        yaw=float(pose[2]),
        latency_s=float("nan"),
        frame_id=frame,
        entropy_nats=float("nan"),
    )


def main(argv: Sequence[str] | None = None) -> int:
    args = NodeArgs.parse(argv, prog="vehicle_sensor")
    cfg = args.config
    dataset = open_dataset(
        cfg.dataset,
        seed=cfg.seed,
        rate_hz=cfg.rate_hz,
        duration_s=cfg.duration_s + DATASET_MARGIN_S,
        corruption=cfg.corruption,
    )
    # A run renders the drive once, ahead (`nodes.edgeloc.frames`): drawing the world is the
    # emulation's work, not the vehicle's, and would cost this node most of its CPU.
    image = dataset.image
    frames = None
    if args.frames is not None and isinstance(dataset, SyntheticDataset):
        key = FramesKey(cfg.seed, cfg.rate_hz, cfg.duration_s + DATASET_MARGIN_S, cfg.corruption)
        frames = Frames(args.frames, dataset, key)
        image = frames.image
    from edgeloc_interfaces.msg import PoseEstimate
    from sensor_msgs.msg import Image

    stats: dict[str, object] = {"node": "vehicle_sensor", "vehicle": args.vehicle, "frames": 0}
    with ros_node(f"{args.vehicle}_sensor", spin=False, record=args.record) as ros:
        stop = ros.stop
        # Camera frames are recorded only when the scenario asks (`record.images`).
        camera = ros.publisher(Image, vehicle_topic(args.vehicle, "camera"), 10, args.record_images)
        vo_pub = ros.publisher(PoseEstimate, vehicle_topic(args.vehicle, "vo"), 50)
        gt_pub = ros.publisher(PoseEstimate, vehicle_topic(args.vehicle, "gt"), 50)
        emit(READY, node="vehicle_sensor", frames=len(dataset), rate_hz=dataset.rate_hz)
        deadline = time.monotonic() + WAIT_FOR_SUBSCRIBERS_S
        while not stop and time.monotonic() < deadline:
            if camera.get_subscription_count() >= 1 and vo_pub.get_subscription_count() >= 1:
                break
            stop.wait(0.05)
        h, w, _ = dataset.image_shape
        period = 1.0 / dataset.rate_hz
        start = None
        if args.start_file is not None:
            emit(MATCHED, subscribers=vo_pub.get_subscription_count())
            start = wait_start(args.start_file, stop, START_TIMEOUT_S)  # None: stopped
        start = time.time() if start is None else start
        stats["start_s"] = start
        emit("publishing", subscribers=vo_pub.get_subscription_count(), start_s=start)
        late_max = 0.0
        for i in range(len(dataset)):
            due = start + i * period
            if stop.wait(max(0.0, due - time.time())):
                break
            late_max = max(late_max, time.time() - due)
            img = Image(height=h, width=w, encoding="rgb8", is_bigendian=0, step=w * 3)
            img.header.stamp = to_stamp(due)
            img.header.frame_id = str(i)
            img.data = array.array("B", np.ascontiguousarray(image(i)).tobytes())
            camera.publish(img)
            vo_pub.publish(pose_msg(args.vehicle, "vo", dataset.vo_pose(i), due, i))
            gt_pub.publish(pose_msg(args.vehicle, "gt", dataset.gt_pose(i), due, i))
            stats["frames"] = i + 1
        else:
            emit("dataset-end", frames=len(dataset))
            stop.wait(1e9)  # stay up until stopped: the supervisor treats an exit as a failure
        stats["end_s"] = time.time()
        stats["max_lateness_s"] = late_max
        stats["prerendered_frames"] = len(frames) if frames is not None else 0
        stats["rendered_here"] = frames.rendered_here if frames is not None else None
    stats["recorded"] = ros.recorded
    write_stats(args.stats, stats)
    return 0


if __name__ == "__main__":
    run_main(main)
