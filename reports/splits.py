"""Learned against fixed splits and the oracle, on a real run: `split_comparison(data)`.

`testbed replay` compares EdgeLoc's learned split choice with every fixed split and the
per-phase oracle on one drive (`nodes.edgeloc.compare`). This module does the same for a real
run's recording: the nodes' settings attached to run.mcap (`nodes/config.json`) give the
drive back (the synthetic dataset is regenerated from its seed, rate, duration and
corruption) and the DNN (the configured weights); the run's own inference records of one
vehicle give the network, as `nodes.edgeloc.latency.MeasuredLatency`: each replayed request of
split k in a phase takes the latency of a request of k that the run measured in that phase.
The learner, each fixed split and the oracle are then replayed under those latencies.

Only the MCAP is read (and the weights, which the recording names but does not hold), so the
block is the same on every rebuild. Anything that stops it (no settings attachment, no torch,
no weights, a recorded dataset, no inference records) gives `{"skipped": why}` instead.

Keys (besides `nodes.edgeloc.compare.SplitComparison.to_dict`'s): `vehicle` (whose requests
timed the replays), `requests` (how many), `replayed_splits` (the splits the run measured,
which the replays could play), `real_learned_total_m` (EdgeLoc's recorded total position
error of that vehicle in the real run).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

from nodes.edgeloc.settings import ReplayConfig, config_from_dict
from nodes.recording.layout import NODE_CONFIG_FILE
from reports.mcapread import Inference, RunData, VehicleData

#: The error text of the request in flight when the node was stopped: not a lost request.
STOPPED_ERROR = "node stopped"


def run_config(data: RunData) -> ReplayConfig | str:
    """The nodes' settings attached to the recording, or why there are none."""
    raw = data.attachments.get(NODE_CONFIG_FILE)
    if raw is None:
        return f"the recording has no {NODE_CONFIG_FILE} attachment (the nodes' settings)"
    try:
        return config_from_dict(json.loads(raw.decode("utf-8", "replace")))
    except (ValueError, TypeError, AttributeError) as err:  # not JSON, stale or foreign keys
        return f"the attached {NODE_CONFIG_FILE} is not a nodes' settings file ({err})"


def measured_requests(vd: VehicleData, t0: float, timeout_s: float) -> list[Any]:
    """The vehicle's requests as `MeasuredRequest`s, run times from `t0`; a lost request
    whose start is unknown took `timeout_s` (the run's request timeout).

    A request's own latency is its answer (the InferenceResult's stamp) minus its start (the
    SplitDecision of the same frame, published as the request starts), as the learner is
    charged; without a decision, the recorded answer - capture time (an upper bound)."""
    from nodes.edgeloc.latency import MeasuredRequest

    starts: dict[int, list[float]] = {}
    for d in vd.decisions:
        starts.setdefault(d.frame_id, []).append(d.t)
    out = []
    for i in vd.inference:
        if _stopped(i):
            continue
        began = [t for t in starts.get(i.frame_id, []) if t <= i.t]
        lost = not i.ok
        if began:
            start = max(began)
            own = i.t - start
        elif math.isfinite(i.latency_s):
            own = i.latency_s
            start = i.t - own
        elif lost:
            own = timeout_s
            start = i.t - own
        else:
            continue  # answered, but neither its start nor its latency is known
        out.append(MeasuredRequest(t_s=start - t0, split=i.split, latency_s=own, lost=lost))
    return out


def _stopped(i: Inference) -> bool:
    return not i.ok and not i.timed_out and i.error.startswith(STOPPED_ERROR)


def split_comparison(
    data: RunData, real_totals: Mapping[str, float | None] | None = None
) -> dict[str, Any]:
    """The learned run, every fixed split the run measured and the oracle, replayed on the
    run's drive under its measured latencies (module doc); `{"skipped": why}` when it cannot
    be done. `real_totals`: per vehicle, the recorded EdgeLoc total
    (`reports.sections.accuracy`'s per-vehicle figure), reported beside the replays."""
    config = run_config(data)
    if isinstance(config, str):
        return {"skipped": config}
    if config.dataset != "synthetic":
        return {
            "skipped": f"the run's dataset is a recorded folder ({config.dataset}), which the "
            "recording does not hold; only the synthetic drive can be regenerated"
        }
    vd = next((v for v in data.vehicles.values() if v.inference), None)
    if vd is None:
        return {"skipped": "no inference request was recorded (/<vehicle>/inference)"}
    requests = measured_requests(vd, data.t0, config.request_timeout_s)
    played = {r.split for r in requests}
    if not played & set(config.splits):
        return {"skipped": f"{vd.name}'s requests played none of the configured splits"}
    try:
        from nodes.edgeloc.answerstore import AnswerStore, answers_key
        from nodes.edgeloc.compare import answer_all, compare_splits
        from nodes.edgeloc.latency import MeasuredLatency
        from nodes.edgeloc.replay import InferenceCache, config_dataset, drive_of
        from nodes.edgeloc.train import load_model
    except ImportError as err:
        return {"skipped": f"the replay needs torch, which does not import here ({err})"}
    try:
        model = load_model(config.weights)
    except OSError as err:  # WeightsMissing: absent, truncated or foreign weights
        return {"skipped": f"the DNN weights do not load ({err})"}
    try:
        measured = MeasuredLatency(requests, config.phases, timeout_s=config.request_timeout_s)
        dataset = config_dataset(config)
        # The DNN's answers to this drive's frames at every split, computed once for the
        # drive and kept (`nodes.edgeloc.answerstore`): a later report of the same drive
        # reads them, whatever frames its run's latencies make the replays ask for.
        store = AnswerStore(answers_key(model, drive_of(config), config.codec))
        cache = InferenceCache(model, dataset, config.codec)
        cache.remember(store.load())
        if answer_all(cache, config.splits):
            store.save(cache.answers())
        # compare_splits leaves out (as skipped) the splits the run never timed
        comparison = compare_splits(config, measured, dataset, model, cache)
    except (ValueError, OSError) as err:
        return {"skipped": f"the replay of the run's drive failed ({err})"}
    return {
        **comparison.to_dict(),
        "vehicle": vd.name,
        "fusion": config.describe_fusion(),
        "requests": len(requests),
        "replayed_splits": list(comparison.fixed),
        "real_learned_total_m": (real_totals or {}).get(vd.name),
    }


__all__ = ["measured_requests", "run_config", "split_comparison"]
