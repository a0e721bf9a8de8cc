"""What ran beside EdgeLoc: the apps a researcher brought (`apps:`), the cross-traffic flows
(`traffic:`), both from run.json, and EdgeLoc with the cross-traffic on against off.

Its key of summary.json (`build_report` adds it to `summarize`'s dict):

- `load`: {windows [[start, end]] (epoch s, when any flow ran), per_vehicle {vehicle:
  {with_load, without_load: {requests, answers, latency_s, edgeloc_error_m}}}}, or null
  without cross-traffic or EdgeLoc data.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from reports.document import Para, Section, Table
from reports.mcapread import RunData
from reports.sections.accuracy import method_errors
from reports.sections.fmt import cell, ms, pct, series_stats


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
                "latency_s": series_stats(answered),
                "edgeloc_error_m": err,
            }
        out[v] = rows
    return {"windows": [[a, b] for a, b in windows], "per_vehicle": out}


def apps_section(data: RunData) -> Section | None:
    """The apps a researcher brought (`apps:`): where each ran, when it was ready, how it
    ended and what it used (run.json's `apps`)."""
    apps = data.run_json.get("apps") or {}
    if not apps:
        return None
    rows = []
    for name, a in apps.items():
        res = a.get("resources") or {}
        ended = (
            "stopped by the testbed"
            if a.get("stopped_by_testbed") and a.get("exit_code") not in (0, None)
            else f"exit {a.get('exit_code')}"
        )
        cpu = a.get("cpu_stat") or {}
        throttled = f", throttled {cpu['nr_throttled']}/{cpu['nr_periods']}" if cpu else ""
        rows.append(
            [
                name,
                str(a.get("node")),
                " ".join(a.get("command") or []),
                cell(a.get("started_at_s"), "{:.1f} s"),
                cell(a.get("ready_at_s"), "{:.1f} s") if a.get("ready") else "-",
                ended,
                f"{cell(res.get('user_s'), '{:.2f}')} + {cell(res.get('system_s'), '{:.2f}')} s"
                + throttled,
                cell((res.get("peak_rss_kb") or 0) / 1024, "{:.0f} MiB"),
                str(a.get("log")),
            ]
        )
    table = Table(
        [
            "app",
            "node",
            "command",
            "started",
            "ready",
            "ended",
            "CPU user + sys",
            "peak memory",
            "log",
        ],
        rows,
    )
    return Section("Apps").add(table)


def _mbit(bps: Any) -> str:
    return "-" if bps is None else f"{bps / 1e6:.2f} Mbit/s"


def traffic_section(data: RunData) -> Section | None:
    """The cross-traffic flows (`traffic:`): offered against carried, loss, delay, RTT, and
    the sender's own lateness (run.json's `traffic`); their samples are /traffic/<flow>."""
    flows = data.run_json.get("traffic") or {}
    if not flows:
        return None
    rows = []
    for name, f in flows.items():
        offered = "unlimited" if f.get("rate_bps") is None else _mbit(f["rate_bps"])
        until = "end" if f.get("stop_s") is None else f"{f['stop_s']:g} s"
        rows.append(
            [
                name,
                str(f.get("kind")),
                f"{f.get('from')} -> {f.get('to')}",
                f"{f.get('start_s', 0):g} s - {until}",
                offered,
                _mbit(f.get("sent_bps")),
                _mbit(f.get("goodput_bps")),
                pct(f.get("loss")),
                cell(f.get("delay_p50_ms"), "{:.1f} ms"),
                cell(f.get("rtt_p50_ms"), "{:.1f} ms"),
                cell(f.get("late_packets"), "{}"),
            ]
        )
    sec = Section("Cross-traffic")
    sec.add(
        Table(
            [
                "flow",
                "kind",
                "path",
                "when",
                "offered",
                "sent",
                "goodput",
                "loss",
                "one-way delay p50",
                "RTT p50",
                "sent late",
            ],
            rows,
        )
    )
    errors = {n: f["errors"] for n, f in flows.items() if f.get("errors")}
    for name, errs in errors.items():
        sec.add(Para(f"{name}: " + "; ".join(f"{k} ({v}x)" for k, v in errs.items()), "warning"))
    return sec


def load_section(s: dict[str, Any]) -> Section | None:
    """EdgeLoc with and without the cross-traffic (`load_comparison`)."""
    load = s.get("load")
    if not load:
        return None
    rows = []
    for v, cmp in load["per_vehicle"].items():
        for label, key in (("with load", "with_load"), ("without load", "without_load")):
            r = cmp[key]
            lat = r["latency_s"] or {}
            rows.append(
                [
                    v,
                    label,
                    str(r["requests"]),
                    str(r["answers"]),
                    ms(lat.get("median")) + " ms",
                    ms(lat.get("p95")) + " ms",
                    cell(r["edgeloc_error_m"], "{:.3f} m"),
                ]
            )
    headers = [
        "vehicle",
        "cross-traffic",
        "requests",
        "answers",
        "latency p50",
        "latency p95",
        "EdgeLoc mean error",
    ]
    sec = Section("EdgeLoc under load")
    sec.add(
        Para(
            "Requests and fused-pose errors while any traffic: flow ran, against the rest of "
            "the run (one drive: its phases differ in more than the load)."
        )
    )
    return sec.add(Table(headers, rows))
