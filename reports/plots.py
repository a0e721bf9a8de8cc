"""The report's figures (matplotlib, drawn off-screen), each from `RunData` and the summary.

Every function writes one PNG into the plots folder and returns a `Plot` (file name, title,
caption), or None when the recording holds nothing to draw it from — the report then says
that part was not recorded. Figures are made with `matplotlib.figure.Figure` directly, not
pyplot, so no global state or display backend is involved.
"""

from __future__ import annotations

import functools
import itertools
import multiprocessing
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

from nodes.recording import linktable
from reports.document import Plot
from reports.labels import place
from reports.mcapread import RunData, VehicleData
from reports.sections.accuracy import FrameErrors
from reports.sections.learner import split_order
from reports.sections.radio import radio_capacity
from reports.sections.timing import fused_method

#: Per-vehicle figures are drawn for at most this many vehicles (the tables cover all).
MAX_VEHICLE_FIGURES = 6
DPI = 100
#: The circle of a fixed split in the error-against-latency figure, in points.
FIXED_MARKER_PT = 6
METHOD_COLORS = {
    "gt": "black",
    "vo": "#7f7f7f",
    "dnn": "#ff7f0e",
    "kalman": "#1f77b4",
    "edgeloc": "#2ca02c",
}
EXTRA_COLORS = ("#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#d62728")
#: Bottoms of the log axes of quantities that cannot be negative. Smaller values (a perfect
#: frame, an idle link) are drawn on the bottom line, labelled "≤ floor": 1 cm is far below
#: any error a method makes here, 1 kbit/s below any traffic the nodes send.
ERROR_FLOOR_M = 0.01
RATE_FLOOR_MBIT = 0.001
#: Lowest bottom of the radio figure's capacity axis: a 106-PRB carrier carries ~1.5 Mbit/s
#: at MCS 0 in its uplink slots, so only a narrow carrier's cell edge comes near it, and a
#: step whose blocks all fail (BLER 1) sits on the bottom line.
CAPACITY_FLOOR_MBIT = 0.1


def color(method: str, order: list[str]) -> str:
    if method in METHOD_COLORS:
        return METHOD_COLORS[method]
    extras = [m for m in order if m not in METHOD_COLORS]
    return EXTRA_COLORS[extras.index(method) % len(EXTRA_COLORS)] if method in extras else "k"


def safe(name: str) -> str:
    """A file-name-safe form of a vehicle or link name."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name) or "_"


def _save(fig: Figure, folder: Path, name: str) -> str:
    fig.tight_layout()
    # No "Software" text chunk: the same data then gives the same bytes on any matplotlib.
    fig.savefig(folder / name, dpi=DPI, metadata={"Software": None})
    return name


def _label_points(
    fig: Figure,
    ax: Any,
    labels: list[tuple[str, float, float, str]],
    markers: list[tuple[float, float, float]],
    fontsize: float = 7,
) -> None:
    """Name points (text, x, y, colour) where no name covers another or a marker (x, y,
    width in points): `reports.labels.place` on the laid-out figure, with a thin leader line
    to a name that had to move away from its point."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.tight_layout()  # as `_save` lays it out: pixel positions must be the saved ones
    px = fig.dpi / 72.0
    to_px = ax.transData.transform
    circles = [(*to_px((x, y)), width_pt * px / 2) for x, y, width_pt in markers]
    sizes = []
    for text, *_ in labels:
        probe = ax.text(0, 0, text, fontsize=fontsize)
        extent = probe.get_window_extent(renderer)
        probe.remove()
        sizes.append((extent.width, extent.height))
    anchors = [tuple(to_px((x, y))) for _, x, y, _ in labels]
    frame = tuple(ax.get_window_extent(renderer).extents)
    boxes = place(anchors, sizes, circles, frame)  # type: ignore[arg-type]
    for (text, x, y, colour), (ax_px, ay_px), box in zip(labels, anchors, boxes, strict=True):
        far = max(box[0] - ax_px, ax_px - box[2], box[1] - ay_px, ay_px - box[3]) > 10
        note = ax.annotate(
            text,
            (x, y),
            xytext=((box[0] - ax_px) / px, (box[1] - ay_px) / px),
            textcoords="offset points",
            ha="left",
            va="bottom",
            fontsize=fontsize,
            color=colour,
            arrowprops={"arrowstyle": "-", "lw": 0.5, "color": colour, "shrinkA": 0, "shrinkB": 4}
            if far
            else None,
        )
        note.set_in_layout(False)  # already placed inside the axes: keep the layout as measured


def _floored(values: Any, floor: float) -> Any:
    """`values` with everything below `floor` (zero included) raised to it, for a log axis."""
    return np.maximum(np.asarray(values, dtype=float), floor)


def _log_axis(ax: Any, floor: float) -> None:
    """A log y axis from `floor` up, for a quantity >= 0 whose large values must not flatten
    the small ones (DNN outliers of 100 m beside errors of a metre): plain tick labels
    (0.1, 0.2, 0.5, 1 ...), the bottom one "≤ floor". Call it after the data is drawn (drawn
    through `_floored`), so the top of the axis fits the data."""
    ax.set_yscale("log")
    top = max(ax.get_ylim()[1], floor * 10)
    ax.set_ylim(floor, top)
    ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_minor_formatter(NullFormatter())

    def label(v: float, _pos: int | None) -> str:
        return f"≤{v:g}" if np.isclose(v, floor) else f"{v:g}"

    ax.yaxis.set_major_formatter(FuncFormatter(label))


def _decade_below(values: Any, floor: float) -> float:
    """The power of ten at or below the smallest positive finite value, not under `floor`:
    the bottom of a log axis that shows the data's low end without empty decades."""
    a = np.asarray(values, dtype=float)
    a = a[np.isfinite(a) & (a > 0)]
    if not len(a):
        return floor
    return max(floor, float(10 ** np.floor(np.log10(a.min()))))


def _shade(ax: Any, summary: dict[str, Any], vehicle: str, t_label: bool = True) -> None:
    """DNN-answer gaps as grey spans, detector resets as red lines (shared by time plots)."""
    first = True
    for g in summary.get("dnn_gaps", {}).get(vehicle, {}).get("gaps", []):
        ax.axvspan(
            g["start_s"],
            g["end_s"],
            color="0.85",
            zorder=0,
            label="no DNN answers" if first and t_label else None,
        )
        first = False
    first = True
    for r in summary.get("learner", {}).get("resets", []):
        if r["vehicle"] == vehicle and r["t_s"] is not None:
            ax.axvline(
                r["t_s"],
                color="red",
                lw=0.8,
                ls="--",
                label="detector reset" if first and t_label else None,
            )
            first = False


def errors_over_time(
    data: RunData, errs: dict[str, dict[str, FrameErrors]], summary: dict[str, Any], out: Path
) -> Plot | None:
    vehicles = [v for v in data.vehicles if any(v in e for e in errs.values())]
    if not vehicles:
        return None
    shown = vehicles[:MAX_VEHICLE_FIGURES]
    order = list(errs)
    fig = Figure(figsize=(11, 3.2 * len(shown)))
    for i, v in enumerate(shown):
        ax = fig.add_subplot(len(shown), 1, i + 1)
        for m in order:
            fe = errs[m].get(v)
            if fe is not None and len(fe.t):
                ax.plot(
                    fe.t - data.t0,
                    _floored(fe.position_m, ERROR_FLOOR_M),
                    lw=1,
                    color=color(m, order),
                    label=m,
                )
        _shade(ax, summary, v)
        ax.set_title(f"{v}: position error per frame")
        ax.set_xlabel("run time (s)")
        _log_axis(ax, ERROR_FLOOR_M)
        ax.set_ylabel("error (m, log)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, ncol=3)
    note = "" if len(shown) == len(vehicles) else f" (first {len(shown)} vehicles)"
    return Plot(
        _save(fig, out, "errors_over_time.png"),
        "Position error over time",
        "Per frame, against ground truth (log axis; errors under "
        f"{ERROR_FLOOR_M * 100:g} cm on its bottom line); grey spans: no DNN answers arrived; "
        f"red dashes: change-detector resets{note}.",
    )


def error_boxplots(errs: dict[str, dict[str, FrameErrors]], out: Path) -> Plot | None:
    methods = [m for m in errs if any(len(fe.t) for fe in errs[m].values())]
    if not methods:
        return None
    fig = Figure(figsize=(11, 4))
    for j, (key, label) in enumerate(
        (("position_m", "position error (m)"), ("heading_deg", "heading error (deg)"))
    ):
        ax = fig.add_subplot(1, 2, j + 1)
        series = [np.concatenate([getattr(fe, key) for fe in errs[m].values()]) for m in methods]
        if key == "position_m":
            # monotonic: the box of the floored errors differs from the true one only below
            # the floor, where the log axis cannot tell values apart anyway
            series = [_floored(x, ERROR_FLOOR_M) for x in series]
        box = ax.boxplot(
            series,
            tick_labels=methods,
            showfliers=True,
            patch_artist=True,
            medianprops={"color": "black"},
        )
        for patch, m in zip(box["boxes"], methods, strict=True):
            patch.set_facecolor(color(m, methods))
            patch.set_alpha(0.6)
        ax.set_ylabel(label + (", log" if key == "position_m" else ""))
        if key == "position_m":
            _log_axis(ax, ERROR_FLOOR_M)
        else:
            ax.set_ylim(bottom=0)  # linear, and an error is never below 0
        ax.grid(alpha=0.3, axis="y")
    return Plot(
        _save(fig, out, "error_boxplot.png"),
        "Error distribution per method",
        "Boxes: quartiles; whiskers: 1.5 IQR; circles: frames beyond (all vehicles pooled).",
    )


def trajectory(data: RunData, vd: VehicleData, out: Path) -> Plot | None:
    names = [n for n in ["gt", *vd.methods()] if n in vd.tracks and len(vd.tracks[n])]
    if not names:
        return None
    order = vd.methods()
    fig = Figure(figsize=(7, 6))
    ax = fig.add_subplot(1, 1, 1)
    for n in names:
        p = vd.tracks[n].pose
        ax.plot(
            p[:, 0],
            p[:, 1],
            lw=2.0 if n == "gt" else 1.0,
            color=color(n, order),
            label="ground truth" if n == "gt" else n,
            ls="--" if n == "gt" else "-",
        )
    gt = vd.tracks.get("gt")
    clipped = ""
    if gt is not None and len(gt):
        # Frame the ground truth: a DNN outlier 200 m off would shrink the drive to a dot.
        lo, hi = gt.pose[:, :2].min(axis=0), gt.pose[:, :2].max(axis=0)
        pad = max(10.0, 0.15 * float((hi - lo).max()))
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        clipped = " Axes frame the ground truth; estimates further off run out of the frame."
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{vd.name}: trajectories")
    return Plot(
        _save(fig, out, f"trajectory_{safe(vd.name)}.png"),
        f"Trajectories of {vd.name}",
        "Every method's pose per frame in the map frame, ground truth dashed." + clipped,
    )


def vehicle_uplink_rates(data: RunData, vehicle: str) -> list[tuple[str, Any, Any]]:
    """(label, t, Mbit/s) of the uplink of every link that has `vehicle` as an end."""
    out = []
    for c in data.counters:
        if c.direction == "up" and vehicle in c.link.split("-"):
            t, r = c.rate_mbit()
            if len(t):
                out.append((f"{c.link} uplink", t - data.t0, r))
    return out


def split_over_time(
    data: RunData, vd: VehicleData, summary: dict[str, Any], out: Path
) -> Plot | None:
    if not vd.decisions:
        return None
    order = split_order(data)
    t = np.array([d.t for d in vd.decisions]) - data.t0
    idx = np.array([order.index(d.chosen) for d in vd.decisions])
    fig = Figure(figsize=(11, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(t, idx, drawstyle="steps-post", lw=0.6, color="#2ca02c", alpha=0.6)
    ax.scatter(t, idx, s=6, color="#2ca02c", label="chosen split", zorder=3)
    ax.set_yticks(range(len(order)), order)
    ax.set_ylim(-0.5, len(order) - 0.5)
    ax.set_xlabel("run time (s)")
    ax.set_ylabel("split point")
    _shade(ax, summary, vd.name)
    first = True
    for e in data.link_events:
        ax.axvline(
            e.t - data.t0,
            color="0.4",
            lw=0.8,
            ls=":",
            label="link event" if first else None,
        )
        first = False
    ax.grid(alpha=0.3)
    links = summary.get("links", {})
    first = True
    for o in links.get("outages", []):
        if vd.name in str(o["link"]).split("-") and o["start_s"] is not None:
            ax.axvspan(
                o["start_s"],
                o["end_s"],
                color="#f4b6b6",
                zorder=0,
                label="link outage" if first else None,
            )
            first = False
    # The workload's span: link counters go on being sampled after the nodes stopped.
    fused = fused_method(vd)
    end = float(t.max())
    if fused is not None and len(vd.tracks[fused]):
        end = max(end, float(vd.tracks[fused].stamp.max() - data.t0))
    ax.set_xlim(min(0.0, float(t.min())), end + 0.5)
    rates = vehicle_uplink_rates(data, vd.name)
    caps = list(links.get("caps", {}).get(vd.name, []))
    handles, labels = ax.get_legend_handles_labels()
    if rates or caps:
        ax2 = ax.twinx()
        for label, rt, r in rates:
            ax2.plot(rt, r, color="#1f77b4", lw=1.0, label=f"{label} delivered")
        if caps:
            ct = [c["t_s"] for c in caps] + [end + 0.5]
            cv = [np.nan if c["uplink_mbit"] is None else c["uplink_mbit"] for c in caps]
            ax2.step(
                ct,
                [*cv, cv[-1]],
                where="post",
                color="#9467bd",
                lw=2,
                ls="--",
                label="uplink cap (timeline)",
            )
        ax2.set_ylabel("uplink (Mbit/s, log)")
        ax2.set_yscale("log")
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    # Below the axes: inside, it would hide the dots and the cap line.
    ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.16), fontsize=8, ncol=4)
    ax.set_title(f"{vd.name}: split chosen per request")
    rate_note = (
        "blue: delivered uplink rate from the link counters, purple dashes: the timeline's "
        "uplink cap"
        if rates or caps
        else "link rate not recorded"
    )
    return Plot(
        _save(fig, out, f"split_{safe(vd.name)}.png"),
        f"Split point over time, {vd.name}",
        f"One dot per request; {rate_note}; red dashes: detector resets; dotted: timeline "
        "events applied to the links; grey spans: no DNN answers; red spans: link outages.",
    )


def latency_per_split(data: RunData, out: Path) -> Plot | None:
    reqs = [i for vd in data.vehicles.values() for i in vd.inference]
    order = [s for s in split_order(data) if any(i.split == s for i in reqs)]
    series = [[i.latency_s * 1e3 for i in reqs if i.split == s and i.ok] for s in order]
    if not any(series):
        return None
    keep = [k for k, s in enumerate(series) if s]
    fig = Figure(figsize=(9, 4))
    ax = fig.add_subplot(1, 1, 1)
    ax.boxplot([series[k] for k in keep], tick_labels=[order[k] for k in keep])
    for pos, k in enumerate(keep, start=1):
        lost = sum(1 for i in reqs if i.split == order[k] and not i.ok)
        ax.annotate(
            f"n={len(series[k])}" + (f", {lost} lost" if lost else ""),
            (pos, 1),
            xycoords=("data", "axes fraction"),
            xytext=(0, -12),
            textcoords="offset points",
            ha="center",
            fontsize=8,
        )
    ax.set_xlabel("split point")
    ax.set_ylabel("end-to-end latency (ms)")
    ax.grid(alpha=0.3, axis="y")
    ax.set_title("Latency per split (answered requests)")
    return Plot(
        _save(fig, out, "latency_per_split.png"),
        "Latency per split",
        "End-to-end time from capture to answer, per request; requests without an answer "
        "(timeout or error) are counted as lost.",
    )


def accuracy_vs_latency(errs: dict[str, FrameErrors] | None, out: Path) -> Plot | None:
    if not errs:
        return None
    lat = np.concatenate([e.latency_s for e in errs.values()])
    err = np.concatenate([e.position_m for e in errs.values()])
    ok = np.isfinite(lat)
    if ok.sum() < 2:
        return None
    lat, err = lat[ok] * 1e3, err[ok]
    fig = Figure(figsize=(8, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    ax.scatter(lat, err, s=4, alpha=0.35, color="#2ca02c", label="frame")
    edges = np.unique(np.percentile(lat, np.linspace(0, 100, 11)))
    if len(edges) > 2:
        mids, meds = [], []
        for lo, hi in itertools.pairwise(edges):
            sel = (lat >= lo) & (lat <= hi)
            if sel.any():
                mids.append((lo + hi) / 2)
                meds.append(float(np.median(err[sel])))
        ax.plot(mids, meds, color="black", marker="o", lw=1.2, label="median per decile")
    ax.set_xlabel("age of the DNN answer used (ms)")
    ax.set_ylabel("EdgeLoc position error (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return Plot(
        _save(fig, out, "accuracy_vs_latency.png"),
        "Accuracy against latency",
        "EdgeLoc's error per frame against the latency of the newest DNN answer it fused.",
    )


def link_rates(data: RunData, out: Path) -> Plot | None:
    series = [(c, *c.rate_mbit()) for c in data.counters]
    series = [s for s in series if len(s[1])]
    if not series:
        return None
    fig = Figure(figsize=(11, 4))
    ax = fig.add_subplot(1, 1, 1)
    for c, t, r in series:
        ax.plot(t - data.t0, _floored(r, RATE_FLOOR_MBIT), lw=1, label=f"{c.link} {c.direction}")
    for e in data.link_events:
        ax.axvline(e.t - data.t0, color="0.4", lw=0.8, ls=":")
    ax.set_xlabel("run time (s)")
    _log_axis(ax, RATE_FLOOR_MBIT)
    ax.set_ylabel("delivered (Mbit/s, log)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    return Plot(
        _save(fig, out, "link_rates.png"),
        "Traffic on the emulated links",
        "Delivered rate per link direction from the backends' byte counters (differences of "
        f"consecutive samples; log axis, under {RATE_FLOOR_MBIT * 1000:g} kbit/s on its bottom "
        "line); dotted: timeline events.",
    )


def realtime(data: RunData, summary: dict[str, Any], out: Path) -> Plot | None:
    rt = summary.get("realtime", {}).get("vehicles", {})
    shown = [v for v in data.vehicles if v in rt][:MAX_VEHICLE_FIGURES]
    if not shown:
        return None
    fig = Figure(figsize=(11, 3.5))
    ax = fig.add_subplot(1, 1, 1)
    period = None
    for v in shown:
        m = fused_method(data.vehicles[v])
        if m is None:
            continue
        tr = data.vehicles[v].tracks[m]
        ax.plot(tr.stamp - data.t0, (tr.log_time - tr.stamp) * 1e3, lw=0.8, label=f"{v} {m}")
        period = rt[v]["period_s"]
    if period is not None:
        ax.axhline(period * 1e3, color="red", ls="--", lw=1, label="deadline (one period)")
    ax.set_xlabel("run time (s)")
    ax.set_ylabel("capture to publish (ms)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return Plot(
        _save(fig, out, "realtime.png"),
        "Real-time thread: fused pose delay",
        "Time from a frame's capture to the publishing of its fused pose (MCAP log time); "
        "above the red line the pose missed its deadline.",
    )


#: Phase colours of the split figure (matplotlib's tab10 order, learned/oracle markers black-edged).
PHASE_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2")
#: Markers of the non-fixed policies in the split figure; fixed splits are circles.
POLICY_MARKERS = {"learned": "*", "oracle": "D", "learned, paper fusion": "P"}


def split_error_latency(summary: dict[str, Any], out: Path) -> Plot | None:
    """Mean position error against mean request latency, per policy and phase, from the
    summary's `splits` block (the replays of `reports.splits`)."""
    sp = summary.get("splits") or {}
    rows, phases = sp.get("rows") or [], sp.get("phases") or []
    points = [
        (j, r["policy"], f["mean_latency_s"] * 1e3, f["mean_error_m"])
        for r in rows
        for j, f in enumerate(r["phases"])
        if f.get("mean_latency_s") is not None and f.get("mean_error_m") is not None
    ]
    if not points:
        return None
    fig = Figure(figsize=(9, 5.5))
    ax = fig.add_subplot(1, 1, 1)
    labels: list[tuple[str, float, float, str]] = []  # (text, x, y, colour)
    markers: list[tuple[float, float, float]] = []  # (x, y, width in points)
    for j, ph in enumerate(phases):
        c = PHASE_COLORS[j % len(PHASE_COLORS)]
        mine = [p for p in points if p[0] == j]
        fixed = sorted((p for p in mine if p[1].startswith("fixed:")), key=lambda p: p[2])
        ax.plot(  # the fixed splits of a phase, joined in latency order
            [p[2] for p in fixed],
            [p[3] for p in fixed],
            color=c,
            lw=0.8,
            alpha=0.5,
            marker="o",
            ms=FIXED_MARKER_PT,
            label=f"phase {ph['start_s']:g}-{ph['end_s']:g} s",
        )
        labels += [(policy.removeprefix("fixed:"), x, y, c) for _, policy, x, y in fixed]
        markers += [(x, y, FIXED_MARKER_PT) for _, _, x, y in fixed]
        for _, policy, x, y in mine:
            if policy in POLICY_MARKERS:
                size = 120 if policy == "learned" else 60
                ax.scatter(
                    [x],
                    [y],
                    marker=POLICY_MARKERS[policy],
                    s=size,
                    color=c,
                    edgecolors="black",
                    linewidths=0.8,
                    zorder=3,
                )
                # a diamond's tips reach 0.71 of its size from the centre, not 0.5
                markers.append((x, y, size**0.5 * (1.42 if policy == "oracle" else 1.0)))
    # One legend entry per marker shape (the colour is the phase's).
    for policy, marker in POLICY_MARKERS.items():
        if any(p[1] == policy for p in points):
            ax.scatter([], [], marker=marker, color="white", edgecolors="black", label=policy)
    ax.set_xlabel("mean request latency (ms)")
    ax.set_ylabel("mean EdgeLoc position error (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("Error against latency per split and phase")
    _label_points(fig, ax, labels, markers)
    return Plot(
        _save(fig, out, "split_error_latency.png"),
        "Error against latency per split and phase",
        "EdgeLoc replayed on the run's drive under the run's measured latencies: one circle "
        "per fixed split and phase (labelled with the split; colours are phases), the learned "
        "replay as a star, the oracle (plays the most accurate split of each phase, reads "
        "ground truth) as a diamond, the learned replay with the paper's bare fusion (when the "
        "run's fusion is not) as a plus. The paper's claim: the fastest split is the most "
        "accurate, so each phase's circles rise from left to right.",
    )


def radio_cdfs(summary: dict[str, Any], out: Path) -> Plot | None:
    """Per radio direction of the link self-test: the measured one-way delay CDF beside the
    closed-form oracle's (the quantiles linktest.json keeps)."""
    lt = (summary.get("links") or {}).get("linktest") or {}
    shown = [
        r
        for r in linktable.radio_directions(lt)
        if r[2].get("measured_ms") and r[2].get("quantiles")
    ][:MAX_VEHICLE_FIGURES]
    if not shown:
        return None
    cols = min(len(shown), 2)
    rows = -(-len(shown) // cols)
    fig = Figure(figsize=(5.5 * cols, 3.6 * rows))
    for i, (link, direction, radio) in enumerate(shown):
        ax = fig.add_subplot(rows, cols, i + 1)
        qs = radio["quantiles"]
        ax.plot(radio["measured_ms"], qs, color="#2ca02c", lw=1.6, label="measured")
        ax.plot(radio["oracle_ms"], qs, color="black", lw=1.2, ls="--", label="oracle")
        ax.set_title(
            f"{link} {direction}: W1 {radio.get('w1_ms', float('nan')):.2f} ms, "
            f"KS {radio.get('ks', float('nan')):.2f}",
            fontsize=9,
        )
        ax.set_xlabel("one-way delay of the radio (ms)")
        ax.set_ylabel("CDF")
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    return Plot(
        _save(fig, out, "radio_cdfs.png"),
        "Radio delays against the oracle",
        "One-way delay of sparse probes per radio direction in the link self-test, net of the "
        "wired delay and the path without the link (solid), beside the closed form the radio's "
        "parameters give for an idle UE (dashed).",
    )


#: Serving-cell colours of the radio map's route: none in the SINR colormap (viridis) nor the
#: handover crosses' red, so the cell shows as a halo the SINR dots do not hide.
CELL_COLORS = ("#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#17becf")


def radio_map(
    data: RunData,
    summary: dict[str, Any],
    vehicle: str,
    out: Path,
    edgeloc: FrameErrors | None = None,
) -> Plot | None:
    """The route coloured by downlink SINR over a halo of the serving cell's colour, the
    cells' sites, the handover points; beside it SINR and MCS of both directions, when
    links.json gives the air links' radios what the serving link carried at that MCS
    (`summary.radio_capacity`: the MCS alone does not say how many Mbit/s it is worth), and,
    when the vehicle ran EdgeLoc (`edgeloc`: its fused errors), EdgeLoc's position error over
    run time, each with the handovers marked (`/radio/<vehicle>`, the summary's handovers)."""
    r = data.radio.get(vehicle)
    if r is None or not len(r):
        return None
    radio = summary.get("radio") or {}
    sites = ((radio.get("channel") or {}).get("sites")) or []
    info = (radio.get("vehicles") or {}).get(vehicle) or {}
    handovers = [h["t_s"] for h in info.get("handovers") or [] if h.get("t_s") is not None]
    errors = edgeloc if edgeloc is not None and len(edgeloc.t) else None
    capacity = radio_capacity(data, r)
    rows = 2 + (capacity is not None) + (errors is not None)
    # 5 in for the two panels every run has, 1.5 in more per panel it adds (each stays legible)
    fig = Figure(figsize=(12, 5 + 1.5 * (rows - 2)))
    grid = fig.add_gridspec(rows, 2)
    ax = fig.add_subplot(grid[:, 0])
    cells = sorted(set(r.cell) | {str(s["name"]) for s in sites})
    cell_color = {c: CELL_COLORS[k % len(CELL_COLORS)] for k, c in enumerate(cells)}
    served = np.array(r.cell)
    for c in sorted(set(r.cell)):
        on = served == c
        ax.scatter(r.x[on], r.y[on], s=90, color=cell_color[c], alpha=0.5, lw=0, label=c)
    dots = ax.scatter(r.x, r.y, c=r.sinr_db, s=3, cmap="viridis", vmin=-10, vmax=30)
    fig.colorbar(dots, ax=ax, label="downlink SINR (dB)")
    for s in sites:
        ax.plot(
            s["x"], s["y"], marker="^", ms=11, color=cell_color[str(s["name"])], mec="black", ls=""
        )
        ax.annotate(s["name"], (s["x"], s["y"]), textcoords="offset points", xytext=(6, 6))
    at = [int(np.abs(r.t - data.t0 - t).argmin()) for t in handovers]
    if at:
        ax.plot(r.x[at], r.y[at], "rx", ms=10, mew=2, ls="none", label="handover")
    ax.legend(fontsize=8, title="serving cell", title_fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.set_title(f"{vehicle}: route by SINR and serving cell")
    t = r.t - data.t0
    top = fig.add_subplot(grid[0, 1])
    top.plot(t, r.sinr_db, lw=0.8, label="downlink")
    top.plot(t, r.ul_sinr_db, lw=0.8, label="uplink")
    top.set_ylabel("SINR (dB)")
    top.legend(fontsize=8)
    mid = fig.add_subplot(grid[1, 1], sharex=top)
    mid.step(t, r.mcs, where="post", lw=0.9, label="downlink")
    mid.step(t, r.ul_mcs, where="post", lw=0.9, label="uplink")
    mid.set_ylabel("MCS")
    mid.set_ylim(-1, 29)
    panels = [top, mid]
    if capacity is not None:
        # Its own panel, not a twin of the MCS one: four step lines on two scales would hide
        # each other. Log: the downlink carries several times the uplink, and a cell edge's
        # MCS 0 must not flatten to the floor beside MCS 28.
        cap = fig.add_subplot(grid[len(panels), 1], sharex=top)
        floor = _decade_below(np.concatenate(list(capacity.values())), CAPACITY_FLOOR_MBIT)
        cap.step(t, _floored(capacity["dl"], floor), where="post", lw=0.9)
        cap.step(t, _floored(capacity["ul"], floor), where="post", lw=0.9)
        _log_axis(cap, floor)
        cap.set_ylabel("capacity (Mbit/s)")
        panels.append(cap)
    if errors is not None:
        low = fig.add_subplot(grid[len(panels), 1], sharex=top)
        low.plot(
            errors.t - data.t0,
            _floored(errors.position_m, ERROR_FLOOR_M),
            lw=0.8,
            color=METHOD_COLORS["edgeloc"],
        )
        _log_axis(low, ERROR_FLOOR_M)
        low.set_ylabel("EdgeLoc error (m)")
        panels.append(low)
    panels[-1].set_xlabel("run time (s)")
    for a in panels:
        a.grid(alpha=0.3)
        for ho in handovers:
            a.axvline(ho, color="red", lw=0.8, ls="--")
    cover = info.get("coverage")
    covered = f" In coverage {cover:.0%} of the run." if isinstance(cover, float) else ""
    capacity_note = (
        ", the Mbit/s the serving cell's air link carried at that MCS and BLER (its radio "
        "from links.json; log axis)"
        if capacity is not None
        else ""
    )
    error_note = ", and EdgeLoc's position error per frame (log axis)" if errors is not None else ""
    return Plot(
        _save(fig, out, f"radio_{safe(vehicle)}.png"),
        f"Radio of {vehicle} along its route",
        "Left: the route, each channel step coloured by its downlink SINR over a halo of its "
        "serving cell's colour, and the cell sites (triangles in their cell's colour; crosses "
        "at the handovers). Right: SINR and the MCS link adaptation ran, downlink and uplink"
        f"{capacity_note}{error_note}, over the run (dashed: handovers)." + covered,
    )


def draw_all(
    data: RunData,
    errs: dict[str, dict[str, FrameErrors]],
    summary: dict[str, Any],
    out: Path,
    workers: int | None = None,
) -> dict[str, Plot | None]:
    """Every figure, keyed by what it shows (None: not recorded). The figures are independent
    (each reads the run and writes its own file), so they are drawn on forked workers, one per
    CPU this process may use (`workers`): the same files as drawn one after another, in about
    half the time on two cores."""
    out.mkdir(parents=True, exist_ok=True)
    jobs: dict[str, Callable[[], Plot | None]] = {
        "errors_over_time": lambda: errors_over_time(data, errs, summary, out),
        "error_boxplot": lambda: error_boxplots(errs, out),
        "latency_per_split": lambda: latency_per_split(data, out),
        "accuracy_vs_latency": lambda: accuracy_vs_latency(errs.get("edgeloc"), out),
        "link_rates": lambda: link_rates(data, out),
        "radio_cdfs": lambda: radio_cdfs(summary, out),
        "realtime": lambda: realtime(data, summary, out),
        "split_error_latency": lambda: split_error_latency(summary, out),
    }
    for v in list(data.vehicles)[:MAX_VEHICLE_FIGURES]:
        vd = data.vehicles[v]
        jobs[f"split:{v}"] = functools.partial(split_over_time, data, vd, summary, out)
        jobs[f"trajectory:{v}"] = functools.partial(trajectory, data, vd, out)
    for v in list(data.radio)[:MAX_VEHICLE_FIGURES]:
        edgeloc = errs.get("edgeloc", {}).get(v)
        jobs[f"radio:{v}"] = functools.partial(radio_map, data, summary, v, out, edgeloc)
    n = min(len(jobs), workers or len(os.sched_getaffinity(0)))
    if n <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        return {k: draw() for k, draw in jobs.items()}
    global _JOBS
    _JOBS = list(jobs.values())
    try:
        with multiprocessing.get_context("fork").Pool(n) as pool:
            drawn = pool.map(_draw, range(len(_JOBS)), chunksize=1)
    finally:
        _JOBS = []
    return dict(zip(jobs, drawn, strict=True))


#: The figures a forked worker of `draw_all` draws, by index: set before the fork, so each
#: worker inherits the run's data instead of receiving it pickled.
_JOBS: list[Callable[[], Plot | None]] = []


def _draw(i: int) -> Plot | None:
    return _JOBS[i]()


__all__ = ["MAX_VEHICLE_FIGURES", "Plot", "draw_all"]
