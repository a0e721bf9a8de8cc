"""What a run's report says, computed from `RunData` alone: `summarize(data) -> dict`.

Pure computations (no files, no plotting). The same MCAP always gives the same dict, and
`summary_json` serialises it byte-identically (no report-time clock in it), so a rebuilt
report can be compared with the run's own. Keys of summary.json (`version` 1):

- `version`, `kind` ("run": a recorded ROS run; replays write "replay");
- `run`: the recorder's `edgeloc.run` metadata as recorded (run_id, scenario, seed,
  link_backend, status, started, ended, duration_s, software versions, host capabilities);
- `partial` (bool) and `recording`: {file, complete (footer read, no damage), problems [text],
  messages (per topic), schemas (per topic), decode_errors}. `partial` is true when the file
  was cut short or the run was interrupted: every figure then covers only what was recorded;
- `status`: the run's status ("ok", "failed: ...", "interrupted", or "unknown ...");
- `vehicles`: names, sorted;
- `t0_epoch_s`: the origin of every `*_s` run time below (first ground-truth stamp);
- `methods`: per method (vo, dnn, kalman, edgeloc, then others), pooled over vehicles:
  {frames, missing_frames (ground-truth frames without this method's pose), position_m,
  heading_deg}, each error block {n, total, mean, median, rmse, p95, max} (null without
  frames). Errors are per frame against ground truth on the same frame id;
- `per_vehicle`: {vehicle: {methods: same as above for that vehicle, requests, answers,
  latency_s {n, mean, median, p95, max} of its answered requests (null without any)}};
- `paper_comparison`: {totals: [{method, paper, ours}], reductions: [{versus, paper_pct,
  ours_pct}]}: the paper's four totals and EdgeLoc's three reductions beside ours;
- `headline`: one line of the above (what `testbed run` prints last);
- `latency`: {source ("inference" or null), per_split: {split: {requests, answers, timed_out,
  errors, latency_s {n, mean, median, p95, max}, mean_payload_bytes, mean_head_s,
  mean_edge_compute_s}}} from `/<vehicle>/inference`;
- `learner`: {decisions, split_share {split: fraction of decisions}, switches (decisions
  that changed split), rules {explore/ucb/fixed: count}, detector_updates, resets [{vehicle,
  t_s, arm, kl, at_play}], phases [{start_s, end_s, plays, share {split: fraction}, chosen
  (most played), best_in_hindsight (lowest mean latency among splits answered >= 2 times),
  mean_latency_s {split: s}, share_best, share_best_second_half}] — one phase per span
  between applied timeline events (an event scheduled at 0 s opens the first), all vehicles
  pooled};
- `accuracy_vs_latency`: EdgeLoc position error against the age of the newest DNN answer it
  used, per frame: {frames, pearson_r, bins [{latency_lo_s, latency_hi_s, frames,
  median_error_m, mean_error_m}]} (quartiles of the latency);
- `realtime`: per vehicle {rate_hz, rate_source, period_s, frames_expected, poses, missing,
  late (published more than one period after capture; MCAP log time is the publish time),
  misses, miss_pct,
  delay_s {median, p95, max}, max_interval_s (longest time between two fused poses)}, and
  `reported_by_nodes` (deadline/miss figures the fusion nodes' own stats carry);
- `dnn_gaps`: per vehicle {threshold_s, answers, gaps [{start_s, end_s, duration_s,
  fused_poses, where ("start", "middle", "end", "whole run")}]}: spans without DNN answers
  while fused poses went on (EdgeLoc then runs on VO alone);
- `links`: {backend, events [{t_s, scheduled_s, lateness_s, action, target, direction,
  changes}], rates [{link, direction, backend, samples, mean_mbit, max_mbit, bytes_out,
  packets_dropped}], caps {node: [{t_s, uplink_mbit, downlink_mbit}]} (Wondershaper-style
  caps set by `shape`, lifted by `clear`; null: none), outages [{link, start_s, end_s}],
  timeline (the recorder's `edgeloc.timeline`: events, applied, failed, lateness),
  linktest (the link self-test table, attachment linktest.json, or null),
  linktest_ran (the recorder's "true"/"false", null if not said)};
- `radio` (runs with `channel:`): {vehicles: {vehicle: {steps, coverage, cells {cell: share},
  handovers [{t_s, from, to, interruption_ms, lossless, lateness_ms, error (null: applied)}],
  handovers_source ("/handover": as applied; "/radio/<vehicle>": changes of the serving cell,
  whose interruption, lossless, lateness and error are null), sinr_db and ul_sinr_db {min, p5,
  median, p95, max}, mean_mcs, mean_ul_mcs, mean_bler, mean_ul_bler, capacity_mbps {ul, dl:
  {min, p5, median, p95, max}} (Mbit/s the serving cell's air link carried at each step's MCS
  and BLER, `radio_capacity`; null without links.json's radios, a run older than it),
  by_uplink_mcs [{mcs [lo, hi], time_share, plays, share {split: fraction},
  mean_payload_bytes}] (the learner's decisions by the uplink MCS at their time,
  `nodes.edgeloc.bands`; null without decisions),
  handover_window_s (W, `HANDOVER_WINDOW_S`), away_from_handovers {plays, top_split, top_share,
  mean_payload_bytes} (the plays outside every [t - W, t + W)), around_handovers [one per
  handover: its keys above, and before and after ([t - W, t) and [t, t + W)), as
  `nodes.edgeloc.bands.around` gives them for the replay: {plays (decided then), top_split
  (most played), top_share, mean_payload_bytes (each play at its split's mean payload per
  request on /<vehicle>/inference), mean_latency_s (the plays' answered requests), mean_error_m
  (EdgeLoc's fused position error of the frames captured then), mean_ul_mcs (over the /radio
  steps)}, plus timed_out (plays whose request timed out) and top_split_vs_away ("smaller",
  "larger" or "same" uplink payload per request than away_from_handovers' top split; null:
  not comparable); smaller_split_near (either window's top split smaller; null: neither
  comparable)]}}, channel (model, los, step_s, sites [{name, x, y}], handover (the
  `channel.handover` settings or null))} from `/radio/<vehicle>` and `/handover`; {} without
  /radio;
- `splits`: EdgeLoc with the learned split choice, every fixed split and the per-phase oracle,
  replayed on the run's drive under the run's own measured request latencies
  (`reports.splits`: the keys of `nodes.edgeloc.compare.SplitComparison.to_dict` plus
  vehicle, requests, replayed_splits, real_learned_total_m), or {skipped: why} when it cannot
  be (no nodes/config.json attachment, no torch or weights, a recorded dataset, no requests);
- `nodes`: the recorder's `edgeloc.nodes` metadata as recorded; `failures`: [{process,
  exit_code, namespace, last_log_lines}] for processes that exited non-zero or carry log
  lines of a failure;
- `not_recorded`: topics/records the report looked for and did not find (`/handover` only
  where `channel.handover` was set and a serving cell changed on /radio).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from netem.nr import Direction
from nodes.edgeloc import bands
from nodes.edgeloc.metrics import (
    METHODS,
    ErrorStats,
    heading_errors_deg,
    paper_comparison,
    position_errors,
)
from nodes.recording.layout import HANDOVER_TOPIC, radio_topic
from reports.mcapread import PoseTrack, RadioSeries, RunData, VehicleData
from reports.splits import split_comparison

SUMMARY_VERSION = 1
#: A DNN-answer gap is reported when longer than this, or 10x the median answer interval.
GAP_MIN_S = 1.0
GAP_MEDIAN_FACTOR = 10.0
PAPER_ORDER = ("vo", "dnn", "kalman", "edgeloc")


def _r(x: float | None, nd: int = 6) -> float | None:
    """Round run times for readability; NaN/inf become null (JSON has neither)."""
    if x is None or not math.isfinite(x):
        return None
    return round(float(x), nd)


def clean_json(obj: Any) -> Any:
    """A copy of `obj` that `json.dumps(allow_nan=False)` accepts: NaN/inf -> None, numpy
    scalars -> Python numbers, tuples -> lists."""
    if isinstance(obj, dict):
        return {str(k): clean_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [clean_json(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def summary_json(summary: dict[str, Any]) -> str:
    """The exact text of summary.json (stable key order, no NaN)."""
    return json.dumps(clean_json(summary), indent=2, allow_nan=False) + "\n"


# ---- errors per method ------------------------------------------------------------------------


@dataclass
class FrameErrors:
    """One method's per-frame errors of one vehicle, on the frames it shares with ground truth."""

    frame: NDArray[np.int64]
    t: NDArray[np.float64]  # ground-truth stamp, epoch seconds
    position_m: NDArray[np.float64]
    heading_deg: NDArray[np.float64]
    latency_s: NDArray[np.float64]
    missing: int  # ground-truth frames this method has no pose for


def frame_errors(vd: VehicleData, method: str) -> FrameErrors | None:
    gt, est = vd.gt, vd.tracks.get(method)
    if gt is None or est is None or not len(gt):
        return None
    common, gi, ei = np.intersect1d(gt.frame, est.frame, return_indices=True)
    # Frames after the method's last pose are not "missing" (the recording ended first).
    last = est.frame.max() if len(est) else -1
    missing = int(np.sum(~np.isin(gt.frame, est.frame) & (gt.frame <= last)))
    e, g = est.pose[ei], gt.pose[gi]
    finite = np.isfinite(e).all(axis=1) & np.isfinite(g).all(axis=1)
    return FrameErrors(
        frame=common[finite],
        t=gt.stamp[gi][finite],
        position_m=position_errors(e[finite], g[finite]),
        heading_deg=heading_errors_deg(e[finite], g[finite]),
        latency_s=est.latency_s[ei][finite],
        missing=missing + int(np.sum(~finite)),
    )


def _stats(x: NDArray[np.float64]) -> dict[str, Any] | None:
    return ErrorStats.of(x).to_dict() if len(x) else None


def _method_block(errs: list[FrameErrors]) -> dict[str, Any]:
    pos = np.concatenate([e.position_m for e in errs]) if errs else np.zeros(0)
    head = np.concatenate([e.heading_deg for e in errs]) if errs else np.zeros(0)
    return {
        "frames": len(pos),
        "missing_frames": sum(e.missing for e in errs),
        "position_m": _stats(pos),
        "heading_deg": _stats(head),
    }


def all_methods(data: RunData) -> list[str]:
    seen = {m for vd in data.vehicles.values() for m in vd.methods()}
    return [m for m in PAPER_ORDER if m in seen] + sorted(seen - set(PAPER_ORDER))


def method_errors(data: RunData) -> dict[str, dict[str, FrameErrors]]:
    """method -> vehicle -> FrameErrors (vehicles without ground truth are left out)."""
    out: dict[str, dict[str, FrameErrors]] = {}
    for m in all_methods(data):
        for v, vd in data.vehicles.items():
            fe = frame_errors(vd, m)
            if fe is not None:
                out.setdefault(m, {})[v] = fe
    return out


def edgeloc_vehicles(run: dict[str, Any]) -> int | None:
    """How many vehicles the run's scenario gave EdgeLoc's nodes (None: a recording from
    before `workload:` could be none, where every vehicle ran them)."""
    if "edgeloc_vehicles" not in run:
        return None
    return len([v for v in str(run["edgeloc_vehicles"]).split(",") if v])


def headline(
    comparison: dict[str, Any],
    run_id: str | None = None,
    partial: bool = False,
    vehicles: int | None = None,
) -> str:
    """`run X: EdgeLoc total error N m; reduction a% vs VO (paper 67.75%), ...`; for a run
    with no EdgeLoc vehicle (`vehicles=0`: `workload: none`), what it recorded instead."""
    head = f"run {run_id}: " if run_id else ""
    tail = " [partial]" if partial else ""
    if vehicles == 0:
        return f"{head}no EdgeLoc workload (workload: none): see its apps and traffic" + tail
    totals = {t["method"]: t["ours"] for t in comparison["totals"]}
    parts = []
    for r in comparison["reductions"]:
        ours = "n/a" if r["ours_pct"] is None else f"{r['ours_pct']:.2f}%"
        parts.append(f"{ours} vs {r['versus'].upper()} (paper {r['paper_pct']:.2f}%)")
    edge = totals.get("edgeloc")
    total = "n/a" if edge is None else f"{edge:.1f} m"
    return f"{head}EdgeLoc total error {total}; reduction " + ", ".join(parts) + tail


# ---- latency, learner, accuracy against latency ------------------------------------------------


def _series_stats(x: list[float]) -> dict[str, Any] | None:
    a = np.asarray([v for v in x if math.isfinite(v)], dtype=np.float64)
    if not len(a):
        return None
    return {
        "n": len(a),
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
        "max": float(a.max()),
    }


def _mean(x: list[float]) -> float | None:
    a = [v for v in x if math.isfinite(v)]
    return float(np.mean(a)) if a else None


def split_order(data: RunData) -> list[str]:
    """Split names in the model's order (from decisions' arm lists), then any others seen."""
    order: list[str] = []
    for vd in data.vehicles.values():
        for d in vd.decisions[:1]:
            order += [a for a in d.arm_names if a not in order]
        for i in sorted(vd.inference, key=lambda i: i.split_index):
            if i.split not in order:
                order.append(i.split)
        for d in vd.decisions:
            if d.chosen not in order:
                order.append(d.chosen)
    return order


def load_windows(run_json: dict[str, Any]) -> list[tuple[float, float]]:
    """When cross-traffic ran, as wall-clock intervals (merged): each `traffic:` flow from its
    start to its stop (or the end of the run), counted from the timeline's 0 s."""
    flows = run_json.get("traffic") or {}
    t0 = (run_json.get("timeline") or {}).get("started_epoch_s")
    if not flows or t0 is None:
        return []
    end = float(run_json.get("duration_s") or math.inf)
    spans = sorted(
        (t0 + float(f.get("start_s") or 0.0), t0 + float(f.get("stop_s") or end))
        for f in flows.values()
    )
    merged: list[tuple[float, float]] = []
    for a, b in spans:
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def load_comparison(data: RunData, windows: list[tuple[float, float]]) -> dict[str, Any] | None:
    """Per vehicle, EdgeLoc with the cross-traffic on (`windows`) and off: requests, answers,
    request latency and mean fused position error. None without windows or EdgeLoc data."""
    if not windows or not data.vehicles:
        return None
    starts = np.array([a for a, _ in windows])
    ends = np.array([b for _, b in windows])

    def loaded(t: NDArray[np.float64]) -> NDArray[np.bool_]:
        t = np.asarray(t, dtype=np.float64)[:, None]
        return np.any((t >= starts) & (t < ends), axis=1)

    errors = method_errors(data).get("edgeloc", {})
    out: dict[str, Any] = {}
    for v, vd in data.vehicles.items():
        req_t = np.array([i.t for i in vd.inference], dtype=np.float64)
        req_on = loaded(req_t) if len(req_t) else np.zeros(0, dtype=bool)
        fe = errors.get(v)
        err_on = loaded(fe.t) if fe is not None and len(fe.t) else None
        rows: dict[str, Any] = {}
        for label, want in (("with_load", True), ("without_load", False)):
            reqs = [i for i, on in zip(vd.inference, req_on, strict=True) if on == want]
            answered = [i.latency_s for i in reqs if i.ok and math.isfinite(i.latency_s)]
            err = None
            if fe is not None and err_on is not None and np.any(err_on == want):
                err = float(np.mean(fe.position_m[err_on == want]))
            rows[label] = {
                "requests": len(reqs),
                "answers": len(answered),
                "latency_s": _series_stats(answered),
                "edgeloc_error_m": err,
            }
        out[v] = rows
    return {"windows": [[a, b] for a, b in windows], "per_vehicle": out}


def latency_summary(data: RunData) -> dict[str, Any]:
    reqs = [i for vd in data.vehicles.values() for i in vd.inference]
    if not reqs:
        return {"source": None, "per_split": {}}
    per: dict[str, Any] = {}
    for split in split_order(data):
        mine = [i for i in reqs if i.split == split]
        if not mine:
            continue
        answered = [i.latency_s for i in mine if i.ok]
        per[split] = {
            "requests": len(mine),
            "answers": len(answered),
            "timed_out": sum(i.timed_out for i in mine),
            "errors": sum(bool(i.error) for i in mine),
            "latency_s": _series_stats(answered),
            "mean_payload_bytes": _mean([float(i.payload_bytes) for i in mine]),
            "mean_head_s": _mean([i.head_s for i in mine]),
            "mean_edge_compute_s": _mean([i.edge_compute_s for i in mine if i.ok]),
        }
    return {"source": "inference", "per_split": per}


def learner_summary(data: RunData) -> dict[str, Any]:
    t0 = data.t0
    decisions = [d for vd in data.vehicles.values() for d in vd.decisions]
    share = Counter(d.chosen for d in decisions)
    switches = 0
    for vd in data.vehicles.values():
        switches += sum(a.chosen != b.chosen for a, b in itertools.pairwise(vd.decisions))
    resets = [
        {"vehicle": v, "t_s": _r(u.t - t0), "arm": u.arm, "kl": u.kl, "at_play": u.at_play}
        for v, vd in data.vehicles.items()
        for u in vd.detector
        if u.reset
    ]
    return {
        "decisions": len(decisions),
        "split_share": {
            s: share[s] / len(decisions) for s in split_order(data) if decisions and share[s]
        },
        "switches": switches,
        "rules": dict(sorted(Counter(d.rule for d in decisions).items())),
        "detector_updates": sum(len(vd.detector) for vd in data.vehicles.values()),
        "resets": resets,
        "phases": learner_phases(data),
    }


def learner_phases(data: RunData) -> list[dict[str, Any]]:
    """Per network phase (the spans between applied timeline events), all vehicles pooled:
    what the learner chose, and which split was fastest in hindsight (lowest mean measured
    latency among splits answered at least twice in the phase)."""
    t0 = data.t0
    decisions = sorted((d.t - t0, d.chosen) for vd in data.vehicles.values() for d in vd.decisions)
    answers = [
        (i.t - t0, i.split, i.latency_s)
        for vd in data.vehicles.values()
        for i in vd.inference
        if i.ok and math.isfinite(i.latency_s)
    ]
    if not decisions:
        return []
    end = max([decisions[-1][0], *(a[0] for a in answers)])
    # An event scheduled at 0 s sets the network the run starts on: it is applied while the
    # nodes come up, so the first decisions can precede it by a fraction of a second, and
    # cutting there would report a phase of one or two plays.
    cuts = sorted(
        {
            e.t - t0
            for e in data.link_events
            if e.scheduled_s > 0 and 0.0 < e.t - t0 < end and e.action != "channel"
        }
    )
    bounds = [min(0.0, decisions[0][0]), *cuts, end]
    out = []
    for k, (a, b) in enumerate(itertools.pairwise(bounds)):
        last = k == len(bounds) - 2
        inside = [c for t, c in decisions if a <= t < b or (last and t == b)]
        lat: dict[str, list[float]] = {}
        for t, split, latency in answers:
            if a <= t < b or (last and t == b):
                lat.setdefault(split, []).append(latency)
        means = {sp: float(np.mean(v)) for sp, v in lat.items() if len(v) >= 2}
        best = min(means, key=lambda sp: (means[sp], sp)) if means else None
        counts = Counter(inside)
        half = inside[len(inside) // 2 :]
        out.append(
            {
                "start_s": _r(a),
                "end_s": _r(b),
                "plays": len(inside),
                "share": {sp: counts[sp] / len(inside) for sp in split_order(data) if counts[sp]},
                "chosen": min(counts, key=lambda sp: (-counts[sp], sp)) if inside else None,
                "best_in_hindsight": best,
                "mean_latency_s": {sp: means[sp] for sp in split_order(data) if sp in means},
                "share_best": counts[best] / len(inside) if best and inside else None,
                "share_best_second_half": (
                    sum(c == best for c in half) / len(half) if best and half else None
                ),
            }
        )
    return out


def accuracy_vs_latency(errs: dict[str, FrameErrors] | None) -> dict[str, Any] | None:
    """EdgeLoc error against the age of the DNN answer it used, pooled over vehicles."""
    if not errs:
        return None
    lat = np.concatenate([e.latency_s for e in errs.values()])
    err = np.concatenate([e.position_m for e in errs.values()])
    ok = np.isfinite(lat)
    lat, err = lat[ok], err[ok]
    if len(lat) < 2:
        return {"frames": len(lat), "pearson_r": None, "bins": []}
    r = None
    if np.std(lat) > 0 and np.std(err) > 0:
        r = float(np.corrcoef(lat, err)[0, 1])
    edges = np.unique(np.percentile(lat, [0, 25, 50, 75, 100]))
    if len(edges) == 1:
        edges = np.array([edges[0], edges[0]])  # every frame had the same age: one bin
    bins = []
    for i, (lo, hi) in enumerate(itertools.pairwise(edges)):
        last = i == len(edges) - 2
        sel = (lat >= lo) & ((lat <= hi) if last else (lat < hi))
        if sel.any():
            bins.append(
                {
                    "latency_lo_s": float(lo),
                    "latency_hi_s": float(hi),
                    "frames": int(sel.sum()),
                    "median_error_m": float(np.median(err[sel])),
                    "mean_error_m": float(np.mean(err[sel])),
                }
            )
    return {"frames": len(lat), "pearson_r": r, "bins": bins}


# ---- real time, DNN gaps -------------------------------------------------------------------------


def scenario_rate_hz(data: RunData) -> float | None:
    """workload.rate_hz of the scenario attached to the recording (None if not there)."""
    raw = data.attachments.get("scenario.yaml")
    if raw is None:
        return None
    try:
        doc = yaml.safe_load(raw.decode("utf-8", "replace"))
        value = doc.get("workload", {}).get("rate_hz", 20.0)  # the schema's default
        text = str(value).strip().lower().removesuffix("hz").strip()
        rate = float(text)
    except (yaml.YAMLError, AttributeError, ValueError):
        return None
    return rate if rate > 0 else None


def fused_method(vd: VehicleData) -> str | None:
    """The real-time thread's output track: EdgeLoc's, else the first method published."""
    methods = vd.methods()
    return "edgeloc" if "edgeloc" in methods else (methods[0] if methods else None)


def realtime_summary(data: RunData) -> dict[str, Any]:
    out: dict[str, Any] = {}
    scen_rate = scenario_rate_hz(data)
    for v, vd in data.vehicles.items():
        m = fused_method(vd)
        ref = vd.tracks.get("gt") or vd.tracks.get("vo_raw")
        if m is None or ref is None or len(ref) < 2:
            continue
        track = vd.tracks[m]
        rate, source = scen_rate, "scenario"
        if rate is None:
            rate, source = 1.0 / float(np.median(np.diff(ref.stamp))), "ground-truth stamps"
        period = 1.0 / rate
        last = track.frame.max() if len(track) else -1
        expected = ref.frame[ref.frame <= last]
        have = np.isin(expected, track.frame)
        delay = track.log_time - track.stamp
        late = int(np.sum(delay > period))
        missing = int(np.sum(~have))
        gaps = np.diff(track.log_time) if len(track) > 1 else np.zeros(0)
        out[v] = {
            "method": m,
            "rate_hz": rate,
            "rate_source": source,
            "period_s": period,
            "frames_expected": len(expected),
            "poses": len(track),
            "missing": missing,
            "late": late,
            "misses": missing + late,
            "miss_pct": 100.0 * (missing + late) / len(expected) if len(expected) else None,
            "delay_s": _series_stats(delay.tolist()),
            "max_interval_s": float(gaps.max()) if len(gaps) else None,
        }
    reported = {}
    for proc, info in (data.nodes or {}).items():
        stats = info.get("stats") if isinstance(info, dict) else None
        if isinstance(stats, dict):
            picked = {k: v for k, v in stats.items() if "deadline" in k or "miss" in k}
            if picked:
                reported[proc] = picked
    return {"vehicles": out, "reported_by_nodes": reported}


def dnn_gaps(data: RunData) -> dict[str, Any]:
    """Spans without DNN answers while the vehicle kept publishing fused poses."""
    t0 = data.t0
    out: dict[str, Any] = {}
    for v, vd in data.vehicles.items():
        m = fused_method(vd)
        if m is None or not len(vd.tracks[m]):
            continue
        poses = vd.tracks[m].log_time
        answers_track: PoseTrack | None = vd.tracks.get("dnn_answer")
        if answers_track is not None:
            answers = np.sort(answers_track.log_time)
        else:
            answers = np.sort([i.log_time for i in vd.inference if i.ok])
        if not len(answers) and not vd.inference and "dnn_answer" not in _topics_of(data, v):
            continue  # no way to tell: neither answers nor requests were recorded
        start, end = float(poses.min()), float(poses.max())
        inside = answers[(answers >= start) & (answers <= end)]
        threshold = GAP_MIN_S
        if len(inside) > 2:
            threshold = max(GAP_MIN_S, GAP_MEDIAN_FACTOR * float(np.median(np.diff(inside))))
        marks = [start, *inside.tolist(), end]
        gaps = []
        for i, (a, b) in enumerate(itertools.pairwise(marks)):
            if b - a <= threshold:
                continue
            if not len(inside):
                where = "whole run"
            elif i == 0:
                where = "start"
            elif i == len(marks) - 2:
                where = "end"
            else:
                where = "middle"
            gaps.append(
                {
                    "start_s": _r(a - t0),
                    "end_s": _r(b - t0),
                    "duration_s": _r(b - a),
                    "fused_poses": int(np.sum((poses > a) & (poses < b))),
                    "where": where,
                }
            )
        out[v] = {"threshold_s": threshold, "answers": len(answers), "gaps": gaps}
    return out


def _topics_of(data: RunData, vehicle: str) -> set[str]:
    prefix = f"/{vehicle}/"
    return {t[len(prefix) :] for t in data.topics if t.startswith(prefix)}


# ---- links, nodes --------------------------------------------------------------------------------


#: A rate in a timeline event's text, as `testbed.timeline.describe` writes it for `shape`.
_CAP_RE = re.compile(r"\b(uplink|downlink)\s+([0-9.]+(?:e[+-]?\d+)?)\s*([kMG]?)bit/s")
_OUTAGE_RE = re.compile(r"\bfor\s+([0-9.]+(?:e[+-]?\d+)?)\s*s\b")
_SCALE = {"": 1e-6, "k": 1e-3, "M": 1.0, "G": 1e3}


def link_changes(data: RunData) -> dict[str, Any]:
    """Wondershaper-style caps per node over time (from `shape`/`clear` events) and outage
    spans per link (from `outage` events), read from the events' recorded text."""
    t0 = data.t0
    caps: dict[str, list[dict[str, Any]]] = {}
    outages = []
    for e in data.link_events:
        text = " ".join(v for _, v in e.changes)
        if e.action == "shape":
            cap: dict[str, Any] = {"t_s": _r(e.t - t0), "uplink_mbit": None, "downlink_mbit": None}
            prev = caps.get(e.target, [])
            if prev:  # a shape event sets the directions it names and keeps the other
                cap.update({k: prev[-1][k] for k in ("uplink_mbit", "downlink_mbit")})
            for d, num, unit in _CAP_RE.findall(text):
                cap[f"{d}_mbit"] = float(num) * _SCALE[unit]
            caps.setdefault(e.target, []).append(cap)
        elif e.action == "clear":
            caps.setdefault(e.target, []).append(
                {"t_s": _r(e.t - t0), "uplink_mbit": None, "downlink_mbit": None}
            )
        elif e.action == "outage":
            m = _OUTAGE_RE.search(text)
            if m:
                start = e.t - t0
                outages.append(
                    {"link": e.target, "start_s": _r(start), "end_s": _r(start + float(m[1]))}
                )
    return {"caps": caps, "outages": outages}


def links_summary(data: RunData) -> dict[str, Any]:
    t0 = data.t0
    rates = []
    for c in data.counters:
        _, r = c.rate_mbit()
        rates.append(
            {
                "link": c.link,
                "direction": c.direction,
                "backend": c.backend,
                "samples": len(c.t),
                "mean_mbit": float(r.mean()) if len(r) else None,
                "max_mbit": float(r.max()) if len(r) else None,
                "bytes_out": float(c.bytes_out[-1] - c.bytes_out[0]) if len(c.t) else None,
                "packets_dropped": (
                    float(c.packets_dropped[-1] - c.packets_dropped[0]) if len(c.t) else None
                ),
            }
        )
    return {
        "backend": data.run.get("link_backend"),
        "events": [
            {
                "t_s": _r(e.t - t0),
                "scheduled_s": e.scheduled_s,
                "lateness_s": e.lateness_s,
                "action": e.action,
                "target": e.target,
                "direction": e.direction,
                "changes": {k: v for k, v in e.changes},
            }
            for e in data.link_events
        ],
        "rates": rates,
        **link_changes(data),
        "timeline": data.timeline,
        "linktest": data.linktest,
        "linktest_ran": data.linktest_meta.get("ran"),
    }


def _spread(x: NDArray[np.float64]) -> dict[str, float | None]:
    """min, p5, median, p95, max: a cell edge shows in the low end."""
    a = x[np.isfinite(x)]
    keys = ("min", "p5", "median", "p95", "max")
    if not len(a):
        return dict.fromkeys(keys)
    values = np.percentile(a, [0, 5, 50, 95, 100])
    return {k: _r(float(v), 3) for k, v in zip(keys, values, strict=True)}


def _payload_by_split(vd: VehicleData) -> dict[str, float]:
    """Mean uplink bytes per request of each split the vehicle sent (/<vehicle>/inference).
    This, not the split order, says which split is smaller: the raw image weighs less than
    the first layers' activations (`nodes.edgeloc.model`)."""
    sent: dict[str, list[int]] = {}
    for i in vd.inference:
        sent.setdefault(i.split, []).append(i.payload_bytes)
    return {s: sum(b) / len(b) for s, b in sent.items() if b}


def _plays_by_uplink_mcs(data: RunData, vehicle: str) -> list[dict[str, Any]] | None:
    """The vehicle's split decisions by the uplink MCS at their time (`nodes.edgeloc.bands`);
    None when it made none (no EdgeLoc on it)."""
    vd, r = data.vehicles.get(vehicle), data.radio[vehicle]
    if vd is None or not vd.decisions:
        return None
    at = np.searchsorted(r.t, [d.t for d in vd.decisions], side="right") - 1
    mcs = [int(r.ul_mcs[max(0, i)]) for i in at]
    rows = bands.by_band(
        mcs,
        [d.chosen for d in vd.decisions],
        _payload_by_split(vd),
        bands.time_shares(r.ul_mcs.astype(int)),
    )
    return [{**row, "share": {k: _r(v) for k, v in row["share"].items()}} for row in rows]


#: The span each side of a handover over which the report says what EdgeLoc did: [t - W, t)
#: before it and [t, t + W) after. The replay's (`nodes.edgeloc.bands.AROUND_S`, 3 s: a few
#: learner windows, and the distance over which the cell edge's SINR falls at urban speeds),
#: so a run's report and its scenario's replay describe the same windows.
HANDOVER_WINDOW_S = bands.AROUND_S


def _handovers(data: RunData, r: RadioSeries) -> tuple[str, list[tuple[float, dict[str, Any]]]]:
    """The vehicle's handovers as (wall-clock time, summary row), and where they come from:
    `/handover` when the recording holds it (what the timeline applied, with its
    interruption), else the changes of the serving cell on `/radio/<vehicle>`."""
    t0 = data.t0
    if data.handovers:
        return HANDOVER_TOPIC, [
            (
                h.t,
                {
                    "t_s": _r(h.t - t0),
                    "from": h.source,
                    "to": h.target,
                    "interruption_ms": _r(h.interruption_s * 1e3, 3),
                    "lossless": h.lossless,
                    "lateness_ms": _r(h.lateness_s * 1e3, 3),
                    "error": h.error or None,
                },
            )
            for h in data.handovers
            if h.vehicle == r.vehicle
        ]
    unknown = dict.fromkeys(("interruption_ms", "lossless", "lateness_ms", "error"))
    return radio_topic(r.vehicle), [
        (
            float(r.t[i]),
            {"t_s": _r(float(r.t[i]) - t0), "from": r.cell[i - 1], "to": r.cell[i], **unknown},
        )
        for i in range(1, len(r))
        if r.cell[i] != r.cell[i - 1]
    ]


def _away(chosen: list[str], payload: Mapping[str, float]) -> dict[str, Any]:
    """The plays away from every handover: how many, the most played split (ties: the first
    played, as `nodes.edgeloc.bands.around`) and its share, and their mean payload."""
    top = Counter(chosen).most_common(1)
    sent = [payload[c] for c in chosen if c in payload]
    return {
        "plays": len(chosen),
        "top_split": top[0][0] if top else None,
        "top_share": top[0][1] / len(chosen) if top else None,
        "mean_payload_bytes": float(np.mean(sent)) if sent else None,
    }


def _size_vs(split: str | None, ref: str | None, payload: Mapping[str, float]) -> str | None:
    """Whether `split` sends less uplink payload per request than `ref` ("smaller"), more
    ("larger") or as much ("same"); None when either is missing or has no recorded payload."""
    if split is None or ref is None:
        return None
    if split == ref:
        return "same"
    if split not in payload or ref not in payload:
        return None
    a, b = payload[split], payload[ref]
    return "smaller" if a < b else "larger" if a > b else "same"


def _around_handovers(
    data: RunData,
    r: RadioSeries,
    handovers: list[tuple[float, dict[str, Any]]],
    fe: FrameErrors | None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The plays away from every handover, and per handover what the learner, EdgeLoc and
    the uplink did in the `HANDOVER_WINDOW_S` before and after it (`bands.around`, as the
    replay: plays at their decision, each with its request's latency; frames at their
    capture), plus the plays whose request timed out and how each window's top split compares
    with the top split away from handovers, which the learner plays where no cell edge is
    near. A vehicle without EdgeLoc gets the radio's figures and no plays."""
    w = HANDOVER_WINDOW_S
    vd = data.vehicles.get(r.vehicle) or VehicleData(r.vehicle)
    payload = _payload_by_split(vd)
    result = {i.frame_id: i for i in vd.inference}  # a play's request, by its frame
    sent = [d.t for d in vd.decisions]
    outcome = [result.get(d.frame_id) for d in vd.decisions]
    series = bands.Series(
        sent_s=sent,
        splits=[d.chosen for d in vd.decisions],
        latency_s=[i.latency_s if i is not None and i.ok else math.nan for i in outcome],
        payload_bytes=payload,
        frame_t=fe.t.tolist() if fe is not None else [],
        frame_error_m=fe.position_m.tolist() if fe is not None else [],
        mcs_t=r.t.tolist(),
        ul_mcs=r.ul_mcs.tolist(),
    )
    times = [t for t, _ in handovers]
    far = [d.chosen for d in vd.decisions if all(not t - w <= d.t < t + w for t in times)]
    away = _away(far, payload)
    rows = []
    for t, row in handovers:
        windows = bands.around(t, series, window_s=w)
        for side, (a, b) in (("before", (t - w, t)), ("after", (t, t + w))):
            x = windows[side]
            x["timed_out"] = sum(
                a <= s < b and i is not None and i.timed_out
                for s, i in zip(sent, outcome, strict=True)
            )
            x["top_split_vs_away"] = _size_vs(x["top_split"], away["top_split"], payload)
        compared = [x["top_split_vs_away"] for x in windows.values() if x["top_split_vs_away"]]
        rows.append(
            {**row, **windows, "smaller_split_near": "smaller" in compared if compared else None}
        )
    return away, rows


def radio_capacity(data: RunData, r: RadioSeries) -> dict[str, NDArray[np.float64]] | None:
    """Per channel step, the Mbit/s the serving cell's air link carried, uplink (`ul`) and
    downlink (`dl`): `Radio.goodput_bps` of the link's radio (`<vehicle>-<cell>`, as
    links.json's starting profiles give it) at the step's MCS and BLER (`ul_mcs`/`ul_bler`
    up, `mcs`/`bler` down), which is what the channel set on that link then. The MCS alone
    hides what it is worth: the same MCS carries more on a wider carrier or a TDD pattern
    with more slots of that direction. NaN at a step whose link has no radio in links.json
    or whose MCS is no MCS; None when no step has a capacity (no links.json: an older run)."""
    if not data.link_radios or not len(r):
        return None
    # `goodput_bps` is the MCS's block rate times (1 - bler): the rate is looked up once per
    # link, direction and MCS, not once per step (every step's BLER is its own).
    rates: dict[tuple[str, Direction, int], float] = {}

    def mbps(cell: str, direction: Direction, mcs: float, bler: float) -> float:
        radio = data.link_radios.get((f"{r.vehicle}-{cell}", direction))
        if radio is None or not (math.isfinite(mcs) and 0.0 <= bler < 1.0):
            return math.nan
        key = (cell, direction, int(mcs))
        if key not in rates:
            try:
                rates[key] = dataclasses.replace(radio, mcs=int(mcs)).rate_bps(direction) / 1e6
            except ValueError:  # NrError: an MCS outside TS 38.214's table
                rates[key] = math.nan
        return rates[key] * (1.0 - bler)

    out = {
        key: np.array(
            [mbps(c, direction, m, b) for c, m, b in zip(r.cell, mcs, bler, strict=True)],
            dtype=np.float64,
        )
        for key, direction, mcs, bler in (
            ("ul", "uplink", r.ul_mcs, r.ul_bler),
            ("dl", "downlink", r.mcs, r.bler),
        )
    }
    return out if any(np.isfinite(x).any() for x in out.values()) else None


def radio_summary(data: RunData, edgeloc: Mapping[str, FrameErrors]) -> dict[str, Any]:
    """Per vehicle of a `channel:` run, from `/radio/<vehicle>` and `/handover`: steps,
    coverage (share of steps at downlink CQI >= 1), the serving cells' shares, handovers,
    SINR, MCS and capacity figures of both directions, and what EdgeLoc (its fused errors
    `edgeloc`, by vehicle) and its learner did around each handover; `sites` as the
    recorder's `edgeloc.run` metadata gives them. {} without /radio."""
    if not data.radio:
        return {}
    out: dict[str, Any] = {}
    for v, r in data.radio.items():
        if not len(r):
            continue
        cells = Counter(r.cell)
        source, handovers = _handovers(data, r)
        away, around = _around_handovers(data, r, handovers, edgeloc.get(v))
        capacity = radio_capacity(data, r)
        out[v] = {
            "steps": len(r),
            "coverage": _r(float(np.mean(r.cqi >= 1))),
            "cells": {c: _r(n / len(r)) for c, n in sorted(cells.items())},
            "handovers": [row for _, row in handovers],
            "handovers_source": source,
            "sinr_db": _spread(r.sinr_db),
            "ul_sinr_db": _spread(r.ul_sinr_db),
            "mean_mcs": _r(float(np.mean(r.mcs))),
            "mean_ul_mcs": _r(float(np.mean(r.ul_mcs))),
            "mean_bler": _r(float(np.mean(r.bler))),
            "mean_ul_bler": _r(float(np.mean(r.ul_bler))),
            "capacity_mbps": (
                {k: _spread(x) for k, x in capacity.items()} if capacity is not None else None
            ),
            "by_uplink_mcs": _plays_by_uplink_mcs(data, v),
            "handover_window_s": HANDOVER_WINDOW_S,
            "away_from_handovers": away,
            "around_handovers": around,
        }
    channel = data.run.get("channel")
    return {"vehicles": out, "channel": channel if isinstance(channel, dict) else None}


def handovers_unrecorded(data: RunData) -> bool:
    """The scenario set `channel.handover` and a vehicle's serving cell changed, yet the
    recording holds no `/handover`: its handovers are known only from /radio's cells."""
    channel = data.run.get("channel")
    if not isinstance(channel, dict) or not channel.get("handover") or data.handovers:
        return False
    return any(r.cell[i] != r.cell[i - 1] for r in data.radio.values() for i in range(1, len(r)))


#: Keys under which the recorder may put a process's last log lines.
LOG_KEYS = ("last_log_lines", "log_tail", "last_log", "log_lines")


def last_log_lines(info: dict[str, Any]) -> list[str]:
    for k in LOG_KEYS:
        v = info.get(k)
        if isinstance(v, str):
            return v.splitlines()
        if isinstance(v, list):
            return [str(x) for x in v]
    return []


def exit_code_of(info: dict[str, Any]) -> int | None:
    for k in ("exit_code", "exit", "returncode"):
        v = info.get(k)
        if isinstance(v, int) and not isinstance(v, bool):
            return v
    return None


def failures(data: RunData) -> list[dict[str, Any]]:
    out = []
    for proc, info in sorted((data.nodes or {}).items()):
        if not isinstance(info, dict):
            continue
        code, lines = exit_code_of(info), last_log_lines(info)
        if (code is not None and code != 0) or lines:
            out.append(
                {
                    "process": proc,
                    "namespace": info.get("namespace"),
                    "exit_code": code,
                    "last_log_lines": lines,
                }
            )
    return out


def not_recorded(data: RunData) -> list[str]:
    missing = []
    if not data.run:
        missing.append("metadata edgeloc.run")
    if not data.nodes:
        missing.append("metadata edgeloc.nodes")
    if not data.linktest:
        ran = str(data.linktest_meta.get("ran", "")).lower()
        why = "it did not run (report.link_test off)" if ran == "false" else "no linktest.json"
        missing.append(f"link self-test table: {why}")
    if not data.vehicles:
        missing.append("any vehicle topic (/<vehicle>/gt, /pose, ...)")
    for v in data.vehicles:
        have = _topics_of(data, v)
        missing += [f"/{v}/{t}" for t in VEHICLE_TOPICS_REQUIRED if t not in have]
    if not data.link_events:
        missing.append("/links/events")
    if not data.counters:
        missing.append("/links/counters")
    if handovers_unrecorded(data):
        missing.append(HANDOVER_TOPIC)
    return missing


VEHICLE_TOPICS_REQUIRED = ("gt", "pose", "dnn_answer", "split_decision", "detector", "inference")


# ---- the whole summary ------------------------------------------------------------------------


def summarize(data: RunData, splits: bool | str = True) -> dict[str, Any]:
    """The summary.json dict of a run (keys in the module docstring). `splits=False` leaves
    out the split comparison (its replays take seconds to a minute)."""
    errs = method_errors(data)
    methods = {m: _method_block(list(errs.get(m, {}).values())) for m in all_methods(data)}
    per_vehicle = {
        v: {
            "methods": {m: _method_block([errs[m][v]]) for m in errs if v in errs[m]},
            "requests": len(vd.inference),
            "answers": sum(i.ok for i in vd.inference),
            "latency_s": _series_stats([i.latency_s for i in vd.inference if i.ok]),
        }
        for v, vd in data.vehicles.items()
    }
    totals = {
        m: methods[m]["position_m"]["total"]
        for m in METHODS
        if m in methods and methods[m]["position_m"] is not None
    }
    comparison = paper_comparison(totals).to_dict()
    run_id = data.run.get("run_id")
    why = splits if isinstance(splits, str) else "not computed (the report was built without it)"
    split_block: dict[str, Any] = {"skipped": why}
    if splits is True:
        edgeloc = {v: pv["methods"].get("edgeloc") for v, pv in per_vehicle.items()}
        real = {v: (b["position_m"] or {}).get("total") for v, b in edgeloc.items() if b}
        split_block = split_comparison(data, real)
    return clean_json(
        {
            "version": SUMMARY_VERSION,
            "kind": "run",
            "run": data.run,
            "status": data.status,
            "partial": data.partial,
            "recording": {
                "file": data.path.name,
                "complete": data.complete,
                "problems": data.problems,
                "messages": data.topics,
                "schemas": data.schemas,
                "decode_errors": data.decode_errors,
            },
            "vehicles": list(data.vehicles),
            "t0_epoch_s": data.t0,
            "methods": methods,
            "per_vehicle": per_vehicle,
            "paper_comparison": comparison,
            "headline": headline(
                comparison,
                None if run_id is None else str(run_id),
                data.partial,
                edgeloc_vehicles(data.run),
            ),
            "latency": latency_summary(data),
            "learner": learner_summary(data),
            "accuracy_vs_latency": accuracy_vs_latency(errs.get("edgeloc")),
            "realtime": realtime_summary(data),
            "dnn_gaps": dnn_gaps(data),
            "links": links_summary(data),
            "radio": radio_summary(data, errs.get("edgeloc", {})),
            "splits": split_block,
            "nodes": data.nodes,
            "failures": failures(data),
            "not_recorded": not_recorded(data),
        }
    )


__all__ = [
    "HANDOVER_WINDOW_S",
    "SUMMARY_VERSION",
    "FrameErrors",
    "clean_json",
    "frame_errors",
    "headline",
    "method_errors",
    "summarize",
    "summary_json",
]
