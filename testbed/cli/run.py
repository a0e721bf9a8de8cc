"""Verbs of a whole experiment: `run` plays a scenario over a network it builds and tears
down, then reports on it; `report` rebuilds a run's report from its run.mcap."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from testbed import console as con
from testbed.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    KNOWN_ERRORS,
    RunsDir,
    ScenarioFile,
    fail,
)
from testbed.folders import check_writable_folder


def run(
    file: ScenarioFile,
    runs_dir: RunsDir = Path("runs"),
    no_capacity_check: Annotated[
        bool,
        typer.Option(
            "--no-capacity-check",
            help=(
                "Skip the check of the link rates against this host's userspace data plane "
                "before the run (which measures it, a few seconds, when no figure is cached)."
            ),
        ),
    ] = False,
) -> None:
    """Run a scenario: build its network, check every vehicle reaches its edge server with real
    packets, run the EdgeLoc ROS 2 nodes in the namespaces while the timeline plays, tear down,
    and leave runs/<run-id>/ (run.json with node stats and link byte counters,
    logs/<host>.<node>.log and logs/app.<name>.log, nodes/<host>.<node>.json, connectivity.json,
    linktest.json, links.json, events.jsonl, scenario.yaml, pcap/<link>.pcapng when captured,
    run.mcap) with the report built from run.mcap (report.html, report.md,
    summary.json, plots/, trajectories/); the last lines are the headline numbers and the
    report's path. A run that fails or is interrupted still gets a (partial) report when
    anything was recorded. Before it starts, it says which link rates this host's relay cannot
    carry (as `validate --host`; it never fails the run).

    Example: testbed run scenarios/default.yaml
    """
    from testbed.run import run_scenario
    from testbed.scenario import ScenarioError, load

    try:
        scenario = load(file)
    except ScenarioError as err:
        raise fail(err) from None
    try:
        result = run_scenario(
            scenario, runs_dir, progress=con.plain, capacity_check=not no_capacity_check
        )
    except (*KNOWN_ERRORS, KeyboardInterrupt) as err:
        folder = getattr(err, "run_folder", None)
        if folder is not None and scenario.report.enabled:
            # After Ctrl-C the user wants out: no K + 2 replays (`testbed report` adds them).
            skip = (
                f"the run was interrupted; `testbed report {folder}` computes it"
                if isinstance(err, KeyboardInterrupt)
                else scenario.report.compare
            )
            _report_after_run(
                Path(folder), scenario.report.formats, scenario.report.plots, splits=skip
            )
        if isinstance(err, KeyboardInterrupt):
            raise
        raise fail(err) from None
    if not result.ok:
        con.error(
            f"run {result.run_id}: a vehicle could not reach its edge server "
            f"(see {result.folder / 'connectivity.json'})"
        )
    else:
        t = result.timings_s
        con.ok(
            f"run {result.run_id} ok: every vehicle reached its edge server; up "
            f"{t['up'] * 1000:.0f} ms, down {t['down'] * 1000:.0f} ms; results in {result.folder}/"
        )
    for link, cap in result.captures.items():
        if "error" in cap:
            con.warn(f"capture of {link}: {cap['error']}")
            continue
        n = cap["packets"]
        con.plain(
            f"capture {link}: {result.folder / cap['path']} ({n['uplink']} uplink, "
            f"{n['downlink']} downlink packets; open in Wireshark)"
        )
    if scenario.report.enabled:  # last: the headline numbers and where the report is
        _report_after_run(
            result.folder,
            scenario.report.formats,
            scenario.report.plots,
            splits=scenario.report.compare,
        )
    if not result.ok:
        raise typer.Exit(EXIT_FAILED)


def _report_after_run(
    folder: Path, formats: tuple[str, ...], plots: bool, splits: bool | str = True
) -> None:
    """Build a run's report from its run.mcap and print the headline and the report's path.
    A report that cannot be built is a warning: the run's own outcome decides the exit code."""
    from reports.build import report_after_run

    t0 = time.perf_counter()
    built, why_not = report_after_run(folder, formats, plots, splits)
    if built is None:
        con.warn(f"no report: {why_not}")
        return
    con.plain(built.headline)
    partial = " (partial)" if built.partial else ""
    con.plain(f"report: {built.main_file}{partial}, built in {time.perf_counter() - t0:.1f} s")


def report(
    run_folder: Annotated[
        Path,
        typer.Argument(
            help="A run folder holding run.mcap (or a run id under runs/).", show_default=False
        ),
    ],
    formats: Annotated[
        str, typer.Option("--formats", metavar="LIST", help="Comma-separated: html, md, json.")
    ] = "html,md,json",
    no_plots: Annotated[bool, typer.Option("--no-plots", help="Skip the figures.")] = False,
    compare: Annotated[
        bool,
        typer.Option(
            "--compare/--no-compare",
            help="Replay EdgeLoc with every measured split held fixed and the per-phase oracle "
            "under the run's measured latencies (K + 2 replays, torch).",
        ),
    ] = True,
) -> None:
    """Build a run's report from its run.mcap alone: report.html (self-contained, figures
    embedded), report.md, summary.json, plots/*.png and trajectories/<vehicle>/*.tum (TUM, for
    evo). Rebuilding gives the same summary.json anywhere (run.json, with the paths to the
    edge, apps and cross-traffic, is attached to run.mcap); a recording cut short gives a
    partial report that says so.

    Examples:

      testbed report runs/4a2cf3

      testbed report 4a2cf3 --formats json --no-compare   # summary.json and trajectories/

    Exits 2 when the folder has no readable run.mcap or this user cannot write in it.
    """
    from reports.build import FORMATS, build_report

    folder = run_folder
    if not folder.exists() and not folder.is_absolute() and (Path("runs") / folder).is_dir():
        folder = Path("runs") / folder  # a bare run id
    wanted = tuple(f.strip() for f in formats.split(",") if f.strip())
    bad = [f for f in wanted if f not in FORMATS]
    if bad or not wanted:
        con.error(
            f"--formats: unknown {', '.join(bad) or '(none given)'}; use {', '.join(FORMATS)}"
        )
        raise typer.Exit(EXIT_BAD_INPUT)
    if not folder.is_dir():
        found = "a file, not a run folder" if folder.exists() else "no such run folder"
        con.error(f"{run_folder}: {found}")
        raise typer.Exit(EXIT_BAD_INPUT)
    try:
        check_writable_folder(folder, "run folder")  # the report is written beside run.mcap
        built = build_report(folder, formats=wanted, plots=not no_plots, splits=compare)
    except KNOWN_ERRORS as err:
        raise fail(err) from None
    for line in built.summary["recording"]["problems"]:
        con.warn(line)
    con.plain(built.headline)
    con.ok(f"report: {built.main_file}" + (" (partial)" if built.partial else ""))
