"""What `testbed replay FILE` calls: replay the scenario over one vehicle's path, write
runs/<id>/ (summary.json, TUM trajectories, scenario.yaml) and return what it wrote
(`ReplayRun`); the CLI prints it. With a channel, the summary also holds the radio bands.
"""

from __future__ import annotations

import math
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nodes.edgeloc import bands
from nodes.edgeloc.compare import compare_splits
from nodes.edgeloc.gate import GateSettings
from nodes.edgeloc.latency import ComputeProfile
from nodes.edgeloc.replay import (
    InferenceCache,
    ReplayResult,
    config_dataset,
    run_replay,
)
from nodes.edgeloc.train import load_model
from nodes.recording import layout as names
from nodes.recording.jsonfile import write_json
from testbed.errors import BadInput
from testbed.folders import check_writable_folder, make_folder
from testbed.nodesettings import DEFAULT_GATE, replay_config
from testbed.replay.path import _PathPlan, latency_model
from testbed.scenario.model import HandoverEvent, Scenario


@dataclass(frozen=True)
class ReplayRun:
    """What a replay wrote: its folder (`runs/<id>/`), the result, and summary.json's content."""

    folder: Path
    result: ReplayResult
    summary: dict[str, Any]


def replay_scenario(
    scenario: Scenario,
    runs_dir: Path,
    compute: ComputeProfile | None = None,
    gate: GateSettings | None = DEFAULT_GATE,
    compare: bool = True,
    vehicle: str | None = None,
) -> ReplayRun:
    """Replay and write runs/<id>/ (summary.json, TUM trajectories, scenario.yaml), over the
    path of `vehicle` (default: the first EdgeLoc vehicle).

    With `compare`, summary.json's `splits` holds EdgeLoc with every fixed split and the
    oracle on the same drive (`nodes.edgeloc.compare`; K + 2 more replays).
    Raises BadInput for a dataset or weights the scenario names that cannot be used, or a
    runs folder this user cannot write."""
    check_writable_folder(Path(runs_dir), "runs folder")
    config = replay_config(scenario, gate=gate)
    model = latency_model(scenario, compute, vehicle=vehicle)
    try:
        dataset = config_dataset(config)
        net = load_model(config.weights)
        cache = InferenceCache(net, dataset, config.codec)
        result = run_replay(config, model, dataset, net, cache)
        splits = None
        if compare:
            learned = result if config.learner.fixed_split is None else None
            splits = compare_splits(config, model, dataset, net, cache, learned).to_dict()
    except ValueError as err:  # a bad dataset folder, weights that do not fit
        raise BadInput(f"{scenario.name}: {err}") from None
    folder = make_folder(Path(runs_dir), "runs folder") / secrets.token_hex(3)
    summary = result.write(folder)
    summary["run_id"] = folder.name
    if splits is not None:
        summary["splits"] = splits
    summary["vehicle"] = model_vehicle = _PathPlan(scenario, vehicle).vehicle.name
    if scenario.channel is not None:
        summary["radio"] = radio_bands(scenario, summary, model_vehicle, result)
    write_json(folder / names.SUMMARY_FILE, summary)
    if scenario.source is not None and Path(scenario.source).is_file():
        shutil.copyfile(scenario.source, folder / names.SCENARIO_FILE)
    return ReplayRun(folder, result, summary)


def radio_bands(
    scenario: Scenario, summary: dict[str, Any], vehicle: str, result: ReplayResult
) -> dict[str, Any]:
    """The replayed vehicle's plays by the uplink MCS their request met, and around each of
    its handovers (`nodes.edgeloc.bands`): where the channel makes the network follow the
    place, what the learner and EdgeLoc's error did."""
    from testbed import mobility

    assert scenario.channel is not None, "radio bands need a channel"
    plan = mobility.plans_of(scenario)[vehicle]
    step = scenario.channel.step_s
    ul = [s.ul_mcs for s in plan.steps]
    decisions = summary["learner"]["decisions"]
    at_play = [ul[min(len(ul) - 1, max(0, int(t / step + 1e-9)))] for t in decisions["sent_s"]]
    payload = {
        split: figures["mean_bytes"]
        for split, figures in summary["latency"]["per_split"].items()
        if figures.get("mean_bytes") is not None
    }
    rows = bands.by_band(at_play, decisions["split"], payload, bands.time_shares(ul))
    series = bands.Series(
        sent_s=decisions["sent_s"],
        splits=decisions["split"],
        latency_s=[math.inf if x is None else x for x in decisions["latency_s"]],
        payload_bytes=payload,
        frame_t=(result.timestamps - result.timestamps[0]).tolist(),
        frame_error_m=np.hypot(*(result.poses["edgeloc"][:, :2] - result.gt[:, :2]).T).tolist(),
        mcs_t=[s.t for s in plan.steps],
        ul_mcs=ul,
    )
    handovers = [
        {
            "t_s": e.at_s,
            "source": e.source,
            "target": e.target,
            "interruption_s": e.interruption_s,
            "lossless": e.lossless,
            "around": bands.around(e.at_s, series),
        }
        for e in scenario.timeline
        if isinstance(e, HandoverEvent) and e.vehicle == vehicle
    ]
    return {"vehicle": vehicle, "by_uplink_mcs": rows, "handovers": handovers}
