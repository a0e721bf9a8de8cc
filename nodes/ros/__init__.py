"""EdgeLoc as ROS 2 (rclpy) nodes: thin adapters between topics/actions and `nodes.edgeloc`.

One node per module, each started as its own process inside a namespace by
`testbed.supervisor`: `vehicle_sensor` (camera frames, VO, ground truth), `inference_request`
(DNN head, split learner, SplitInference client), `fusion_node` (EdgeLoc fusion and the
baselines), `edge_inference` (action server, DNN tail), `link_events` (timeline events as
LinkEvent messages). `common` holds what every node shares (settings, lifecycle, stats).
"""
