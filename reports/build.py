"""`build_report(run_folder)`: read runs/<id>/run.mcap and write the report beside it.

Writes (formats as the scenario's `report.formats`, all by default): `summary.json`,
`report.md`, `report.html` (self-contained), `plots/*.png`, and
`trajectories/<vehicle>/{gt,<method>}.tum` (TUM format, for evo: `evo_ape tum gt.tum
edgeloc.tum`). Only the MCAP is read, so the report can be rebuilt anywhere from the file
alone; a recording cut short gives a report that says it is partial, and anything not
recorded is named as such rather than failing the build.

The pipeline: read the recording (`reports.mcapread`), `summarize` it, draw the figures
(`reports.plots`), have each section (`reports.sections`) write its part in the report's
order (`document`), and render that as Markdown and HTML. `summarize(data) -> dict` is what
the report says, computed from `RunData` alone by the sections' pure computations (no files,
no plotting). The same MCAP always gives the same dict, and `summary_json` serialises it
byte-identically (no report-time clock in it), so a rebuilt report can be compared with the
run's own. Keys of summary.json (`version` 1), each documented by the section that computes
it:

- `version`, `kind` ("run": a recorded ROS run; replays write "replay");
- `run`, `partial`, `recording`, `status`: `reports.sections.run`;
- `vehicles`: names, sorted;
- `t0_epoch_s`: the origin of every `*_s` run time below (first ground-truth stamp);
- `methods`, `per_vehicle`, `paper_comparison`, `headline`: `reports.sections.accuracy`;
- `latency`: `reports.sections.timing`; `learner`: `reports.sections.learner`;
- `accuracy_vs_latency`, `realtime`, `dnn_gaps`: `reports.sections.timing`;
- `links`: `reports.sections.network`; `radio`: `reports.sections.radio`;
- `splits`: `reports.sections.learner`;
- `nodes`, `failures`, `not_recorded`: `reports.sections.run`;
- `load` (added by `build_report`): `reports.sections.apps`.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nodes.edgeloc.metrics import write_tum
from nodes.recording.layout import PARTS_DIR, RUN_MCAP, SUMMARY_FILE
from reports.document import Document, Plot, to_markdown
from reports.html import to_html
from reports.mcapread import ReportInputError, RunData, read_run
from reports.plots import draw_all, safe
from reports.sections.accuracy import (
    accuracy_section,
    accuracy_summary,
    headline,
    method_errors,
    paper_section,
    trajectories_section,
)
from reports.sections.apps import (
    apps_section,
    load_comparison,
    load_section,
    load_windows,
    traffic_section,
)
from reports.sections.core_path import paths_section
from reports.sections.learner import (
    learner_section,
    learner_summary,
    splits_section,
    splits_summary,
)
from reports.sections.network import links_section, links_summary
from reports.sections.radio import radio_section, radio_summary
from reports.sections.run import (
    failures,
    failures_section,
    nodes_section,
    not_recorded,
    overview_section,
    recording_section,
    recording_summary,
)
from reports.sections.timing import (
    accuracy_vs_latency,
    accuracy_vs_latency_section,
    dnn_gaps,
    gaps_section,
    latency_section,
    latency_summary,
    realtime_section,
    realtime_summary,
)

FORMATS = ("html", "md", "json")
SUMMARY_VERSION = 1


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


def edgeloc_vehicles(run: dict[str, Any]) -> int | None:
    """How many vehicles the run's scenario gave EdgeLoc's nodes (None: a recording from
    before `workload:` could be none, where every vehicle ran them)."""
    if "edgeloc_vehicles" not in run:
        return None
    return len([v for v in str(run["edgeloc_vehicles"]).split(",") if v])


# ---- the whole summary, the whole document ----------------------------------------------


def air_link(data: RunData) -> str | None:
    """What the first air link's uplink was, for the headline: `NR <TDD> <PRBs> PRB, <access>
    uplink` where it had a radio (links.json), None for a plain pipe."""
    for (link, direction), radio in sorted(data.link_radios.items()):
        if direction == "uplink" and radio is not None:
            return f"NR {radio.slots} {radio.n_prb} PRB, {radio.ul_access} uplink ({link})"
    return None


def summarize(data: RunData, splits: bool | str = True) -> dict[str, Any]:
    """The summary.json dict of a run (keys in the module docstring). `splits=False` leaves
    out the split comparison (its replays take seconds to a minute)."""
    errs = method_errors(data)
    accuracy = accuracy_summary(data, errs)
    run_id = data.run.get("run_id")
    split_block = splits_summary(data, accuracy["per_vehicle"], splits)
    return clean_json(
        {
            "version": SUMMARY_VERSION,
            "kind": "run",
            "run": data.run,
            "status": data.status,
            "partial": data.partial,
            "recording": recording_summary(data),
            "vehicles": list(data.vehicles),
            "t0_epoch_s": data.t0,
            **accuracy,
            "headline": headline(
                accuracy["paper_comparison"],
                None if run_id is None else str(run_id),
                data.partial,
                edgeloc_vehicles(data.run),
                air_link(data),
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


def document(
    data: RunData, s: dict[str, Any], plots: dict[str, Plot | None], tum: list[Path]
) -> Document:
    run_id = s["run"].get("run_id", data.path.parent.name)
    scen = s["run"].get("scenario")
    title = f"EdgeLoc run {run_id}" + (f" — {scen}" if scen else "")
    if s["partial"]:
        title += " (partial)"
    sections = [overview_section(data, s), failures_section(s)]
    if edgeloc_vehicles(s["run"]) != 0:  # a `workload: none` run has none of these
        sections += [accuracy_section(s, plots), paper_section(s)]
        sections += [trajectories_section(data, plots, tum), learner_section(data, s, plots)]
        sections += [splits_section(s, plots), latency_section(s, plots)]
        sections += [
            accuracy_vs_latency_section(s, plots),
            realtime_section(s, plots),
            gaps_section(s),
        ]
    else:
        title = title.replace("EdgeLoc run", "Run", 1)
    sections += [links_section(s, plots), radio_section(s, plots)]
    sections += [paths_section(data, s.get("per_vehicle"), s["links"].get("linktest"))]
    sections += [apps_section(data), traffic_section(data), load_section(s)]
    sections += [nodes_section(s), recording_section(data, s)]
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


__all__ = [
    "FORMATS",
    "SUMMARY_VERSION",
    "Report",
    "ReportInputError",
    "build_report",
    "clean_json",
    "report_after_run",
    "summarize",
    "summary_json",
]


#: Why a run's report has no split comparison when its scenario says `report.compare: false`.
NOT_COMPARED = (
    "the scenario's report.compare is false; `testbed report {folder} --compare` computes it"
)


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
