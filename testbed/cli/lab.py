"""Verbs of a network left up, the lab: `up` builds it, `exec` and `env` reach into its
namespaces, `status` lists the runs, `down` tears one down, `clean` removes what dead ones
left. A topology across hosts is built and torn down one part per host, or from one host with
--engine ray (testbed.multihost)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from testbed import console as con
from testbed.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_FAILED,
    EXIT_HOST,
    KNOWN_ERRORS,
    HostsAddress,
    HostsEngine,
    JsonFlag,
    ScenarioFile,
    check_engine,
    fail,
)
from testbed.errors import BadInput


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

    check_engine(engine, {"--address": (address, "auto")})
    try:
        scenario = load(file)
    except ScenarioError as err:
        raise fail(err) from None
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
        raise fail(err) from None
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
        raise fail(
            BadInput(
                f"--engine ray builds every host's part; {'--host' if host else '--dry-run'} is "
                "for one host (testbed up FILE --dry-run --host NAME prints its commands)"
            )
        )
    if len(hosts) < 2:
        raise fail(
            BadInput(
                f"--engine ray builds a topology across hosts, and {file} has "
                f"{'one host' if hosts else 'no topology.hosts'}: `testbed up {file}` builds it "
                "here"
            )
        )
    try:
        outcome = up_on_ray(file, hosts, run_id, address, progress=con.plain)
    except KNOWN_ERRORS as err:
        raise fail(err) from None
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


RunArg = Annotated[str, typer.Argument(help="Run id (see `testbed status`).", show_default=False)]


NodeArg = Annotated[
    str, typer.Argument(help="A node (namespace) of the run, e.g. av1.", show_default=False)
]


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
        raise fail(err) from None


def env_(run_id: RunArg, node: NodeArg) -> None:
    """Print the ROS environment of a live run's node as shell `export` lines, for a shell
    you opened in its namespace.

    Example: ip netns exec el-3fa2c1-av1 bash ; eval "$(testbed env 3fa2c1 av1)" ; ros2 topic list
    """
    from testbed.attach import Attachment

    try:
        lines = Attachment.of(run_id, node).shell_lines()
    except KNOWN_ERRORS as err:
        raise fail(err) from None
    sys.stdout.write("\n".join(lines) + "\n")


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

    check_engine(engine, {"--address": (address, "auto")})
    if engine == "ray":
        _down_on_ray(run_id, address)
        return
    try:
        removed = teardown_run(run_id)
    except KNOWN_ERRORS as err:
        raise fail(err) from None
    con.ok(f"run {removed.run_id} is down ({removed.summary()})")


def _down_on_ray(run_id: str | None, address: str) -> None:
    """`down --engine ray`: `testbed down RUN_ID` on every host's Ray node; per host what it
    removed, or that it had nothing of the run."""
    from testbed.multihost import down_on_ray

    if run_id is None:
        raise fail(BadInput("--engine ray: name the run: testbed down <run id> --engine ray"))
    try:
        parts = down_on_ray(run_id, address)
    except KNOWN_ERRORS as err:
        raise fail(err) from None
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
        raise fail(
            BadInput(
                f"no host of the Ray cluster ({', '.join(p.host for p in parts)}) has run {run_id}"
            )
        )


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
        raise fail(err) from None
    con.ok(report)
    failed = False
    for line in finalise_orphans(folders):
        bad = line.startswith("error: ")
        failed |= bad
        (con.error if bad else con.ok)(line.removeprefix("error: "))
    if failed:
        raise typer.Exit(EXIT_FAILED)
