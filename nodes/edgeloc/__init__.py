"""EdgeLoc algorithms, pure Python/numpy/torch. Nothing here imports ROS or pyroute2.

From the paper (EdgeLoc: "a communication-adaptive parallel system for real-time localization
in infrastructure-assisted autonomous driving") to the code:
  §3 parallel architecture (thread 1 never waits on the network; thread 2 requests):
    nodes/ros/fusion_node.py (thread 1), inference_request.py (thread 2), edge_inference.py
  §4.1 Kalman filtering as the baseline: `kalman`
  §4.2 time-zone revision and the sigmoid latency weight (k_s, Δt0): `fusion`
  §4.3 accuracy improvement as latency reduction (split DNN): `model`, `codec`, `latency`
  §5.1 sliding-window UCB1-normal split selection: `bandit`
  §5.2 KL-divergence change detection: `detector`
  §6.1 comparison with VO, DNN and Kalman (four totals, three reductions): `metrics` and the
    report's accuracy section (`reports.sections.accuracy`)
  §6.2 cellular network with Wondershaper-shaped uplink phases: scenarios/default.yaml, the tc
    backend's shaping (`netem.tc.shaping`), the testbed's timeline
  the whole loop offline: `replay` (`testbed replay`, `testbed sweep`)
  learned vs every fixed split vs the per-phase oracle on the same drive: `compare` (a real
    run's report replays it with the run's measured latencies, `latency.MeasuredLatency`)
Beyond the paper: the robust (uncertainty-aware) weight `workload.fusion.robust`, its centring
on the recent innovation `workload.fusion.robust_centre`, and the plausibility gate (`fusion`,
`gate`); the DNN's own doubt, `workload.fusion.confidence` (each answer's weight scaled by its
place entropy, calibrated on held-out drives: weights/confidence.json, `python -m
nodes.edgeloc.train --calibrate`; `model.vehicle_side`, `model.edge_side`; `train`);
`workload.fusion.method: ekf`, a delayed-measurement EKF over pose, VO scale and yaw-rate bias
(each answer corrects the state at its capture time, the VO since is replayed), with
`workload.fusion.correlation: 150ms` telling it the DNN's errors are correlated over that time
(`ekf`).
"""
