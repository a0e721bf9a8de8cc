"""`testbed`: the command line. Verbs read as sentences; the work lives in other modules.

Exit codes mean the same thing for every verb:
  0  done as asked
  1  the run or the measurement failed (a node died, a link out of tolerance)
  2  bad input (scenario file, option, unknown run id, a folder that cannot be written)
  3  this host cannot do it (not root, a kernel feature or ROS 2 missing, a link rate beyond
     its relay)
  130 interrupted (Ctrl-C); everything created was removed
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from netem.errors import NetemError, ProfileError
from netem.traces import TraceError
from nodes.edgeloc.errors import EdgeLocError
from nodes.recording import RecordingError
from nodes.ros.env import RosEnvError
from nodes.ros.errors import RosError
from reports.errors import ReportError, ReportInputError
from testbed import console as con
from testbed.errors import BadInput, HostError, TestbedError
from testbed.folders import check_writable_folder

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_HOST, EXIT_INTERRUPTED = 0, 1, 2, 3, 130

#: The one place an error's type becomes an exit code: the first row whose type matches wins,
#: so the more specific types come first. Every package's error root is in it.
EXIT_CODES: tuple[tuple[type[Exception], int], ...] = (
    (BadInput, EXIT_BAD_INPUT),  # scenarios (ScenarioError), options, run ids
    (ProfileError, EXIT_BAD_INPUT),
    (TraceError, EXIT_BAD_INPUT),
    (ReportInputError, EXIT_BAD_INPUT),
    (RosEnvError, EXIT_BAD_INPUT),
    (HostError, EXIT_HOST),
    (TestbedError, EXIT_FAILED),
    (NetemError, EXIT_FAILED),
    (RecordingError, EXIT_FAILED),
    (ReportError, EXIT_FAILED),
    (EdgeLocError, EXIT_FAILED),
    (RosError, EXIT_FAILED),
)
#: What a verb turns into a message and an exit code instead of a traceback.
KNOWN_ERRORS = tuple(kind for kind, _ in EXIT_CODES)


def exit_code(err: BaseException) -> int:
    """The exit code `err` means (EXIT_CODES); 1 for anything else."""
    return next((code for kind, code in EXIT_CODES if isinstance(err, kind)), EXIT_FAILED)


app = typer.Typer(
    name="testbed",
    help=(
        "Emulate a 5G UE-gNB-core network in Linux namespaces and run EdgeLoc over it.\n\n"
        "Typical session:\n\n"
        "  testbed check                      # can this host run it?\n\n"
        "  testbed validate scenarios/*.yaml  # are my scenarios right?\n\n"
        "  testbed up scenarios/default.yaml  # build the network, leave it up\n\n"
        "  testbed status ; testbed down      # see it, tear it down\n\n"
        "  testbed run scenarios/default.yaml # the whole experiment\n\n"
        "  testbed report runs/<id>           # rebuild its report from run.mcap\n\n"
        "  testbed sweep FILE --set KEY=A,B   # a grid of variants, one comparison"
    ),
    epilog=(
        "Exit codes, the same for every command: 0 done as asked; 1 the run or the "
        "measurement failed (a node died, a link out of tolerance); 2 bad input (a scenario "
        "file, an option, an unknown run id, a folder that cannot be written); 3 this host "
        "cannot do it (not root, a kernel feature or ROS 2 missing, a link rate beyond its "
        "relay); 130 interrupted (Ctrl-C), everything created removed."
    ),
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
)

ScenarioFile = Annotated[
    Path,
    typer.Argument(help="Scenario YAML file.", show_default=False, dir_okay=False, metavar="FILE"),
]
JsonFlag = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON.")]
RunsDir = Annotated[Path, typer.Option("--runs-dir", help="Where run folders go.", file_okay=False)]
HostsEngine = Annotated[
    str,
    typer.Option(
        "--engine",
        metavar="local|ray",
        help="local: this host only; ray: every host of topology.hosts, each on its own Ray "
        "node (the one offering the resource testbed-host-<name>; pip install '.[ray]').",
    ),
]
HostsAddress = Annotated[
    str,
    typer.Option(
        "--address",
        metavar="ADDRESS",
        help="--engine ray: the Ray cluster: auto (a running one) or HOST:PORT.",
    ),
]


def _fail(err: BaseException) -> typer.Exit:
    for line in str(err).splitlines():
        con.error(line)
    return typer.Exit(exit_code(err))


def _check_engine(engine: str, ray_options: dict[str, tuple[str, str]]) -> None:
    """--engine is local or ray, and the options only Ray reads ({option: (value, default)})
    are left alone with local: a cluster address given to a local run was silently ignored."""
    if engine not in ("local", "ray"):
        raise _fail(BadInput(f"--engine: expected local or ray, found {engine!r}"))
    given = [name for name, (value, default) in ray_options.items() if value != default]
    if engine == "local" and given:
        it = "it" if len(given) == 1 else "them"
        raise _fail(
            BadInput(
                f"{', '.join(given)}: only --engine ray uses {it}; add --engine ray or leave "
                f"{it} out"
            )
        )


@app.command()
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
        raise _fail(HostError(f"validate --host: {err}")) from None
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
                raise _fail(err) from None
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


@app.command()
def schema() -> None:
    """Print the scenario JSON Schema (for editors).

    Save it and point your YAML at it:
    testbed schema > scenario.schema.json, then put
    '# yaml-language-server: $schema=scenario.schema.json' at the top of a scenario.
    """
    from testbed.scenario import json_schema

    sys.stdout.write(json.dumps(json_schema(), indent=2) + "\n")


@app.command()
def up(
    file: ScenarioFile,
    dry_run: Annotated[
        bool,
        typer.Option(
            "--dry-run",
            help="Print the equivalent ip/tc (and relay) commands and build nothing (as root, "
            "the sch_netem probe of backend auto/tc makes and removes one throwaway namespace; "
            "without root, auto is taken to mean the relay).",
        ),
    ] = False,
    host: Annotated[
        str | None,
        typer.Option(
            "--host",
            help=(
                "Build only this host's part of a topology across hosts (topology.hosts): its "
                "nodes, the links among them, and its VXLAN ends of the links to the others. "
                "Without it, every node is built here."
            ),
            show_default=False,
        ),
    ] = None,
    run_id: Annotated[
        str | None,
        typer.Option(
            "--run-id",
            metavar="ID",
            help=(
                "The run id (6 lowercase hex characters) instead of a fresh one. Every host of "
                "a topology across hosts is given the same: its tunnels' VNIs come from it."
            ),
            show_default=False,
        ),
    ] = None,
    engine: HostsEngine = "local",
    address: HostsAddress = "auto",
) -> None:
    """Build the scenario's network (namespaces, links, routes) and leave it up.

    A topology across hosts is built one part per host, each with the same run id (the first
    `up` prints the command for the others):

      sudo testbed up FILE --host a --run-id 4a2cf3   # on host a

      sudo testbed up FILE --host b --run-id 4a2cf3   # on host b

    or from any one of them, each host's part by a Ray task on that host's node (started with
    `ray start ... --resources='{"testbed-host-a": 1}'`; see the README):

      sudo testbed up FILE --engine ray --address HEAD:6379

    Example: testbed up scenarios/default.yaml ; ip netns exec <ns> ping ... ; testbed down
    """
    from testbed.scenario import ScenarioError, load
    from testbed.topology import build

    _check_engine(engine, {"--address": (address, "auto")})
    try:
        scenario = load(file)
    except ScenarioError as err:
        raise _fail(err) from None
    hosts = [h.name for h in scenario.topology.hosts]
    if engine == "ray":
        _up_on_ray(file, hosts, run_id, address, host=host, dry_run=dry_run)
        return
    if host is None and len(hosts) > 1:
        con.plain(
            f"note: topology.hosts names {', '.join(hosts)}; building every node here "
            "(--host NAME builds one host's part)"
        )
    try:
        net = build(
            scenario,
            dry_run=dry_run,
            echo=con.plain if dry_run else None,
            run_id=run_id,
            host=host,
        )
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
    if dry_run:
        return
    nodes = net.local_nodes()
    where = f" on host {host}" if host is not None else ""
    across = f", {len(net.tunnels)} to other hosts" if net.tunnels else ""
    con.ok(
        f"run {net.run_id} is up{where}: {len(nodes)} namespaces, "
        f"{len(net.local_links())} links{across}"
    )
    con.plain(f"link backend: {net.backend_text()}")
    for node in nodes:
        con.plain(f"  {node.name:<10} {node.role:<8} {node.netns:<18} {node.addresses()}")
    for tunnel in net.tunnels.values():
        con.plain(f"  {tunnel.describe()}")
    others = [h for h in hosts if h != host] if host is not None else []
    if others:
        con.plain("build the other hosts' parts with the same run id:")
        for other in others:
            con.plain(f"  testbed up {file} --host {other} --run-id {net.run_id}")
    con.plain(f"tear down with: testbed down {net.run_id}" + (" (on each host)" if others else ""))


def _up_on_ray(
    file: Path, hosts: list[str], run_id: str | None, address: str, host: str | None, dry_run: bool
) -> None:
    """`up --engine ray`: each host's part on its Ray node (testbed.multihost); per host what
    it built, or why it failed (the hosts that came up are then taken down again)."""
    from testbed.multihost import up_on_ray

    if host is not None or dry_run:
        raise _fail(
            BadInput(
                f"--engine ray builds every host's part; {'--host' if host else '--dry-run'} is "
                "for one host (testbed up FILE --dry-run --host NAME prints its commands)"
            )
        )
    if len(hosts) < 2:
        raise _fail(
            BadInput(
                f"--engine ray builds a topology across hosts, and {file} has "
                f"{'one host' if hosts else 'no topology.hosts'}: `testbed up {file}` builds it "
                "here"
            )
        )
    try:
        outcome = up_on_ray(file, hosts, run_id, address, progress=con.plain)
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
    for part in outcome.parts:
        if part.ok:
            con.ok(f"host {part.host} ({part.machine}): up in {part.seconds:.1f} s")
            for line in part.result():
                con.plain(f"  {line}")
        else:
            con.error(f"host {part.host} ({part.machine}): `testbed up` failed (exit {part.code})")
            for line in part.lines[-6:]:
                con.plain(f"  {line}")
    for part in outcome.undone:
        if part.ok:
            con.plain(f"host {part.host}: taken down again: {part.lines[-1] if part.lines else ''}")
        else:
            con.error(
                f"host {part.host} could not be taken down again: run `testbed down "
                f"{outcome.run_id}` there ({part.lines[-1] if part.lines else part.code})"
            )
    if outcome.failed:
        code = outcome.failed[0].code
        raise typer.Exit(code if code in (EXIT_FAILED, EXIT_BAD_INPUT, EXIT_HOST) else EXIT_FAILED)
    where = "" if address == "auto" else f" --address {address}"
    con.ok(
        f"run {outcome.run_id} is up on {len(outcome.parts)} hosts "
        f"({', '.join(p.host for p in outcome.parts)}) in {outcome.seconds:.1f} s"
    )
    con.plain(f"tear down with: testbed down {outcome.run_id} --engine ray{where}")


@app.command()
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
        raise _fail(err) from None
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
        raise _fail(err) from None
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

    built, why_not = report_after_run(folder, formats, plots, splits)
    if built is None:
        con.warn(f"no report: {why_not}")
        return
    con.plain(built.headline)
    con.plain(f"report: {built.main_file}" + (" (partial)" if built.partial else ""))


@app.command()
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
        raise _fail(err) from None
    for line in built.summary["recording"]["problems"]:
        con.warn(line)
    con.plain(built.headline)
    con.ok(f"report: {built.main_file}" + (" (partial)" if built.partial else ""))


@app.command()
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
            raise _fail(err) from None
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
        raise _fail(err) from None
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


@app.command()
def sweep(
    file: ScenarioFile,
    sets: Annotated[
        list[str],
        typer.Option(
            "--set",
            metavar="KEY=V1,V2",
            help="KEY=V1,V2,...: a scenario field (dotted path) and its values; repeat for a "
            "grid. Values are written as in the YAML (8ms, 20mbit, 0.5%, [image,conv3]).",
            show_default=False,
        ),
    ],
    real: Annotated[
        bool, typer.Option("--real", help="Run each variant for real (testbed run; root).")
    ] = False,
    out: Annotated[
        Path | None,
        typer.Option("--out", help="Report folder (default: runs/sweep-<id>/).", file_okay=False),
    ] = None,
    duration: Annotated[
        str | None,
        typer.Option(
            "--duration",
            metavar="TIME",
            help="Play every variant for this long (e.g. 10s). Shorter than the scenario: "
            "timeline times and outage lengths scale with it; longer: its last phase is "
            "lengthened.",
            show_default=False,
        ),
    ] = None,
    engine: Annotated[
        str,
        typer.Option(
            "--engine",
            metavar="local|ray",
            help="local: run the variants one by one here; ray: each run is a Ray task on a "
            "cluster (pip install '.[ray]'), its folder copied back into --out.",
        ),
    ] = "local",
    address: Annotated[
        str,
        typer.Option(
            "--address",
            metavar="ADDRESS",
            help="--engine ray: auto (a running cluster), HOST:PORT, or local (start a "
            "one-host cluster for this sweep).",
        ),
    ] = "auto",
    ray_resource: Annotated[
        str,
        typer.Option(
            "--ray-resource",
            metavar="NAME",
            help="--engine ray: the custom resource a real run takes one unit of (each "
            "testbed host offers 1, so two real runs never share a host).",
        ),
    ] = "testbed",
    seeds: Annotated[
        int,
        typer.Option(
            "--seeds",
            metavar="N",
            help="Run each variant N times, with the scenario's seed and the N-1 after it; the "
            "report adds each figure's mean and 95% confidence interval, the plot error bars.",
            min=1,
        ),
    ] = 1,
) -> None:
    """Run a grid of variants of a scenario (offline replay, or real runs with --real) and
    write one comparison: DIR/sweep.json, sweep.md (variant values -> per-method total and
    mean error, EdgeLoc's reductions, split shares, mean latency) and sweep.png.

    Keys: dotted paths into the scenario (workload.learner.window, links.air.uplink.delay,
    topology.vehicles.av1.cpu, timeline[1].uplink); links.<link>.<direction>.<field> changes
    one link (an entry of links.overrides). Every variant is checked like `testbed validate`
    before anything runs.

    Examples:

      testbed sweep scenarios/latency_sweep.yaml --set links.air.uplink.delay=2ms,20ms,50ms

      testbed sweep scenarios/default.yaml --set workload.learner.window=20,100
      --set timeline[1].uplink=4mbit,8mbit --out runs/window-vs-squeeze

      sudo testbed sweep scenarios/smoke.yaml --set links.av1-gnb1.uplink.loss=0%,2% --real

      testbed sweep scenarios/default.yaml --set workload.fusion.method=paper,ekf --seeds 5

      sudo testbed sweep scenarios/smoke.yaml --set seed=1,2,3,4 --real --engine ray
    """
    from testbed.sweep import run_sweep
    from testbed.sweep.rayengine import RayOptions

    _check_engine(
        engine, {"--address": (address, "auto"), "--ray-resource": (ray_resource, "testbed")}
    )
    ray = RayOptions(address, ray_resource) if engine == "ray" else None
    try:
        report = run_sweep(
            file,
            sets,
            out=out,
            real=real,
            progress=con.plain,
            duration=duration,
            seeds=seeds,
            ray=ray,
        )
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
    for name in ("sweep.md", "sweep.json", "sweep.png"):
        con.plain(f"wrote {report.out / name}")
    if report.failed:
        con.error(f"{len(report.failed)} variant row(s) failed (see sweep.md)")
        raise typer.Exit(EXIT_FAILED)
    con.ok(f"sweep done: {len({r.index for r in report.rows})} variant(s) in {report.wall_s:.1f} s")


@app.command("link-test")
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
        raise _fail(err) from None
    progress = None if json_out else con.plain
    try:
        check_link_names(scenario.links.names(), links, f"scenario {scenario.name!r}")
        capacity = check_scenario(scenario, progress=progress)
        report = measure(scenario, quick=quick, progress=progress, capacity=capacity, links=links)
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
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


RunArg = Annotated[str, typer.Argument(help="Run id (see `testbed status`).", show_default=False)]
NodeArg = Annotated[
    str, typer.Argument(help="A node (namespace) of the run, e.g. av1.", show_default=False)
]


@app.command(
    "exec",
    context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
)
def exec_(
    run_id: RunArg,
    node: NodeArg,
    command: Annotated[
        list[str],
        typer.Argument(help="The command and its arguments, after --.", show_default=False),
    ],
) -> None:
    """Run a command inside a live run's namespace with that run's ROS environment (domain,
    Fast DDS profile, the node's unicast peers): your own ROS 2 tool meets the run's nodes.
    The exit code is the command's; Ctrl-C goes to it. `python` is the testbed's interpreter.

    Example: testbed exec 3fa2c1 av1 -- python my_listener.py --topic /av1/pose
    """
    from testbed.attach import Attachment

    try:
        Attachment.of(run_id, node).exec(command)
    except KNOWN_ERRORS as err:
        raise _fail(err) from None


@app.command("env")
def env_(run_id: RunArg, node: NodeArg) -> None:
    """Print the ROS environment of a live run's node as shell `export` lines, for a shell
    you opened in its namespace.

    Example: ip netns exec el-3fa2c1-av1 bash ; eval "$(testbed env 3fa2c1 av1)" ; ros2 topic list
    """
    from testbed.attach import Attachment

    try:
        lines = Attachment.of(run_id, node).shell_lines()
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
    sys.stdout.write("\n".join(lines) + "\n")


@app.command()
def down(
    run_id: Annotated[
        str | None, typer.Argument(help="Run id (default: the only live run).", show_default=False)
    ] = None,
    engine: HostsEngine = "local",
    address: HostsAddress = "auto",
) -> None:
    """Tear down a run made by `testbed up`: exactly what its state file records.

    A topology across hosts is torn down on each host: each removes its part (its nodes'
    namespaces, its VXLAN tunnels, relays and transit namespaces). With --engine ray, on every
    host whose Ray node offers a testbed-host-<name> resource, from any one of them:

      sudo testbed down 4a2cf3 --engine ray --address HEAD:6379
    """
    from testbed.topology import teardown_run

    _check_engine(engine, {"--address": (address, "auto")})
    if engine == "ray":
        _down_on_ray(run_id, address)
        return
    try:
        removed = teardown_run(run_id)
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
    con.ok(f"run {removed.run_id} is down ({removed.summary()})")


def _down_on_ray(run_id: str | None, address: str) -> None:
    """`down --engine ray`: `testbed down RUN_ID` on every host's Ray node; per host what it
    removed, or that it had nothing of the run."""
    from testbed.multihost import down_on_ray

    if run_id is None:
        raise _fail(BadInput("--engine ray: name the run: testbed down <run id> --engine ray"))
    try:
        parts = down_on_ray(run_id, address)
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
    for part in parts:
        if part.absent:
            con.plain(f"host {part.host} ({part.machine}): no run {run_id} there")
        elif part.ok:
            con.ok(f"host {part.host} ({part.machine}): {part.lines[-1] if part.lines else 'down'}")
        else:
            con.error(
                f"host {part.host} ({part.machine}): `testbed down` failed (exit {part.code})"
            )
            for line in part.lines[-6:]:
                con.plain(f"  {line}")
    failed = [p for p in parts if not p.ok]
    if failed:
        code = failed[0].code
        raise typer.Exit(code if code in (EXIT_FAILED, EXIT_BAD_INPUT, EXIT_HOST) else EXIT_FAILED)
    if all(p.absent for p in parts):
        raise _fail(
            BadInput(
                f"no host of the Ray cluster ({', '.join(p.host for p in parts)}) has run {run_id}"
            )
        )


@app.command()
def status(json_out: JsonFlag = False) -> None:
    """List runs on this host: live, detached (`up`) or dead (left by a crash)."""
    from testbed.state import list_runs

    runs = list_runs()
    if json_out:
        sys.stdout.write(json.dumps([r.describe() for r in runs], indent=2) + "\n")
        return
    if not runs:
        con.plain("no runs")
        return
    con.table(
        ["run", "state", "scenario", "namespaces", "started"],
        [
            [r.run_id, r.liveness(), r.scenario, str(len(r.namespaces)), r.started_text()]
            for r in runs
        ],
    )


@app.command()
def clean(
    all_runs: Annotated[
        bool, typer.Option("--all", help="Also tear down detached runs made by `testbed up`.")
    ] = False,
) -> None:
    """Remove what dead runs left: namespaces, links, qdiscs, TUN and VXLAN devices, processes,
    cgroups (on a topology across hosts, this host's part of them).

    Only this project's resources are touched (names prefixed 'el-' and runs in its state dir).
    A run whose orchestrator was killed gets its run.mcap: the parts its nodes recorded are
    merged once they are stopped.
    """
    from testbed.recording import finalise_orphans, unfinished_folders
    from testbed.topology import clean as clean_runs

    try:
        folders = unfinished_folders(include_detached=all_runs)  # before state files go
        report = clean_runs(include_detached=all_runs)
    except KNOWN_ERRORS as err:
        raise _fail(err) from None
    con.ok(report)
    failed = False
    for line in finalise_orphans(folders):
        bad = line.startswith("error: ")
        failed |= bad
        (con.error if bad else con.ok)(line.removeprefix("error: "))
    if failed:
        raise typer.Exit(EXIT_FAILED)


@app.command()
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


def main() -> None:
    try:
        app()
    except KeyboardInterrupt:
        con.error("interrupted")
        sys.exit(EXIT_INTERRUPTED)


if __name__ == "__main__":
    main()
