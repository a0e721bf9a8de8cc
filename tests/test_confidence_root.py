"""`workload.fusion.confidence` in a real run: the DNN's doubt travels with each answer.

The smoke scenario, cut to a few seconds, with camera frames recorded and the confidence weight
on. Every answer on `/av1/dnn_answer` must carry the place entropy of the DNN on that very frame
at that split: recomputed here from the recorded camera image with the model and the codec
(not from the nodes' code path: `LocNet.head`/`tail` and torch's own Categorical entropy), for
the splits the edge reads it at and for the vehicle split, where the vehicle does. The fusion
node must have fused every one of them with the committed calibration, and the report's replay
must use the weight and name it as beyond the paper.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tests.realrun import short_smoke

pytestmark = [pytest.mark.root, pytest.mark.ros, pytest.mark.slow, pytest.mark.e2e]


def test_each_answer_carries_the_dnns_doubt_and_the_fusion_weighs_it(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    import numpy as np
    import torch
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from nodes.edgeloc.codec import decode, encode
    from nodes.edgeloc.fusion import ConfidenceWeight
    from nodes.edgeloc.model import SPLITS
    from nodes.edgeloc.settings import confidence_file
    from nodes.edgeloc.train import load_model
    from reports.mcapread import read_run
    from reports.splits import split_comparison
    from testbed.run import run_scenario
    from testbed.scenario.loader import load

    lines: list[str] = []
    doubt = ("learner: {window: 20}", "learner: {window: 20}\n  fusion: {confidence: true}")
    scenario = load(short_smoke(tmp_path, 8, images=True, name="confidence", also=(doubt,)))
    result = run_scenario(scenario, tmp_path, lines.append)
    assert result.ok, "\n".join(lines)

    by_topic: dict[str, list] = {}
    with open(result.folder / "run.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, msg in reader.iter_decoded_messages(
            topics=["/av1/dnn_answer", "/av1/camera", "/av1/inference"]
        ):
            by_topic.setdefault(channel.topic, []).append(msg)
    answers = by_topic["/av1/dnn_answer"]
    images = {int(m.header.frame_id): m for m in by_topic["/av1/camera"]}
    split_of = {m.frame_id: m.split for m in by_topic["/av1/inference"] if m.ok}
    assert len(answers) >= 20, len(answers)

    model = load_model(scenario.workload.weights)
    codec = scenario.workload.codec
    seen: set[str] = set()
    for a in answers:
        split = split_of[a.frame_id]
        seen.add(split)
        img = images[a.frame_id]
        x = torch.from_numpy(
            np.frombuffer(bytes(img.data), dtype=np.uint8)
            .reshape(1, img.height, img.width, 3)
            .copy()
        )
        with torch.no_grad():
            if split == SPLITS[-1]:  # the vehicle reads the logits; only the pose is sent
                features = model.head(SPLITS[-2], x)
            else:  # the edge: what crossed the link, decoded, up to the pose layer
                features = decode(encode(model.head(split, x), codec))
                for stage in model.stages[SPLITS.index(split) : -1]:
                    features = stage(features)
            logits = model.pose_layer.parts(features)[0]
        oracle = float(torch.distributions.Categorical(logits=logits).entropy()[0])
        assert math.isfinite(a.entropy_nats), (a.frame_id, split)
        assert a.entropy_nats == pytest.approx(oracle, abs=1e-4), (a.frame_id, split)
    assert "vehicle" in seen and seen - {"vehicle"}, seen

    procs = {n: p["stats"] for n, p in result.nodes["processes"].items()}
    fusion = procs["av1.fusion"]
    committed = ConfidenceWeight.read(confidence_file(None))
    assert fusion["confidence"] == {
        "per_nat": committed.per_nat,
        "reference_nats": committed.reference_nats,
    }
    assert fusion["answers"] == len(answers) and fusion["answers_without_entropy"] == 0
    assert fusion["applied_edgeloc"] > 0
    # The report's replay of the drive (learned, each fixed split, the oracle) uses the weight
    # too, and says it is beyond the paper.
    comparison = split_comparison(read_run(result.folder))
    assert "rows" in comparison, comparison
    assert "scaled by the DNN's entropy" in comparison["fusion"]
    assert "BEYOND THE PAPER" in comparison["fusion"]
