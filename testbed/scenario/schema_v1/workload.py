"""The `workload` section of schema v1: EdgeLoc's rates, data, model, and the knobs of its
split-point learner, its latency-aware fusion and the Kalman baseline.
"""

from __future__ import annotations

from testbed.scenario import model
from testbed.scenario.kinds import (
    Bool,
    Duration,
    Enum,
    Field,
    Float,
    Int,
    ListOf,
    Nullable,
    Obj,
    Percent,
    Str,
)
from testbed.scenario.schema_v1.shared import MAX_DELAY_S, WORKLOAD_KIND

LEARNER = Obj(
    "Split-point learner (sliding-window UCB1-normal) and its KL change detector.",
    [
        Field("window", Int(2, noun="a window of plays"), "W: plays kept by the sliding window."),
        Field("cost", Enum(("latency", "error")), "What the learner minimizes."),
        Field(
            "fixed_split",
            Nullable(Str("a split name")),
            "Play only this split (a baseline); null: learn.",
        ),
        Field("detector", Bool(), "Reset the learner when the cost distribution changes."),
        Field(
            "kl_threshold",
            Float(0.0, lo_open=True, noun="a KL divergence"),
            "KL divergence that counts as a change.",
        ),
        Field(
            "consecutive",
            Int(1, noun="a count"),
            "C: consecutive exceedances that trigger a reset.",
        ),
        Field(
            "detector_window",
            Int(2, noun="a number of samples"),
            "Samples per Gaussian fit of the detector.",
        ),
    ],
    model=model.Learner,
)
FUSION = Obj(
    "Latency-aware fusion weight 1 / (1 + exp(-k_s (dt - dt0))).",
    [
        Field("k_s", Float(0.0, lo_open=True, noun="a slope (1/s)"), "Slope k_s, in 1/s."),
        Field(
            "dt0",
            Duration(MAX_DELAY_S, lo=-MAX_DELAY_S, noun="a latency offset", signed=True),
            "Midpoint latency dt0 of the sigmoid; may be negative (the weight u is then below"
            " 1/2 even for an instant answer).",
            attr="dt0_s",
        ),
        Field(
            "robust",
            Nullable(Float(0.0, lo_open=True, noun="a multiple of the median innovation")),
            "BEYOND THE PAPER: scale each answer's weight by 1 / (1 + (r / (c s))^2), r its"
            " distance from the fused pose, s the median of the last 50; null: the paper's"
            " latency-only weight.",
            attr="robust_c",
        ),
        Field(
            "robust_centre",
            Nullable(Duration(60.0, lo_open=True, noun="a window")),
            "BEYOND THE PAPER, with robust and method paper: measure r from the answers' mean"
            " innovation over this window (in the vehicle's frame) instead of from the fused"
            " pose, so the lag a drifting VO builds up is corrected rather than shrunk as an"
            " outlier; null: from the fused pose.",
            attr="robust_centre_s",
        ),
        Field(
            "method",
            Enum(("paper", "ekf")),
            "paper: the latency weight above; ekf (BEYOND THE PAPER): a delayed-measurement EKF"
            " over pose, VO scale and yaw-rate bias that corrects its state at each answer's"
            " capture time and replays the VO since, with the kalman block's r_pos/r_yaw as the"
            " DNN's noise and robust as above (k_s and dt0 unused).",
        ),
        Field(
            "correlation",
            Nullable(Duration(10.0, lo_open=True, noun="a correlation time")),
            "ekf only (BEYOND THE PAPER): the DNN's errors are correlated over this time, so an"
            " answer soon after the previous one counts for less (its R times (1 + rho) /"
            " (1 - rho), rho = exp(-gap / correlation)); null: every answer independent.",
            attr="correlation_s",
        ),
        Field(
            "confidence",
            Bool(),
            "BEYOND THE PAPER, method paper only: scale each answer's weight by the DNN's own"
            " doubt, the entropy H of its place classifier, as min(1, exp(-per_nat (H -"
            " H_ref))), calibrated on held-out drives (confidence.json beside the weights:"
            " `python -m nodes.edgeloc.train --calibrate --out DIR` writes it).",
        ),
    ],
    model=model.Fusion,
)
_VARIANCE = Float(0.0, noun="a variance")
_POSITIVE_VARIANCE = Float(0.0, lo_open=True, noun="a variance")
KALMAN = Obj(
    "Kalman-filter baseline noise (per-axis variances, m^2 and rad^2).",
    [
        Field("q_pos", _VARIANCE, "Process noise of x and y (m^2)."),
        Field("q_yaw", _VARIANCE, "Process noise of the heading (rad^2)."),
        Field("r_pos", _POSITIVE_VARIANCE, "Measurement noise of x and y (m^2)."),
        Field("r_yaw", _POSITIVE_VARIANCE, "Measurement noise of the heading (rad^2)."),
    ],
    model=model.Kalman,
)
WORKLOAD = Obj(
    "The EdgeLoc workload: rates, data, model and algorithm knobs.",
    [
        Field(
            "kind",
            WORKLOAD_KIND,
            "The built-in workload: edgeloc, or none (a scenario of apps and traffic only).",
        ),
        Field(
            "rate_hz",
            Float(0.0, 1000.0, lo_open=True, noun="a rate in Hz"),
            "Real-time thread rate (VO and fused pose).",
        ),
        Field(
            "dataset",
            Str("'synthetic' or a path to a folder of recorded data"),
            "'synthetic', or a folder of recorded data relative to the scenario file.",
        ),
        Field("codec", Enum(("fp16-zlib", "int8-zlib")), "How intermediate features are sent."),
        Field(
            "weights",
            Nullable(Str("a path to a weights file")),
            "Model weights relative to the scenario file; null: the repo's trained model.",
        ),
        Field(
            "splits",
            Nullable(ListOf(Str("a split name"), min_items=1, unique=True)),
            "Split points the learner may play; null: every split point of the model.",
        ),
        Field(
            "corruption",
            Percent(noun="a corruption rate"),
            "Experiment knob: share of corrupted requests (off by default; reports name it).",
        ),
        Field("learner", LEARNER, "Split-point learner."),
        Field("fusion", FUSION, "Latency-aware fusion."),
        Field("kalman", KALMAN, "Kalman-filter baseline."),
    ],
    model=model.Workload,
)
