"""EdgeLoc as ROS 2 (rclpy) nodes: thin adapters between topics/actions and `nodes.edgeloc`.

One node per module, each runnable as its own process: `vehicle_sensor` (camera frames, VO,
ground truth), `inference_request` (DNN head, split learner, SplitInference client),
`fusion_node` (EdgeLoc fusion and the baselines), `edge_inference` (action servers, one per
vehicle, DNN tail), `link_events` (timeline events as LinkEvent messages). `container` runs
several in one process, one rclpy context, a node and executor thread each: in a run
(`testbed.supervisor`) a vehicle's three nodes are one process. `common` holds what every node
shares (settings, lifecycle, stats, and what a container's roles share).

Every drive starts at the timeline's 0 s: each vehicle's sensor, once its subscribers are there,
waits for a start time the supervisor writes once all are (`start`), so a `set` at 20 s reaches
every drive at its 20 s and a vehicle's radio moves with its camera (without it a report's
handovers fell away from the times the timeline applied them).

Interfaces: `make setup` builds nodes/edgeloc_interfaces (the SplitInference action and the
PoseEstimate, SplitDecision, DetectorEvent, InferenceResult, LinkEvent, LinkCounters,
RadioState, Handover and TrafficSample messages) against the installed Jazzy with cmake, into
.venv (`python -m nodes.ros.build`; it skips the build when the sources have not changed). Each
DNN answer carries the DNN's place entropy (`entropy_nats` of the action's result and of the
`dnn_answer` PoseEstimate, NaN on the other topics): the edge computes it with the pose, the
vehicle for the `vehicle` split, since the logits never leave it.

DDS (`env`): nodes find each other across the gNB router with unicast peers (multicast
discovery does not cross a router), Fast DDS socket buffers of 4 MiB so 1 MiB activations are
not dropped, and reliable writers that heartbeat every 100 ms, so a camera frame lost on the air
link is repaired in ~0.1 s rather than Fast DDS's default 3 s.
"""
