"""Time: latency per split, EdgeLoc's accuracy against the age of its DNN answers, the
real-time deadlines of the fused poses, and the gaps in DNN answers (EdgeLoc on VO alone).

Its keys of summary.json:

- `latency`: {source ("inference" or null), per_split: {split: {requests, answers, timed_out,
  errors, latency_s {n, mean, median, p95, max}, mean_payload_bytes, mean_head_s,
  mean_edge_compute_s}}} from `/<vehicle>/inference`;
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
  while fused poses went on (EdgeLoc then runs on VO alone).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np
import yaml

from reports.document import Image, Para, Plot, Section, Table
from reports.mcapread import PoseTrack, RunData, VehicleData
from reports.sections.accuracy import FrameErrors
from reports.sections.fmt import cell, ms, not_recorded_note, rounded, series_stats
from reports.sections.learner import split_order
from reports.sections.run import topics_of

#: A DNN-answer gap is reported when longer than this, or 10x the median answer interval.
GAP_MIN_S = 1.0
GAP_MEDIAN_FACTOR = 10.0


def _mean(x: list[float]) -> float | None:
    a = [v for v in x if math.isfinite(v)]
    return float(np.mean(a)) if a else None


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
            "latency_s": series_stats(answered),
            "mean_payload_bytes": _mean([float(i.payload_bytes) for i in mine]),
            "mean_head_s": _mean([i.head_s for i in mine]),
            "mean_edge_compute_s": _mean([i.edge_compute_s for i in mine if i.ok]),
        }
    return {"source": "inference", "per_split": per}


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
            "delay_s": series_stats(delay.tolist()),
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
        if not len(answers) and not vd.inference and "dnn_answer" not in topics_of(data, v):
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
                    "start_s": rounded(a - t0),
                    "end_s": rounded(b - t0),
                    "duration_s": rounded(b - a),
                    "fused_poses": int(np.sum((poses > a) & (poses < b))),
                    "where": where,
                }
            )
        out[v] = {"threshold_s": threshold, "answers": len(answers), "gaps": gaps}
    return out


def latency_section(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Latency per split")
    lat = s["latency"]
    if lat["source"] is None:
        return sec.add(not_recorded_note("inference results", "/<vehicle>/inference"))
    rows = []
    for k, b in lat["per_split"].items():
        ls = b["latency_s"] or {}
        rows.append(
            [k, str(b["requests"]), str(b["answers"]), str(b["timed_out"]), str(b["errors"])]
            + [ms(ls.get(q)) for q in ("mean", "median", "p95", "max")]
            + [
                cell(b["mean_payload_bytes"], "{:.0f}"),
                ms(b["mean_head_s"]),
                ms(b["mean_edge_compute_s"]),
            ]
        )
    sec.add(
        Table(
            [
                "split",
                "requests",
                "answers",
                "timed out",
                "errors",
                "mean ms",
                "median ms",
                "p95 ms",
                "max ms",
                "payload B",
                "head ms",
                "edge ms",
            ],
            rows,
        )
    )
    if plots.get("latency_per_split"):
        sec.add(Image(plots["latency_per_split"]))  # type: ignore[arg-type]
    return sec


def accuracy_vs_latency_section(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Accuracy against latency")
    a = s["accuracy_vs_latency"]
    if not a or not a["bins"]:
        return sec.add(not_recorded_note("EdgeLoc poses with a DNN answer age"))
    sec.add(
        Para(
            f"{a['frames']} EdgeLoc frames with a DNN answer; Pearson r = {cell(a['pearson_r'])}."
        ),
        Table(
            ["answer age ms", "frames", "median error m", "mean error m"],
            [
                [
                    f"{b['latency_lo_s'] * 1e3:.1f}-{b['latency_hi_s'] * 1e3:.1f}",
                    str(b["frames"]),
                    cell(b["median_error_m"]),
                    cell(b["mean_error_m"]),
                ]
                for b in a["bins"]
            ],
            caption="quartiles of the answer age",
        ),
    )
    if plots.get("accuracy_vs_latency"):
        sec.add(Image(plots["accuracy_vs_latency"]))  # type: ignore[arg-type]
    return sec


def realtime_section(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Real-time deadlines")
    rt = s["realtime"]
    if not rt["vehicles"]:
        sec.add(not_recorded_note("fused poses with ground-truth frames"))
    else:
        sec.add(
            Para(
                "A frame misses its deadline when its fused pose was never published, or was "
                "published (its MCAP log time: the recorder writes on the publisher's side) "
                "more than one frame period after the frame's capture."
            ),
            Table(
                [
                    "vehicle",
                    "method",
                    "rate Hz",
                    "frames",
                    "poses",
                    "missing",
                    "late",
                    "miss %",
                    "median delay ms",
                    "p95 delay ms",
                    "max delay ms",
                    "longest interval ms",
                ],
                [
                    [
                        v,
                        r["method"],
                        cell(r["rate_hz"], "{:g}"),
                        str(r["frames_expected"]),
                        str(r["poses"]),
                        str(r["missing"]),
                        str(r["late"]),
                        cell(r["miss_pct"], "{:.2f}"),
                        ms((r["delay_s"] or {}).get("median")),
                        ms((r["delay_s"] or {}).get("p95")),
                        ms((r["delay_s"] or {}).get("max")),
                        ms(r["max_interval_s"]),
                    ]
                    for v, r in rt["vehicles"].items()
                ],
            ),
        )
    for proc, figures in rt["reported_by_nodes"].items():
        sec.add(
            Table(
                ["figure", "value"],
                [[k, cell(v, "{:g}")] for k, v in figures.items()],
                caption=f"reported by {proc}",
            )
        )
    if plots.get("realtime"):
        sec.add(Image(plots["realtime"]))  # type: ignore[arg-type]
    return sec


def gaps_section(s: dict[str, Any]) -> Section:
    sec = Section("Gaps in DNN answers")
    if not s["dnn_gaps"]:
        return sec.add(not_recorded_note("DNN answers", "/<vehicle>/dnn_answer"))
    for v, g in s["dnn_gaps"].items():
        if not g["gaps"]:
            sec.add(
                Para(f"{v}: {g['answers']} answers, no gap longer than {g['threshold_s']:.2f} s.")
            )
            continue
        sec.add(
            Table(
                ["where", "from s", "to s", "length s", "fused poses meanwhile"],
                [
                    [
                        x["where"],
                        cell(x["start_s"], "{:.2f}"),
                        cell(x["end_s"], "{:.2f}"),
                        cell(x["duration_s"], "{:.2f}"),
                        str(x["fused_poses"]),
                    ]
                    for x in g["gaps"]
                ],
                caption=(
                    f"{v}: {g['answers']} answers; spans over {g['threshold_s']:.2f} s without "
                    "one (EdgeLoc ran on VO alone meanwhile)"
                ),
            )
        )
    return sec
