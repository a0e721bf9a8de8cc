"""Verbs about scenario files, before anything is built: `validate` (the schema, then with
--host this host's data plane) and `schema` (the JSON Schema, for editors, or the field reference
in Markdown)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from testbed import console as con
from testbed.cli.common import EXIT_BAD_INPUT, EXIT_HOST, KNOWN_ERRORS, fail
from testbed.errors import HostError


def validate(
    files: Annotated[
        list[Path],
        typer.Argument(help="Scenario YAML files.", show_default=False, metavar="FILE..."),
    ],
    host: Annotated[
        bool,
        typer.Option(
            "--host",
            help=(
                "Also check the link rates against what this host's userspace data plane "
                "carries (measured in throwaway namespaces, a few seconds, cached for a day; "
                "root)."
            ),
        ),
    ] = False,
) -> None:
    """Check scenario files against schema v1 and report every error with file:line:column.

    With --host, also say which link rates this host cannot emulate: where the links are the
    userspace relay (no sch_netem), a rate above what the relay carries even for TCP is an
    error, one above what it carries one packet at a time (UDP without GSO, as ROS 2 DDS
    sends) a note. Exits 2 for a bad file, 3 for such an error (or without root), 0 with notes.

    Example: testbed validate scenarios/*.yaml ; sudo testbed validate --host scenarios/default.yaml
    """
    from testbed.scenario import ScenarioError, load
    from testbed.scenario.model import from_channel, from_route

    bad = 0
    scenarios = []
    for path in files:
        try:
            scenario = load(path)
        except ScenarioError as err:
            bad += 1
            for line in str(err).splitlines():
                con.error(line)
            continue
        scenarios.append((path, scenario))
        extra = [
            f"{n} {what}"
            for n, what in (
                (len(scenario.apps), "app(s)"),
                (len(scenario.traffic), "traffic flow(s)"),
                (len(scenario.record.topics), "recorded topic pattern(s)"),
            )
            if n
        ]
        if scenario.workload.kind == "none":
            extra.append("no EdgeLoc workload")
        by_channel = sum(map(from_channel, scenario.timeline))
        by_route = sum(map(from_route, scenario.timeline))
        if by_channel:
            extra.append(f"{by_channel} radio change(s) from the channel")
        if by_route > by_channel:
            extra.append(f"{by_route - by_channel} handover(s)")
        con.ok(
            f"{path}: valid ({len(scenario.topology.vehicles)} vehicle(s), "
            f"{len(scenario.topology.cells)} cell(s), "
            f"{len(scenario.timeline) - by_route} timeline event(s)"
            + "".join(f", {e}" for e in extra)
            + ")"
        )
        if scenario.channel is not None:
            from testbed.mobility import coverage_notes

            for note in coverage_notes(scenario):
                con.plain(f"note: {path}: {note}")
    host_failed = False
    if host and scenarios:
        try:
            host_failed = _validate_host(scenarios) > 0
        except typer.Exit:
            if not bad:  # a bad file is the first thing to fix: its exit code wins
                raise
    if bad:
        raise typer.Exit(EXIT_BAD_INPUT)
    if host_failed:
        raise typer.Exit(EXIT_HOST)


def _validate_host(scenarios: list[tuple[Path, Any]]) -> int:
    """`validate --host`: each scenario's link rates against this host's data plane (measured
    once for all); prints them per file and returns how many files have an error."""
    from testbed import capacity
    from testbed.links import choose_backend
    from testbed.namespaces import require_root

    try:
        require_root()  # the netem probe and the measurement make namespaces
    except HostError as err:
        raise fail(HostError(f"validate --host: {err}")) from None
    failed = 0
    plane = None
    for path, scenario in scenarios:
        try:
            backend = choose_backend(scenario)
        except HostError as err:  # `backend: tc` on a kernel without netem, needing netem
            failed += 1
            con.error(f"{path}: {err}")
            continue
        if backend.name != "userspace":
            con.ok(f"{path}: links on {backend.describe()}: not limited by the relay")
            continue
        if plane is None:
            try:
                plane = capacity.host_data_plane(progress=con.plain)
            except KNOWN_ERRORS as err:
                raise fail(err) from None
            con.plain(f"host data plane: {plane.text()}; {plane.source()}")
        warnings = capacity.check_links(scenario, plane)
        failed += any(w.level == "error" for w in warnings)
        if not warnings:
            con.ok(f"{path}: every link rate is within what this host's relay carries")
        for w in warnings:
            if w.level == "error":
                con.error(f"{path}: {w.message}")
            else:
                con.plain(f"note: {path}: {w.message}")
    return failed


def schema(
    markdown: Annotated[
        bool,
        typer.Option(
            "--markdown",
            help=(
                "Print the field reference in Markdown instead: every field's path, type, "
                "range, default and meaning."
            ),
        ),
    ] = False,
) -> None:
    """Print the scenario JSON Schema (for editors), or with --markdown the field reference.

    Save it and point your YAML at it:
    testbed schema > scenario.schema.json, then put
    '# yaml-language-server: $schema=scenario.schema.json' at the top of a scenario.
    """
    if markdown:
        from testbed.scenario import reference

        sys.stdout.write(reference.markdown())
        return
    from testbed.scenario import json_schema

    sys.stdout.write(json.dumps(json_schema(), indent=2) + "\n")
