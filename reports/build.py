"""`build_report(run_folder)`: read runs/<id>/run.mcap and write the report beside it.

Writes (formats as the scenario's `report.formats`, all by default): `summary.json` (keys in
`reports.summary`), `report.md`, `report.html` (self-contained), `plots/*.png`, and
`trajectories/<vehicle>/{gt,<method>}.tum` (TUM format, for evo: `evo_ape tum gt.tum
edgeloc.tum`). Only the MCAP is read, so the report can be rebuilt anywhere from the file
alone; a recording cut short gives a report that says it is partial, and anything not
recorded is named as such rather than failing the build.
"""

from __future__ import annotations

import math
import shutil
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nodes.edgeloc.metrics import write_tum
from nodes.recording import linktable
from nodes.recording.layout import HANDOVER_TOPIC, PARTS_DIR, PCAP_DIR, RUN_MCAP, SUMMARY_FILE
from reports.document import Code, Document, Image, Para, Section, Table, to_markdown
from reports.html import to_html
from reports.mcapread import ReportInputError, RunData, read_run
from reports.plots import Plot, draw_all, safe
from reports.summary import (
    edgeloc_vehicles,
    load_comparison,
    load_windows,
    method_errors,
    summarize,
    summary_json,
)

FORMATS = ("html", "md", "json")


@dataclass
class Report:
    """What `build_report` wrote, and the headline line `testbed run` prints last."""

    folder: Path
    headline: str
    partial: bool
    status: str
    summary: dict[str, Any]
    files: list[Path] = field(default_factory=list)

    @property
    def html(self) -> Path | None:
        p = self.folder / "report.html"
        return p if p in self.files else None

    @property
    def main_file(self) -> Path:
        """The file to point a person at: the HTML report, else the Markdown, else the JSON."""
        for name in ("report.html", "report.md", "summary.json"):
            if self.folder / name in self.files:
                return self.folder / name
        return self.folder


# ---- formatting -----------------------------------------------------------------------------


def _f(x: Any, spec: str = "{:.3f}") -> str:
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float | int):
        return spec.format(x)
    return str(x)


def _pct(x: Any) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def _ms(x: Any) -> str:
    return "-" if x is None else f"{x * 1e3:.1f}"


def _not_recorded(what: str, why: str = "") -> Para:
    return Para(f"Not recorded: {what}" + (f" ({why})." if why else "."), "note")


# ---- sections -------------------------------------------------------------------------------


def _overview(data: RunData, s: dict[str, Any]) -> Section:
    sec = Section("Run")
    if s["partial"]:
        why = "; ".join(data.problems) or f"the run ended with status {s['status']!r}"
        sec.add(
            Para(
                f"PARTIAL REPORT: the recording does not cover the whole run ({why}). Every "
                "figure below covers only what was recorded.",
                "warning",
            )
        )
    if str(s["status"]).startswith("failed"):
        why = str(s["status"]).removeprefix("failed").lstrip(": ") or "no reason recorded"
        sec.add(Para(f"The run FAILED: {why}", "warning"))
    run = s["run"]
    keys = ["run_id", "scenario", "seed", "status", "link_backend", "started", "ended"]
    keys += ["duration_s", "testbed_version", "python", "ros", "torch", "kernel"]
    rows = [[k, _f(run.get(k), "{:g}")] for k in keys if k in run]
    rows += [
        [k, _f(v, "{:g}")]
        for k, v in run.items()
        if k not in keys and not isinstance(v, dict | list)
    ]
    if rows:
        sec.add(Table(["field", "value"], rows))
    else:
        sec.add(_not_recorded("the run's metadata (edgeloc.run)"))
    backend = run.get("link_backend")
    sec.add(Para(f"Link backend that ran: {backend}" if backend else "Link backend: not recorded."))
    for k, v in run.items():
        if isinstance(v, dict | list) and v:
            rows = [[str(a), _f(b, "{:g}")] for a, b in v.items()] if isinstance(v, dict) else []
            if rows:
                sec.add(Table([k, "value"], rows, caption=k.replace("_", " ")))
            else:
                sec.add(Code("\n".join(str(x) for x in v), caption=k))
    return sec


def _failures(s: dict[str, Any]) -> Section | None:
    if not s["failures"]:
        return None
    # In a run that ended "ok", a non-zero exit is a node that had to be killed at the stop.
    ok = s["status"] == "ok"
    sec = Section("Nodes that did not exit cleanly" if ok else "Failed nodes")
    for f in s["failures"]:
        sec.add(
            Para(
                f"{f['process']} (namespace {f['namespace'] or '-'}) "
                + (
                    "has no exit code recorded"
                    if f["exit_code"] is None
                    else f"exited with code {f['exit_code']}"
                )
                + ".",
                "warning",
            )
        )
        if f["last_log_lines"]:
            sec.add(
                Code("\n".join(f["last_log_lines"]), caption=f"last log lines of {f['process']}")
            )
        else:
            sec.add(_not_recorded(f"the log lines of {f['process']}"))
    return sec


def _method_table(methods: dict[str, Any], caption: str = "") -> Table:
    rows = []
    for m, b in methods.items():
        p, h = b["position_m"] or {}, b["heading_deg"] or {}
        rows.append(
            [m, str(b["frames"]), str(b["missing_frames"])]
            + [_f(p.get(k)) for k in ("total", "mean", "median", "rmse", "p95", "max")]
            + [_f(h.get(k), "{:.2f}") for k in ("mean", "median", "rmse", "p95", "max")]
        )
    heads = ["method", "frames", "missing", "total m", "mean m", "median m", "RMSE m", "p95 m"]
    heads += ["max m", "yaw mean°", "yaw median°", "yaw RMSE°", "yaw p95°", "yaw max°"]
    return Table(heads, rows, caption)


def _accuracy(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Accuracy per method")
    if not s["methods"]:
        return sec.add(
            _not_recorded("poses with ground truth", "/<vehicle>/gt and /<vehicle>/pose")
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


def _paper(s: dict[str, Any]) -> Section:
    pc = s["paper_comparison"]
    sec = Section("Against the paper (Oxford RobotCar, total position error)")
    sec.add(
        Table(
            ["method", "paper total m", "ours total m"],
            [
                [t["method"], _f(t["paper"], "{:.2f}"), _f(t["ours"], "{:.2f}")]
                for t in pc["totals"]
            ],
        ),
        Table(
            ["EdgeLoc's reduction vs", "paper %", "ours %"],
            [
                [r["versus"], _f(r["paper_pct"], "{:.2f}"), _f(r["ours_pct"], "{:.2f}")]
                for r in pc["reductions"]
            ],
        ),
        Para(
            "Totals are sums over different drives (the paper's RobotCar run, our synthetic "
            "drive), so compare the reductions, not the totals."
        ),
    )
    return sec


def _trajectories(data: RunData, plots: dict[str, Plot | None], tum: list[Path]) -> Section:
    sec = Section("Trajectories")
    shown = False
    for v in data.vehicles:
        p = plots.get(f"trajectory:{v}")
        if p:
            sec.add(Image(p))
            shown = True
    if not shown and not tum:  # figures may be off; TUM files mean poses were recorded
        sec.add(_not_recorded("poses"))
    if tum:
        names = ", ".join(str(p) for p in tum)
        sec.add(
            Para(
                f"TUM files for evo: {names}. Example: evo_ape tum gt.tum edgeloc.tum "
                "(in trajectories/<vehicle>/)."
            )
        )
    return sec


def _learner(data: RunData, s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Split-point learner")
    lr = s["learner"]
    if not lr["decisions"]:
        sec.add(_not_recorded("split decisions", "/<vehicle>/split_decision"))
    else:
        sec.add(
            Para(
                f"{lr['decisions']} decisions, {lr['switches']} split changes; rules: "
                + ", ".join(f"{k} {v}" for k, v in lr["rules"].items())
                + "."
            ),
            Table(
                ["split", "share of decisions"],
                [[k, f"{100 * v:.1f}%"] for k, v in lr["split_share"].items()],
            ),
        )
    if lr["phases"]:
        sec.add(
            Table(
                [
                    "from s",
                    "to s",
                    "plays",
                    "most played",
                    "share",
                    "fastest in hindsight",
                    "its share",
                    "in 2nd half",
                    "mean latency per split ms",
                ],
                [
                    [
                        _f(ph["start_s"], "{:.2f}"),
                        _f(ph["end_s"], "{:.2f}"),
                        str(ph["plays"]),
                        _f(ph["chosen"]),
                        _pct(ph["share"].get(ph["chosen"])) if ph["chosen"] else "-",
                        _f(ph["best_in_hindsight"]),
                        _pct(ph["share_best"]),
                        _pct(ph["share_best_second_half"]),
                        ", ".join(f"{k} {v * 1e3:.1f}" for k, v in ph["mean_latency_s"].items()),
                    ]
                    for ph in lr["phases"]
                ],
                caption="per network phase (between applied timeline events), vehicles pooled",
            )
        )
    for v in data.vehicles:
        p = plots.get(f"split:{v}")
        if p:
            sec.add(Image(p))
    if lr["detector_updates"] == 0 and not any(vd.detector for vd in data.vehicles.values()):
        sec.add(_not_recorded("change-detector updates", "/<vehicle>/detector"))
    elif lr["resets"]:
        sec.add(
            Table(
                ["vehicle", "t (s)", "arm", "KL", "at play"],
                [
                    [
                        r["vehicle"],
                        _f(r["t_s"], "{:.2f}"),
                        r["arm"],
                        _f(r["kl"], "{:.3f}"),
                        str(r["at_play"]),
                    ]
                    for r in lr["resets"]
                ],
                caption=f"detector resets ({lr['detector_updates']} detector updates)",
            )
        )
    else:
        sec.add(Para(f"No detector reset in {lr['detector_updates']} detector updates."))
    return sec


def _splits(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Split points: learned, fixed, oracle")
    sp = s.get("splits") or {}
    if "skipped" in sp and "rows" not in sp:
        return sec.add(Para(f"Not computed: {sp['skipped']}.", "note"))
    sec.add(
        Para(
            "EdgeLoc replayed on this run's drive (the dataset regenerated from the attached "
            "nodes' settings, the same DNN) with the learned split choice, with every split "
            "the run measured held fixed, and with the oracle. Every replayed request takes "
            f"the latency of one of {sp['vehicle']}'s {sp['requests']} measured requests of "
            "the same split in the same phase. The fixed-split and oracle rows are replays with "
            "the run's measured latencies, not runs of their own; the oracle plays the most "
            "accurate split of each phase, which it knows by reading ground truth (no vehicle "
            "could). Cells: mean position error m / mean request latency ms."
        )
    )
    if sp.get("fusion"):
        sec.add(Para(f"EdgeLoc's fusion in every row: {sp['fusion']}."))
    phases = sp["phases"]
    heads = ["policy", "total m"] + [f"{p['start_s']:g}-{p['end_s']:g} s" for p in phases]
    rows = []
    for r in sp["rows"]:
        cells = [
            f"{_f(f['mean_error_m'], '{:.2f}')} / {_ms(f['mean_latency_s'])}" for f in r["phases"]
        ]
        rows.append([r["policy"], _f(r["total_m"], "{:.1f}"), *cells])
    sec.add(Table(heads, rows, caption=f"replays under {sp['vehicle']}'s measured latencies"))
    real = sp.get("real_learned_total_m")
    learned = next((r for r in sp["rows"] if r["policy"] == "learned"), None)
    sec.add(
        Para(
            f"The real run's learned EdgeLoc ({sp['vehicle']}, as recorded): total "
            f"{_f(real, '{:.1f}')} m"
            + (f"; its replay above: {learned['total_m']:.1f} m." if learned else ".")
        )
    )
    for p in phases:
        if p["latency_best"] is None or p["error_best"] is None:
            verdict = "no split was timed in this phase"
        else:
            verdict = "the same split" if p["agree"] else "they DISAGREE"
        sec.add(
            Para(
                f"Phase {p['start_s']:g}-{p['end_s']:g} s: fastest {_f(p['latency_best'])}, "
                f"most accurate {_f(p['error_best'])} ({verdict})."
            )
        )
    # Latency-best against error-best, inversions and the learned run against the fixed
    # splits: what the drive resolves is a warning; a tie inside its noise is a row of one
    # table (with K splits there are up to K(K-1)/2 pairs per phase). Imported here: the
    # comparison that wrote these rows has loaded it (and torch) already; a report without
    # them does not pay for it.
    from nodes.edgeloc.compare import WITHIN_NOISE

    for line in sp["disagreements"]:
        if WITHIN_NOISE not in line:
            sec.add(Para(f"Against the paper's claim: {line}.", "warning"))
    ties = [
        [
            f"{p['start_s']:g}-{p['end_s']:g} s",
            v["slower"],
            v["faster"],
            f"{v['by_m']:.2f}",
            f"±{v['noise_m']:.2f}",
        ]
        for p in phases
        for v in p.get("inversions", [])
        if not v["beyond_noise"] and v["noise_m"] is not None and math.isfinite(v["noise_m"])
    ]
    if ties:
        sec.add(
            Table(
                ["phase", "more accurate", "than the faster", "by m", "drive's noise m"],
                ties,
                caption="ties: a slower split ahead of a faster one within the drive's noise",
            )
        )
    for line in sp["disagreements"]:
        if line.startswith("the learned run") and WITHIN_NOISE in line:
            sec.add(Para(f"A tie: {line}.", "note"))
    if any(p.get("inversions") for p in phases):
        sec.add(
            Para(
                "The drive's noise is Student's 95% interval for the mean difference in error "
                "between the two splits, from that difference's means over blocks of about "
                f"{sp['noise_block_s']:g} s: an inversion within it is a tie that this drive "
                "cannot resolve, one beyond it is evidence against the claim.",
                "note",
            )
        )
    fixed = [r for r in sp["rows"] if r["policy"].startswith("fixed:")]
    if len(fixed) < 2:
        sec.add(
            Para(
                "The run measured fewer than two splits, so latency and error cannot be "
                "compared across splits."
            )
        )
    elif not sp["disagreements"]:
        sec.add(
            Para(
                "In every phase the fastest split is also the most accurate, and error rises "
                "with latency across the splits, as the paper claims."
            )
        )
    if sp.get("learned_beats_fixed"):  # when it does not, a disagreement above says so
        sec.add(Para(f"The learned replay beats every fixed split (best: {sp['best_fixed']})."))
    for k, why in sp.get("skipped", {}).items():
        sec.add(Para(f"No row for {k}: {why}.", "note"))
    if sp.get("skipped"):
        sec.add(
            Para(
                "The learned and oracle replays chose among the measured splits only: "
                + ", ".join(sp.get("replayed_splits", []))
                + ".",
                "note",
            )
        )
    if plots.get("split_error_latency"):
        sec.add(Image(plots["split_error_latency"]))  # type: ignore[arg-type]
    return sec


def _latency(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Latency per split")
    lat = s["latency"]
    if lat["source"] is None:
        return sec.add(_not_recorded("inference results", "/<vehicle>/inference"))
    rows = []
    for k, b in lat["per_split"].items():
        ls = b["latency_s"] or {}
        rows.append(
            [k, str(b["requests"]), str(b["answers"]), str(b["timed_out"]), str(b["errors"])]
            + [_ms(ls.get(q)) for q in ("mean", "median", "p95", "max")]
            + [
                _f(b["mean_payload_bytes"], "{:.0f}"),
                _ms(b["mean_head_s"]),
                _ms(b["mean_edge_compute_s"]),
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


def _acc_lat(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Accuracy against latency")
    a = s["accuracy_vs_latency"]
    if not a or not a["bins"]:
        return sec.add(_not_recorded("EdgeLoc poses with a DNN answer age"))
    sec.add(
        Para(f"{a['frames']} EdgeLoc frames with a DNN answer; Pearson r = {_f(a['pearson_r'])}."),
        Table(
            ["answer age ms", "frames", "median error m", "mean error m"],
            [
                [
                    f"{b['latency_lo_s'] * 1e3:.1f}-{b['latency_hi_s'] * 1e3:.1f}",
                    str(b["frames"]),
                    _f(b["median_error_m"]),
                    _f(b["mean_error_m"]),
                ]
                for b in a["bins"]
            ],
            caption="quartiles of the answer age",
        ),
    )
    if plots.get("accuracy_vs_latency"):
        sec.add(Image(plots["accuracy_vs_latency"]))  # type: ignore[arg-type]
    return sec


def _realtime(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Real-time deadlines")
    rt = s["realtime"]
    if not rt["vehicles"]:
        sec.add(_not_recorded("fused poses with ground-truth frames"))
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
                        _f(r["rate_hz"], "{:g}"),
                        str(r["frames_expected"]),
                        str(r["poses"]),
                        str(r["missing"]),
                        str(r["late"]),
                        _f(r["miss_pct"], "{:.2f}"),
                        _ms((r["delay_s"] or {}).get("median")),
                        _ms((r["delay_s"] or {}).get("p95")),
                        _ms((r["delay_s"] or {}).get("max")),
                        _ms(r["max_interval_s"]),
                    ]
                    for v, r in rt["vehicles"].items()
                ],
            ),
        )
    for proc, figures in rt["reported_by_nodes"].items():
        sec.add(
            Table(
                ["figure", "value"],
                [[k, _f(v, "{:g}")] for k, v in figures.items()],
                caption=f"reported by {proc}",
            )
        )
    if plots.get("realtime"):
        sec.add(Image(plots["realtime"]))  # type: ignore[arg-type]
    return sec


def _gaps(s: dict[str, Any]) -> Section:
    sec = Section("Gaps in DNN answers")
    if not s["dnn_gaps"]:
        return sec.add(_not_recorded("DNN answers", "/<vehicle>/dnn_answer"))
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
                        _f(x["start_s"], "{:.2f}"),
                        _f(x["end_s"], "{:.2f}"),
                        _f(x["duration_s"], "{:.2f}"),
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


def _links(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Links")
    ls = s["links"]
    sec.add(Para(f"Link backend: {ls['backend'] or 'not recorded'}."))
    tl = ls.get("timeline") or {}
    if tl:
        late = tl.get("lateness") if isinstance(tl.get("lateness"), dict) else {}
        sec.add(
            Para(
                f"Timeline: {tl.get('events', '-')} event(s) in the scenario, "
                f"{tl.get('applied', '-')} applied, {tl.get('failed', '-')} failed; lateness "
                f"median {_f(late.get('median_ms'), '{:.2f}')} ms, p99 "
                f"{_f(late.get('p99_ms'), '{:.2f}')} ms, max {_f(late.get('max_ms'), '{:.2f}')} ms."
            )
        )
    # The channel's radio changes (several a second) are counted, not listed.
    events = [e for e in ls["events"] if e["action"] != "channel"]
    by_channel = len(ls["events"]) - len(events)
    if by_channel:
        sec.add(Para(f"The channel changed the air links' radio {by_channel} time(s)."))
    if events:
        sec.add(
            Table(
                ["t s", "scheduled s", "late ms", "action", "target", "direction", "changes"],
                [
                    [
                        _f(e["t_s"], "{:.2f}"),
                        _f(e["scheduled_s"], "{:.2f}"),
                        _ms(e["lateness_s"]),
                        e["action"],
                        e["target"],
                        e["direction"],
                        ", ".join(f"{k}={v}" for k, v in e["changes"].items()),
                    ]
                    for e in events
                ],
                caption="timeline events applied to the links",
            )
        )
    elif not by_channel:
        sec.add(_not_recorded("link events", "/links/events"))
    if ls["rates"]:
        sec.add(
            Table(
                [
                    "link",
                    "dir",
                    "backend",
                    "samples",
                    "mean Mbit/s",
                    "max Mbit/s",
                    "bytes",
                    "dropped pkts",
                ],
                [
                    [
                        r["link"],
                        r["direction"],
                        r["backend"],
                        str(r["samples"]),
                        _f(r["mean_mbit"], "{:.3f}"),
                        _f(r["max_mbit"], "{:.3f}"),
                        _f(r["bytes_out"], "{:.0f}"),
                        _f(r["packets_dropped"], "{:.0f}"),
                    ]
                    for r in ls["rates"]
                ],
                caption="delivered traffic per link direction (counter differences)",
            )
        )
        if plots.get("link_rates"):
            sec.add(Image(plots["link_rates"]))  # type: ignore[arg-type]
    else:
        sec.add(_not_recorded("link counters", "/links/counters"))
    lt = ls["linktest"]
    if lt:
        verdict = "every link within tolerance" if lt.get("ok") else "a link is OUT of tolerance"
        sec.add(
            Table(
                list(linktable.HEADERS),  # the same columns `testbed link-test` prints
                linktable.rows(lt),
                caption=f"link self-test ({verdict}; backend {lt.get('backend', '-')})",
            )
        )
        radio = _radio_table(lt)
        if radio is not None:
            sec.add(radio)
            if plots.get("radio_cdfs"):
                sec.add(Image(plots["radio_cdfs"]))  # type: ignore[arg-type]
    elif str(ls.get("linktest_ran")).lower() == "false":
        sec.add(Para("The link self-test did not run (the scenario's report.link_test is off)."))
    else:
        sec.add(_not_recorded("the link self-test", "no linktest.json attachment"))
    return sec


def _radio_table(lt: dict[str, Any]) -> Table | None:
    """The self-test's radio directions against their oracle (`nodes.recording.linktable`
    holds the figures' text, as `testbed link-test` prints it)."""
    directions = linktable.radio_directions(lt)
    if not directions:
        return None
    rows = []
    for link, direction, radio in directions:
        points = {round(q * 100): (m, o) for q, m, o in linktable.cdf_points(radio)}
        cells = [
            f"{points[k][0]:.2f} / {points[k][1]:.2f}" if k in points else "-"
            for k in (10, 50, 90, 99)
        ]
        harq, slots = radio.get("harq"), radio.get("slots")
        rows.append(
            [
                link,
                direction,
                str(radio.get("samples", "-")),
                _f(radio.get("w1_ms")),
                _f(radio.get("ks")),
                f"{_f(radio.get('tolerance_ms'))} ({_f(radio.get('host_tolerance_ms'))} host "
                f"+ {_f(radio.get('sampling_tolerance_ms'))} chance)",
                *cells,
                linktable.harq_text(harq) if isinstance(harq, dict) else "-",
                linktable.slots_text(slots) if isinstance(slots, dict) else "-",
            ]
        )
    floor = lt.get("timer_floor")
    timer = (
        f"; this host's timer floor: p50 {_f(floor.get('p50_ms'))} ms, p99 "
        f"{_f(floor.get('p99_ms'))} ms over {floor.get('count', '-')} timed wake-ups"
        if isinstance(floor, dict)
        else ""
    )
    return Table(
        [
            "link",
            "dir",
            "probes",
            "W1 ms",
            "KS",
            "tolerance ms",
            "p10 ms meas / oracle",
            "p50",
            "p90",
            "p99",
            "HARQ shares measured (expected %)",
            "per slot at saturation",
        ],
        rows,
        caption="radio directions against the closed-form oracle (one-way delay of sparse "
        f"probes, net of the wired delay and the path without the link){timer}",
    )


def _radio(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section | None:
    """The vehicles' radio along their routes (runs with `channel:`)."""
    radio = s.get("radio") or {}
    vehicles = radio.get("vehicles") or {}
    if not vehicles:
        return None
    ch = radio.get("channel") or {}
    sec = Section("Radio along the route")
    source = f"trace {ch['trace']}" if ch.get("trace") else f"TR 38.901 {ch.get('model', '?')}"
    sec.add(
        Para(
            f"The channel ({source}, LOS {ch.get('los', '?')}, a step every "
            f"{_ms(ch.get('step_s'))} ms) set each vehicle's air link from where it was; "
            f"{len(ch.get('sites') or [])} cell site(s)."
        )
    )

    def db(block: Any, key: str) -> str:
        return _f((block or {}).get(key), "{:.1f}")

    def capacity(block: Any) -> str:
        """The uplink's p5 / median: the uplink is what EdgeLoc's requests wait on, and its
        p5 is the cell edge. "-" for a run without links.json's radios."""
        ul = (block or {}).get("ul") or {}
        if ul.get("median") is None:
            return "-"
        return f"{_f(ul.get('p5'), '{:.1f}')} / {_f(ul.get('median'), '{:.1f}')}"

    sec.add(
        Table(
            [
                "vehicle",
                "coverage",
                "cells",
                "handovers",
                "DL SINR p5/median dB",
                "UL SINR p5/median dB",
                "mean MCS DL/UL",
                "mean BLER DL/UL",
                "capacity p5/median UL Mbit/s",
            ],
            [
                [
                    v,
                    _pct(r.get("coverage")),
                    ", ".join(f"{c} {_pct(x)}" for c, x in (r.get("cells") or {}).items()),
                    str(len(r.get("handovers") or [])),
                    f"{db(r.get('sinr_db'), 'p5')} / {db(r.get('sinr_db'), 'median')}",
                    f"{db(r.get('ul_sinr_db'), 'p5')} / {db(r.get('ul_sinr_db'), 'median')}",
                    f"{_f(r.get('mean_mcs'), '{:.1f}')} / {_f(r.get('mean_ul_mcs'), '{:.1f}')}",
                    f"{_pct(r.get('mean_bler'))} / {_pct(r.get('mean_ul_bler'))}",
                    capacity(r.get("capacity_mbps")),
                ]
                for v, r in vehicles.items()
            ],
            caption="per vehicle, from /radio/<vehicle>: coverage is the share of steps at "
            "downlink CQI 1 or better; capacity is what the serving cell's uplink carried at "
            "each step's MCS and BLER, its radio from links.json (- without it)",
        )
    )
    for v, r in vehicles.items():
        rows = r.get("by_uplink_mcs")
        if rows:
            sec.add(
                Table(
                    ["uplink MCS", "share of the run", "plays", "splits chosen", "mean payload"],
                    [
                        [
                            f"{row['mcs'][0]}-{row['mcs'][1]}",
                            _pct(row.get("time_share")),
                            str(row["plays"]),
                            ", ".join(f"{s} {_pct(x)}" for s, x in list(row["share"].items())[:3]),
                            "-"
                            if row["mean_payload_bytes"] is None
                            else f"{row['mean_payload_bytes'] / 1000:.1f} kB",
                        ]
                        for row in rows
                    ],
                    caption=f"{v}: the learner's decisions by the uplink MCS at their time",
                )
            )
    if HANDOVER_TOPIC in (s.get("not_recorded") or []):
        sec.add(
            _not_recorded(
                "the handovers as applied",
                f"{HANDOVER_TOPIC}, though the scenario sets channel.handover: the handovers "
                "below are the serving cell's changes on /radio/<vehicle>, without their "
                "interruption or lateness",
            )
        )
    for v, r in vehicles.items():
        if r.get("around_handovers"):
            sec.add(_around_table(v, r))
            sentence = _smaller_split_sentence(r)
            if sentence:
                sec.add(Para(sentence))
    for key in sorted(k for k in plots if k.startswith("radio:")):
        plot = plots[key]
        if plot is not None:
            sec.add(Image(plot))
    return sec


def _around_table(vehicle: str, r: dict[str, Any]) -> Table:
    """One row per handover of `vehicle`: what it was, and the radio, EdgeLoc's error and the
    learner's plays in the window before it beside the window after it."""

    def both(row: dict[str, Any], show: Callable[[dict[str, Any]], str]) -> str:
        return f"{show(row.get('before') or {})} / {show(row.get('after') or {})}"

    def top(w: dict[str, Any]) -> str:
        return "-" if w.get("top_split") is None else f"{w['top_split']} {_pct(w['top_share'])}"

    rows = []
    for h in r["around_handovers"]:
        cut = "-"
        if h.get("interruption_ms") is not None:
            cut = f"{h['interruption_ms']:.1f} " + ("lossless" if h.get("lossless") else "lossy")
        rows.append(
            [
                _f(h.get("t_s"), "{:.2f}"),
                f"{h['from']} → {h['to']}" + (f" (failed: {h['error']})" if h.get("error") else ""),
                cut,
                _f(h.get("lateness_ms"), "{:.1f}"),
                both(h, lambda w: _f(w.get("mean_ul_mcs"), "{:.1f}")),
                both(h, lambda w: _f(w.get("mean_error_m"), "{:.2f}")),
                both(h, top),
                both(h, lambda w: _ms(w.get("mean_latency_s"))),
            ]
        )
    w = _f(r.get("handover_window_s"), "{:g}")
    source = r.get("handovers_source") or "/radio/<vehicle>"
    return Table(
        [
            "time s",
            "from → to",
            "interruption ms",
            "lateness ms",
            "UL MCS before / after",
            "EdgeLoc error m before / after",
            "top split before / after",
            "mean latency ms before / after",
        ],
        rows,
        caption=f"Around each handover of {vehicle} (from {source}), the {w} s before it and "
        f"the {w} s after: mean uplink MCS of the channel steps, EdgeLoc's mean position error "
        "of the frames captured, the learner's most-played split and its share of the plays, "
        "the mean latency of the plays' answered requests",
    )


def _smaller_split_sentence(r: dict[str, Any]) -> str | None:
    """Whether the learner moved to a smaller split near the handovers, said plainly from the
    numbers. Rule: near a handover the learner moved to a smaller split when its most-played
    split in the window before or the window after it sends less uplink payload per request
    (that split's mean over the vehicle's requests) than its most-played split away from every
    handover; "near most" when that holds for more than half of the handovers where at least
    one window could be compared. None for a vehicle without plays (no EdgeLoc on it)."""
    around = r["around_handovers"]
    away = r.get("away_from_handovers") or {}
    near = sum(h["before"]["plays"] + h["after"]["plays"] for h in around)
    if not near and not away.get("plays"):
        return None
    judged = [h for h in around if h.get("smaller_split_near") is not None]
    w = _f(r.get("handover_window_s"), "{:g}")
    if not judged:
        why = (
            "it made no plays away from them to compare with"
            if not away.get("plays")
            else "no window near them has plays of a split whose payload was recorded "
            "(/<vehicle>/inference)"
        )
        return f"Whether the learner moved to a smaller split near the handovers is unknown: {why}."
    n = sum(bool(h["smaller_split_near"]) for h in judged)
    before = sum(h["before"]["top_split_vs_away"] == "smaller" for h in judged)
    after = sum(h["after"]["top_split_vs_away"] == "smaller" for h in judged)
    verdict = "moved" if 2 * n > len(judged) else "did not move"
    text = (
        f"The learner {verdict} to a smaller split near most handovers: near {n} of "
        f"{len(judged)} handovers its most-played split in the {w} s before or after sent less "
        f"uplink payload per request than {away['top_split']}, its most-played split away "
        f"from handovers ({before} in the window before, {after} in the window after)."
    )
    left = len(around) - len(judged)
    if left:
        text += (
            f" {left} handover(s) could not be compared (no plays near them, or a split "
            "without recorded payload)."
        )
    return text


def _nodes(s: dict[str, Any]) -> Section:
    sec = Section("Nodes")
    nodes = s["nodes"]
    if not nodes:
        return sec.add(_not_recorded("node processes", "metadata edgeloc.nodes"))
    from reports.summary import exit_code_of

    rows = []
    for proc, info in nodes.items():
        info = info if isinstance(info, dict) else {}
        stats = info.get("stats") if isinstance(info.get("stats"), dict) else {}
        brief = ", ".join(
            f"{k}={_f(v, '{:.4g}') if isinstance(v, float) else v}"
            for k, v in stats.items()
            if isinstance(v, int | float | str) and k != "node"
        )
        rows.append([proc, str(info.get("namespace", "-")), _f(exit_code_of(info), "{}"), brief])
    return sec.add(Table(["process", "namespace", "exit code", "stats"], rows))


def _recording(data: RunData, s: dict[str, Any]) -> Section:
    sec = Section("Recording")
    rec = s["recording"]
    sec.add(
        Para(
            f"{rec['file']}: {'complete' if rec['complete'] else 'INCOMPLETE'}, "
            f"{sum(rec['messages'].values())} messages decoded, {rec['decode_errors']} not."
        )
    )
    for p in rec["problems"]:
        sec.add(Para(p, "warning"))
    sec.add(
        Table(
            ["topic", "type", "messages"],
            [[t, rec["schemas"].get(t, "-"), str(n)] for t, n in rec["messages"].items()],
        )
    )
    if s["not_recorded"]:
        sec.add(Para("Not recorded: " + ", ".join(s["not_recorded"]) + ".", "note"))
    if data.attachments:
        sec.add(Para("Attachments: " + ", ".join(sorted(data.attachments)) + "."))
    if not data.run_json:
        sec.add(Para(NO_RUN_JSON, "note"))
    _captures(sec, data)
    return sec


#: Why a run's report has no split comparison when its scenario says `report.compare: false`.
NOT_COMPARED = (
    "the scenario's report.compare is false; `testbed report {folder} --compare` computes it"
)
#: What a report cannot show without the run's run.json (a run that ended before writing it).
NO_RUN_JSON = (
    "No run.json, in the run folder or attached to run.mcap (the run ended before writing "
    "it): the path to the edge, apps, cross-traffic and EdgeLoc under load are left out."
)


def _apps(data: RunData) -> Section | None:
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
                _f(a.get("started_at_s"), "{:.1f} s"),
                _f(a.get("ready_at_s"), "{:.1f} s") if a.get("ready") else "-",
                ended,
                f"{_f(res.get('user_s'), '{:.2f}')} + {_f(res.get('system_s'), '{:.2f}')} s"
                + throttled,
                _f((res.get("peak_rss_kb") or 0) / 1024, "{:.0f} MiB"),
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


def _traffic(data: RunData) -> Section | None:
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
                _pct(f.get("loss")),
                _f(f.get("delay_p50_ms"), "{:.1f} ms"),
                _f(f.get("rtt_p50_ms"), "{:.1f} ms"),
                _f(f.get("late_packets"), "{}"),
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


def _load(s: dict[str, Any]) -> Section | None:
    """EdgeLoc with and without the cross-traffic (`summary.load_comparison`)."""
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
                    _ms(lat.get("median")) + " ms",
                    _ms(lat.get("p95")) + " ms",
                    _f(r["edgeloc_error_m"], "{:.3f} m"),
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


def _captures(sec: Section, data: RunData) -> None:
    """The run's packet captures (`record.pcap`) beside run.mcap, with what run.json says each
    holds."""
    files = sorted((data.path.parent / PCAP_DIR).glob("*.pcapng"))
    if not files:
        return
    captures = data.run_json.get("captures") or {}
    rows = []
    for f in files:
        info = captures.get(f.stem) or {}
        packets, dropped = info.get("packets") or {}, info.get("dropped") or {}
        rows.append(
            [
                f"{PCAP_DIR}/{f.name}",
                f"{f.stat().st_size / 1e6:.2f}",
                *[f"{packets.get(d, '-')} / {dropped.get(d, '-')}" for d in ("uplink", "downlink")],
            ]
        )
    sec.add(
        Table(
            ["capture (open in Wireshark)", "MB", "uplink packets / dropped", "downlink"],
            rows,
            caption="what each link delivered, after its impairments; drops are counted, "
            "not captured",
            link_columns=(0,),
        )
    )


def _paths(
    data: RunData,
    per_vehicle: dict[str, Any] | None = None,
    linktest: dict[str, Any] | None = None,
) -> Section | None:
    """Each vehicle's path to its edge (run.json `paths`): addresses, the N3 tunnel, the edge's
    placement and each hop's delay, configured and, where the link self-test ran, measured
    (its one-way median per direction, `_measured_hops`), and what the path gave (the
    summary's `per_vehicle`): its requests' median latency and EdgeLoc's mean error, so
    placements compare side by side; with a UPF, what GTP-U added on N3."""
    run = data.run_json
    paths, core = run.get("paths") or [], run.get("core_path")
    if not paths:
        return None
    sec = Section("Path to the edge")
    measured = _measured_hops(linktest)
    rows = []
    for p in paths:
        tunnel = p.get("tunnel") or {}
        hops = " + ".join(
            f"{h['link']} ({h['kind']}, {_f(h.get('uplink_delay_ms'), '{:g}')}/"
            f"{_f(h.get('downlink_delay_ms'), '{:g}')} ms"
            + (f"; measured {measured[h['link']]})" if h["link"] in measured else ")")
            for h in p.get("hops", [])
        )
        rows.append(
            [
                p["vehicle"],
                p["address"],
                p["gnb"],
                p.get("upf") or "-",
                f"UL {tunnel['ul_teid']} / DL {tunnel['dl_teid']}" if tunnel else "-",
                f"{p['edge']} {p['edge_address']} ({p['placement']})",
                hops,
                *_path_outcome((per_vehicle or {}).get(p["vehicle"]) or {}),
            ]
        )
    sec.add(
        Table(
            [
                "vehicle",
                "address",
                "gNB",
                "UPF",
                "N3 TEIDs",
                "edge (placement)",
                "hops (up/down delay" + (", measured by the link self-test)" if measured else ")"),
                "answers / requests",
                "median latency ms",
                "EdgeLoc mean error m",
            ],
            rows,
        )
    )
    if core:
        share = core.get("gtp_overhead_share")
        sec.add(
            Para(
                f"GTP-U on N3: {core.get('gtp_overhead_bytes_per_packet')} bytes per packet "
                f"(outer IPv4, UDP, GTP-U with its PDU Session Container); "
                f"{core.get('gtp_overhead_bytes', 0) / 1e6:.2f} MB of the "
                f"{core.get('n3_bytes', 0) / 1e6:.2f} MB on N3"
                + (f" ({share * 100:.1f}%)" if share is not None else "")
                + f"; UE pool {core.get('ue_pool')}."
            )
        )
        if core.get("qos_flows"):
            sec.add(Para(f"QoS flows: {core['qos_flows']}. {_qfi_counts(core)}"))
    return sec


def _measured_hops(linktest: dict[str, Any] | None) -> dict[str, str]:
    """Link -> "uplink/downlink" one-way delay medians (ms) that the link self-test measured
    before the nodes started, each net of the same path's delay with the link neutral
    (`owd_median_ms` - `baseline_ms`), so they read against the configured delays."""
    out: dict[str, str] = {}
    for link in (linktest or {}).get("links") or []:
        net = {}
        for d in link.get("directions") or []:
            owd, base = d.get("owd_median_ms"), d.get("baseline_ms")
            net[d.get("direction")] = None if owd is None else owd - (base or 0.0)
        if any(v is not None for v in net.values()):
            out[link["link"]] = (
                f"{_f(net.get('uplink'), '{:.2f}')}/{_f(net.get('downlink'), '{:.2f}')}"
            )
    return out


def _path_outcome(pv: dict[str, Any]) -> list[str]:
    """A vehicle's answers / requests, its answered requests' median latency and EdgeLoc's
    mean position error, as the path table shows them."""
    latency = (pv.get("latency_s") or {}).get("median")
    edgeloc = ((pv.get("methods") or {}).get("edgeloc") or {}).get("position_m") or {}
    count = f"{pv['answers']} / {pv['requests']}" if "requests" in pv else "-"
    return [count, _ms(latency), _f(edgeloc.get("mean"), "{:.2f}")]


def _qfi_counts(core: dict[str, Any]) -> str:
    """G-PDUs per QFI and direction, from the gNB ends (uplink) and the UPF ends (downlink)."""
    counts: dict[str, Counter[str]] = {"uplink": Counter(), "downlink": Counter()}
    for key, stats in (core.get("endpoints") or {}).items():
        direction = "downlink" if "/" in key else "uplink"  # "upf1/gnb1" is a UPF's end
        counts[direction].update(stats.get("qfi_sent") or {})
    parts = [
        f"{d} " + ", ".join(f"QFI {q}: {n}" for q, n in sorted(c.items()))
        for d, c in counts.items()
        if c
    ]
    return f"G-PDUs sent: {'; '.join(parts)}." if parts else ""


def document(
    data: RunData, s: dict[str, Any], plots: dict[str, Plot | None], tum: list[Path]
) -> Document:
    run_id = s["run"].get("run_id", data.path.parent.name)
    scen = s["run"].get("scenario")
    title = f"EdgeLoc run {run_id}" + (f" — {scen}" if scen else "")
    if s["partial"]:
        title += " (partial)"
    sections = [_overview(data, s), _failures(s)]
    if edgeloc_vehicles(s["run"]) != 0:  # a `workload: none` run has none of these
        sections += [_accuracy(s, plots), _paper(s)]
        sections += [_trajectories(data, plots, tum), _learner(data, s, plots)]
        sections += [_splits(s, plots), _latency(s, plots)]
        sections += [_acc_lat(s, plots), _realtime(s, plots), _gaps(s)]
    else:
        title = title.replace("EdgeLoc run", "Run", 1)
    sections += [_links(s, plots), _radio(s, plots)]
    sections += [_paths(data, s.get("per_vehicle"), s["links"].get("linktest"))]
    sections += [_apps(data), _traffic(data), _load(s)]
    sections += [_nodes(s), _recording(data, s)]
    return Document(title, s["headline"], [x for x in sections if x is not None])


# ---- files --------------------------------------------------------------------------------


def write_trajectories(data: RunData, folder: Path) -> list[Path]:
    """trajectories/<vehicle>/{gt,<method>}.tum; returns the paths relative to `folder`."""
    out = []
    for v, vd in data.vehicles.items():
        for name in ["gt", *vd.methods()]:
            tr = vd.tracks.get(name)
            if tr is None:
                continue
            ok = np.isfinite(tr.stamp) & np.isfinite(tr.pose).all(axis=1)
            if not ok.any():
                continue
            rel = Path("trajectories") / safe(v) / f"{safe(name)}.tum"
            (folder / rel).parent.mkdir(parents=True, exist_ok=True)
            write_tum(folder / rel, tr.stamp[ok], tr.pose[ok])
            out.append(rel)
    return out


def build_report(
    run_folder: Path | str,
    formats: Iterable[str] = FORMATS,
    plots: bool = True,
    splits: bool | str = True,
) -> Report:
    """Read `run_folder`/run.mcap and write the report files into `run_folder`. `splits=False`
    (or a string: the reason the report gives) leaves out the replays of the split
    comparison (`reports.splits`).

    Raises ReportInputError when there is no readable MCAP; anything else the recording
    lacks shows in the report as not recorded."""
    folder = Path(run_folder)
    if not (folder / RUN_MCAP).is_file() and (folder / PARTS_DIR).is_dir():
        raise ReportInputError(
            f"{folder}: the recording was never merged into {RUN_MCAP} (the run was killed?); "
            "`testbed clean` finalises it from the parts in parts/"
        )
    if not (folder / RUN_MCAP).is_file():
        raise ReportInputError(
            f"{folder}: no {RUN_MCAP} here (is it a run folder of `testbed run` with "
            "record.enabled?)"
        )
    fmts = set(formats)
    unknown = fmts - set(FORMATS)
    if unknown:
        raise ReportInputError(f"unknown report format(s) {sorted(unknown)}; use {list(FORMATS)}")
    data = read_run(folder / RUN_MCAP)
    s = summarize(data, splits=splits)
    s["load"] = load_comparison(data, load_windows(data.run_json))
    errs = method_errors(data)
    files: list[Path] = []
    tum = write_trajectories(data, folder)
    files += [folder / p for p in tum]
    plot_dir = folder / "plots"
    drawn: dict[str, Plot | None] = {}
    if plots and fmts & {"html", "md"}:
        if plot_dir.exists():
            shutil.rmtree(plot_dir)  # figures of an earlier build must not linger
        drawn = draw_all(data, errs, s, plot_dir)
        files += [plot_dir / p.file for p in drawn.values() if p is not None]
    if "json" in fmts:
        (folder / SUMMARY_FILE).write_text(summary_json(s), encoding="utf-8")
        files.append(folder / SUMMARY_FILE)
    doc = document(data, s, drawn, tum)
    if "md" in fmts:
        (folder / "report.md").write_text(to_markdown(doc), encoding="utf-8")
        files.append(folder / "report.md")
    if "html" in fmts:
        (folder / "report.html").write_text(to_html(doc, plot_dir), encoding="utf-8")
        files.append(folder / "report.html")
    return Report(folder, s["headline"], s["partial"], s["status"], s, files)


__all__ = ["FORMATS", "Report", "ReportInputError", "build_report"]


def report_after_run(
    run_folder: Path,
    formats: Iterable[str] = FORMATS,
    plots: bool = True,
    splits: bool | str = True,
) -> tuple[Report | None, str | None]:
    """The report at the end of a run (`testbed run`, each real variant of `testbed sweep`):
    `(report, None)`, or `(None, why not)` when the run recorded nothing or the report cannot
    be built. Never raises for a report's own failure: the run's outcome is what counts.
    `splits` False is the scenario's `report.compare: false`, which the report says."""
    folder = Path(run_folder)
    if splits is False:
        splits = NOT_COMPARED.format(folder=folder)
    if not (folder / RUN_MCAP).is_file():
        return None, f"{folder} has no {RUN_MCAP} (record.enabled off, or nothing recorded)"
    try:
        return build_report(folder, formats=formats, plots=plots, splits=splits), None
    except ReportInputError as err:
        return None, str(err)
    except Exception as err:  # a report bug must not hide the run's result
        return None, f"the report of {folder} could not be built: {type(err).__name__}: {err}"
