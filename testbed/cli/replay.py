"""The `replay` verb: a scenario's EdgeLoc workload in one process (testbed.replay), and the
tables and lines it prints of the replay's summary (per method, per bandwidth phase, per
split policy) or of its latency model against a real run (--against)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from testbed import console as con
from testbed.cli.common import KNOWN_ERRORS, JsonFlag, RunsDir, ScenarioFile, fail


def replay(
    file: ScenarioFile,
    runs_dir: RunsDir = Path("runs"),
    json_out: JsonFlag = False,
    compare: Annotated[
        bool,
        typer.Option(
            "--compare/--no-compare",
            help="Also replay EdgeLoc with every fixed split and the per-phase oracle "
            "(K + 2 more replays).",
        ),
    ] = True,
    against: Annotated[
        Path | None,
        typer.Option(
            "--against",
            help="A run folder of `testbed run` of this scenario: print, per split, its "
            "measured request latency beside the model's for the same requests (with "
            "--json, as JSON), and do nothing else.",
        ),
    ] = None,
    vehicle: Annotated[
        str | None,
        typer.Option(
            "--vehicle",
            metavar="NAME",
            help="Replay this EdgeLoc vehicle's path (default: the first); with --against, "
            "compare its requests (default: the first vehicle that made any).",
        ),
    ] = None,
) -> None:
    """Replay the scenario's EdgeLoc workload in one process (no network, faster than real
    time): VO, DNN, Kalman and EdgeLoc errors beside the paper's, the learner per bandwidth
    phase, and EdgeLoc with every fixed split and the oracle on the same drive; writes
    runs/<id>/summary.json and TUM trajectories.

    Examples: testbed replay scenarios/default.yaml;
    testbed replay scenarios/nr_cell.yaml --against runs/e91fff;
    testbed replay scenarios/multi_vehicle_nr.yaml --vehicle av4
    """
    from testbed.replay import latency_against_run, replay_scenario
    from testbed.scenario import load

    if against is not None:
        try:
            agreement = latency_against_run(load(file), against, vehicle=vehicle)
        except KNOWN_ERRORS as err:
            raise fail(err) from None
        if json_out:
            sys.stdout.write(json.dumps(agreement.to_dict(), indent=2) + "\n")
            return
        con.table(
            ["split", "requests", "measured ms", "model ms", "measured / model"],
            [
                [
                    a.split,
                    str(a.requests),
                    f"{a.measured_s * 1000:.1f}",
                    f"{a.model_s * 1000:.1f}",
                    f"{a.ratio:.2f}",
                ]
                for a in agreement.rows
            ],
        )
        con.plain(
            f"fixed overhead per request: {agreement.overhead_s * 1000:.1f} ms, from "
            f"{agreement.overhead_from}"
        )
        if agreement.neighbours:
            con.plain(
                f"the cell shared with {agreement.neighbours} other EdgeLoc vehicle(s): their "
                f"{agreement.neighbour_requests} uplink requests beside these in the slot model"
            )
        worst = agreement.worst()
        con.plain(f"largest disagreement: {worst * 100:.0f}% (the model's requests are the run's)")
        return

    try:
        done = replay_scenario(load(file), runs_dir, compare=compare, vehicle=vehicle)
    except KNOWN_ERRORS as err:
        raise fail(err) from None
    if json_out:
        sys.stdout.write(json.dumps(done.summary, indent=2) + "\n")
        return
    con.table(REPLAY_HEADERS, replay_rows(done.summary))
    for line in replay_phase_lines(done.summary):
        con.plain(line)
    if "radio" in done.summary:
        from nodes.edgeloc.bands import AROUND_S, around_lines, lines

        radio = done.summary["radio"]
        con.plain(f"{radio['vehicle']}'s plays by the uplink MCS the channel gave them:")
        for line in lines(radio["by_uplink_mcs"]):
            con.plain(f"  {line}")
        if radio.get("handovers"):
            con.plain(f"{radio['vehicle']}'s handovers, {AROUND_S:g} s before and after each:")
            for line in around_lines(radio["handovers"]):
                con.plain(f"  {line}")
    splits = done.summary.get("splits")
    if splits:
        con.table(split_headers(splits), split_rows(splits))
        for line in split_phase_lines(splits):
            con.plain(line)
    resets = done.summary["learner"]["resets"]
    con.plain(f"detector resets: {len(resets)}; compute: {done.result.latency.compute.source}")
    con.plain(f"wrote {done.folder}/ (summary.json, *.tum) in {done.result.wall_s:.1f} s")
    con.plain(str(done.summary["headline"]))


REPLAY_HEADERS = ["method", "total m", "mean m", "median m", "rmse m", "p95 m", "max m", "yaw deg"]


def replay_rows(summary: dict[str, Any]) -> list[list[str]]:
    """Per method, the replay's position error figures and its mean heading error."""
    rows = []
    for m in ("vo", "dnn", "kalman", "edgeloc"):
        p, h = summary["methods"][m]["position_m"], summary["methods"][m]["heading_deg"]
        figures = [p["total"], p["mean"], p["median"], p["rmse"], p["p95"], p["max"], h["mean"]]
        rows.append([m, f"{figures[0]:.1f}", *(f"{x:.2f}" for x in figures[1:])])
    return rows


def replay_phase_lines(summary: dict[str, Any]) -> list[str]:
    """One line per bandwidth phase: what the learner chose against the best in hindsight."""
    lines = []
    for ph in summary["learner"]["phases"]:
        rate = ph["uplink_rate_bps"]
        uplink = "unlimited" if rate is None or rate == math.inf else f"{rate / 1e6:g} Mbit/s"
        converged = (
            "never converged)"
            if ph["converged_after_s"] is None
            else f"converged after {ph['converged_after_plays']} plays, "
            f"{ph['converged_after_s']:.1f} s)"
        )
        lines.append(
            f"phase {ph['start_s']:g}-{ph['end_s']:g} s, uplink {uplink}: "
            f"chose {ph['chosen']}, best in hindsight {ph['best_in_hindsight']} "
            f"({100 * ph['share_best']:.0f}% of {ph['plays']} plays, "
            f"{100 * ph['share_best_last_third']:.0f}% in the last third; " + converged
        )
    return lines


def split_headers(splits: dict[str, Any]) -> list[str]:
    phases = [f"{p['start_s']:g}-{p['end_s']:g} s err m / ms" for p in splits["phases"]]
    return ["EdgeLoc with", "total m", *phases]


def split_rows(splits: dict[str, Any]) -> list[list[str]]:
    """Per policy (learned, each fixed split, oracle): total error and, per phase, mean error
    and mean request latency."""
    rows = []
    for r in splits["rows"]:
        cells = []
        for f in r["phases"]:
            lat = f["mean_latency_s"]
            cells.append(
                f"{f['mean_error_m']:.2f} / " + ("-" if lat is None else f"{lat * 1e3:.0f}")
            )
        rows.append([r["policy"], f"{r['total_m']:.1f}", *cells])
    return rows


def _monotone_note(phase: dict[str, Any]) -> str:
    if phase["monotone"] in (True, None):
        return ""
    if phase.get("monotone_within_noise"):  # absent from summaries written before it
        return "; error not monotone in latency, within the drive's noise"
    return "; error not monotone in latency"


def split_phase_lines(splits: dict[str, Any]) -> list[str]:
    """Per phase, the fastest and the most accurate split; then where they disagree."""
    lines = [
        f"phase {p['start_s']:g}-{p['end_s']:g} s: fastest {p['latency_best']}, most accurate "
        f"{p['error_best']}" + _monotone_note(p)
        for p in splits["phases"]
    ]
    beats = splits["learned_beats_fixed"]
    if beats is not None:
        lines.append(
            f"learned {'beats' if beats else 'does not beat'} every fixed split "
            f"(best fixed: {splits['best_fixed']}; latencies: {splits['latency_source']})"
            + (
                ", within the drive's noise"
                if splits.get("learned_beats_fixed_within_noise") and not beats
                else ""
            )
        )
    return lines
