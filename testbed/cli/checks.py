"""Verbs that measure this host rather than run anything on it: `check` (the preflight: kernel
features, ROS, torch, the link backend `auto` picks) and `link-test` (a scenario's links
against their profiles)."""

from __future__ import annotations

import json
import sys
from typing import Annotated

import typer

from testbed import console as con
from testbed.cli.common import EXIT_FAILED, EXIT_HOST, KNOWN_ERRORS, JsonFlag, ScenarioFile, fail


def link_test(
    file: ScenarioFile,
    json_out: JsonFlag = False,
    quick: Annotated[
        bool, typer.Option("--quick", help="Shorter probes (what `testbed run` does).")
    ] = False,
    links: Annotated[
        list[str] | None,
        typer.Option(
            "--link",
            metavar="LINK",
            help="Measure only this link (repeatable), e.g. --link av1-gnb1. Default: every link.",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Bring the scenario's network up, measure every link direction (RTT, one-way delay,
    TCP/UDP goodput, loss over 10,000 datagrams) against its profile, tear down.

    First it says which link rates this host's relay cannot carry (as `validate --host`; in
    the JSON as `capacity`). Exits 1 when a figure is out of tolerance (delay 0.5 ms over the
    measured baseline, rate 5% of configured x payload fraction, loss 0.5 percentage points).

    A radio direction is also measured against its closed-form oracle: one-way delay CDFs
    side by side, their Wasserstein-1 and KS distances, HARQ retransmission shares against
    the BLER (4 sigma) and what each slot carried while saturated. Its W1 tolerance is this
    host's (its timer floor, measured and printed) plus what the number of probes allows by
    chance. Examples: testbed link-test scenarios/smoke.yaml --quick; testbed link-test
    scenarios/nr_cell.yaml --link av1-gnb1 (the air link alone; a run does the same with
    `report: {link_test: [av1-gnb1]}`)
    """
    from testbed.capacity import check_scenario
    from testbed.linktest import check_link_names
    from testbed.linktest import link_test as measure
    from testbed.scenario import ScenarioError, load

    try:
        scenario = load(file)
    except ScenarioError as err:
        raise fail(err) from None
    progress = None if json_out else con.plain
    try:
        check_link_names(scenario.links.names(), links, f"scenario {scenario.name!r}")
        capacity = check_scenario(scenario, progress=progress)
        report = measure(scenario, quick=quick, progress=progress, capacity=capacity, links=links)
    except KNOWN_ERRORS as err:
        raise fail(err) from None
    if json_out:
        sys.stdout.write(json.dumps(report.to_dict(), indent=2) + "\n")
    else:
        con.plain(f"link backend: {report.backend}")
        for line in report.text().splitlines():
            con.plain(line)
    if not report.ok:
        if not json_out:
            con.error("a link is out of tolerance (rows marked OUT)")
        raise typer.Exit(EXIT_FAILED)
    if not json_out:
        con.ok(f"every link within tolerance ({report.seconds:.1f} s)")


def check(json_out: JsonFlag = False) -> None:
    """Preflight: try every kernel feature, ROS and torch; say which link backend `auto` picks.

    Exits 3 when something a run needs is missing.
    """
    from testbed.check import run_checks

    result = run_checks()
    if json_out:
        sys.stdout.write(json.dumps(result.to_dict(), indent=2) + "\n")
    else:
        con.table(
            ["capability", "needed", "ok", "detail"],
            [
                [c.name, "yes" if c.required else "", "yes" if c.ok else "NO", c.detail]
                for c in result.checks
            ],
        )
        con.plain(f"link backend for 'auto': {result.auto_backend}")
        if result.runnable:
            con.ok("this host can run the testbed")
    if not result.runnable:
        con.error("cannot run: missing " + ", ".join(result.missing))
        raise typer.Exit(EXIT_HOST)
