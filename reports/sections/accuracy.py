"""Accuracy per method, against the paper, and the trajectories: each method's errors per
frame against ground truth on the same frame id (no alignment), and the paper's totals and
reductions beside ours, which make the headline `testbed run` prints last.

Its keys of summary.json:

- `methods`: per method (vo, dnn, kalman, edgeloc, then others), pooled over vehicles:
  {frames, missing_frames (ground-truth frames without this method's pose), position_m,
  heading_deg}, each error block {n, total, mean, median, rmse, p95, max} (null without
  frames). Errors are per frame against ground truth on the same frame id;
- `per_vehicle`: {vehicle: {methods: same as above for that vehicle, requests, answers,
  latency_s {n, mean, median, p95, max} of its answered requests (null without any)}};
- `paper_comparison`: {totals: [{method, paper, ours}], reductions: [{versus, paper_pct,
  ours_pct}]}: the paper's four totals and EdgeLoc's three reductions beside ours;
- `headline`: one line of the above (what `testbed run` prints last).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from nodes.edgeloc.metrics import (
    METHODS,
    ErrorStats,
    heading_errors_deg,
    paper_comparison,
    position_errors,
)
from reports.document import Image, Para, Plot, Section, Table
from reports.mcapread import RunData, VehicleData
from reports.sections.fmt import cell, not_recorded_note, series_stats

PAPER_ORDER = ("vo", "dnn", "kalman", "edgeloc")


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


def accuracy_summary(data: RunData, errs: dict[str, dict[str, FrameErrors]]) -> dict[str, Any]:
    """summary.json's `methods`, `per_vehicle` and `paper_comparison`, from the errors per
    method (`method_errors`)."""
    methods = {m: _method_block(list(errs.get(m, {}).values())) for m in all_methods(data)}
    per_vehicle = {
        v: {
            "methods": {m: _method_block([errs[m][v]]) for m in errs if v in errs[m]},
            "requests": len(vd.inference),
            "answers": sum(i.ok for i in vd.inference),
            "latency_s": series_stats([i.latency_s for i in vd.inference if i.ok]),
        }
        for v, vd in data.vehicles.items()
    }
    totals = {
        m: methods[m]["position_m"]["total"]
        for m in METHODS
        if m in methods and methods[m]["position_m"] is not None
    }
    comparison = paper_comparison(totals).to_dict()
    return {"methods": methods, "per_vehicle": per_vehicle, "paper_comparison": comparison}


def headline(
    comparison: dict[str, Any],
    run_id: str | None = None,
    partial: bool = False,
    vehicles: int | None = None,
    air: str | None = None,
) -> str:
    """`run X: EdgeLoc total error N m; reduction a% vs VO (paper 67.75%), ...`, then what the
    air link was (`air`: `NR DDDSUDDSUU 273 PRB, SR uplink`, or none for a plain pipe); for
    a run with no EdgeLoc vehicle (`vehicles=0`: `workload: none`), what it recorded instead."""
    head = f"run {run_id}: " if run_id else ""
    tail = (f"; over {air}" if air else "") + (" [partial]" if partial else "")
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


def _method_table(methods: dict[str, Any], caption: str = "") -> Table:
    rows = []
    for m, b in methods.items():
        p, h = b["position_m"] or {}, b["heading_deg"] or {}
        rows.append(
            [m, str(b["frames"]), str(b["missing_frames"])]
            + [cell(p.get(k)) for k in ("total", "mean", "median", "rmse", "p95", "max")]
            + [cell(h.get(k), "{:.2f}") for k in ("mean", "median", "rmse", "p95", "max")]
        )
    heads = ["method", "frames", "missing", "total m", "mean m", "median m", "RMSE m", "p95 m"]
    heads += ["max m", "yaw mean°", "yaw median°", "yaw RMSE°", "yaw p95°", "yaw max°"]
    return Table(heads, rows, caption)


def accuracy_section(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Accuracy per method")
    if not s["methods"]:
        return sec.add(
            not_recorded_note("poses with ground truth", "/<vehicle>/gt and /<vehicle>/pose")
        )
    sec.add(
        Para(
            "Errors per frame against ground truth on the same frame id (no alignment), "
            "position in metres and heading in degrees; 'missing': ground-truth frames the "
            "method published no pose for."
        ),
        _method_table(s["methods"], "all vehicles"),
    )
    if len(s["per_vehicle"]) > 1:
        for v, pv in s["per_vehicle"].items():
            sec.add(_method_table(pv["methods"], v))
    for key in ("errors_over_time", "error_boxplot"):
        if plots.get(key):
            sec.add(Image(plots[key]))  # type: ignore[arg-type]
    return sec


def paper_section(s: dict[str, Any]) -> Section:
    pc = s["paper_comparison"]
    sec = Section("Against the paper (Oxford RobotCar, total position error)")
    sec.add(
        Table(
            ["method", "paper total m", "ours total m"],
            [
                [t["method"], cell(t["paper"], "{:.2f}"), cell(t["ours"], "{:.2f}")]
                for t in pc["totals"]
            ],
        ),
        Table(
            ["EdgeLoc's reduction vs", "paper %", "ours %"],
            [
                [r["versus"], cell(r["paper_pct"], "{:.2f}"), cell(r["ours_pct"], "{:.2f}")]
                for r in pc["reductions"]
            ],
        ),
        Para(
            "Totals are sums over different drives (the paper's RobotCar run, our synthetic "
            "drive), so compare the reductions, not the totals."
        ),
    )
    return sec


def trajectories_section(data: RunData, plots: dict[str, Plot | None], tum: list[Path]) -> Section:
    sec = Section("Trajectories")
    shown = False
    for v in data.vehicles:
        p = plots.get(f"trajectory:{v}")
        if p:
            sec.add(Image(p))
            shown = True
    if not shown and not tum:  # figures may be off; TUM files mean poses were recorded
        sec.add(not_recorded_note("poses"))
    if tum:
        names = ", ".join(str(p) for p in tum)
        sec.add(
            Para(
                f"TUM files for evo: {names}. Example: evo_ape tum gt.tum edgeloc.tum "
                "(in trajectories/<vehicle>/)."
            )
        )
    return sec
