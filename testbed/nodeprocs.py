"""The processes of a run's EdgeLoc nodes: which nodes share one, how it is started, and, when
one has died, which node to blame.

A node (`NodeProcess`: a role such as `av1.fusion`, with its own log, stats file and MCAP part)
runs in a process of its own, or with the other nodes of its vehicle in one container
(`nodes.ros.container`), the process named `<vehicle>.vehicle`, its own log
`logs/<vehicle>.vehicle.log`. The supervisor keeps one `NodeProcess` per node either way, so
run.json, the report and the tests find each node's log, stats and part where they always were;
the nodes of one container share its `proc`.

When a container exits, its log says which role ended on its own (`ROLE_EXIT` lines): that role
is the one the watcher's error names, quoting the role's log. A container killed from outside
(SIGKILL, the OOM killer) has no such line; the error then names the container and its roles.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from nodes.ros.common import READY
from nodes.ros.container import ROLE_EXIT, RoleSpec, container_argv

#: Log lines quoted when a node dies.
TAIL_LINES = 15
#: The module that runs several nodes in one process.
CONTAINER = "nodes.ros.container"
#: The process name suffix of a vehicle's container: `av1.vehicle`.
VEHICLE_PROCESS = "vehicle"


def read_events(log: Path) -> list[dict[str, Any]]:
    """The JSON event lines of a log (other lines, e.g. a traceback, skipped)."""
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return []
    out = []
    for line in text.splitlines():
        if line.startswith("{"):
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
    return out


def tail_of(log: Path, lines: int = TAIL_LINES) -> str:
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return "(no log)"
    return "\n".join(text.splitlines()[-lines:]) or "(empty log)"


@dataclass
class NodeProcess:
    """One EdgeLoc node of a run: where it runs, how it was started, and its process."""

    name: str  # e.g. "av1.fusion": <namespace node>.<role>
    host: str  # the topology node (namespace) it runs in
    module: str  # nodes.ros.<module>
    argv: list[str]
    peers: list[str]
    log: Path
    stats: Path
    proc: subprocess.Popen[Any] | None = None
    exit_code: int | None = None
    #: The process it runs in: its own name, or its vehicle's container (`av1.vehicle`).
    process: str = ""

    def __post_init__(self) -> None:
        if not self.process:
            self.process = self.name

    @property
    def composed(self) -> bool:
        """Whether it runs as one role of a container."""
        return self.process != self.name

    def tail(self, lines: int = TAIL_LINES) -> str:
        return tail_of(self.log, lines)

    def ready(self) -> bool:
        return self.logged(READY)

    def logged(self, event: str) -> bool:
        """Whether the node has logged `event` (one of its JSON event lines)."""
        try:
            text = self.log.read_text(errors="replace")
        except OSError:
            return False
        return any(
            line.startswith("{") and f'"event": "{event}"' in line for line in text.splitlines()
        )


def processes(nodes: list[NodeProcess]) -> dict[str, list[NodeProcess]]:
    """The nodes of each process, in start order (a process starts with its first node)."""
    out: dict[str, list[NodeProcess]] = {}
    for n in nodes:
        out.setdefault(n.process, []).append(n)
    return out


def process_log(folder: Path, process: str) -> Path:
    """A container's own log (the roles' lines are in their own logs)."""
    return folder / "logs" / f"{process}.log"


def command(group: list[NodeProcess]) -> list[str]:
    """The command line of one process: the node's module alone, or a container of them."""
    first = group[0]
    if not first.composed:
        return [sys.executable, "-m", first.module, *first.argv]
    roles = [
        RoleSpec(n.name, n.module.removeprefix("nodes.ros."), n.log, tuple(n.argv)) for n in group
    ]
    return [sys.executable, "-m", CONTAINER, *container_argv(roles)]


def death(run_id: str, group: list[NodeProcess], folder: Path) -> str:
    """Why the watcher fails the run when the process of `group` has exited (its nodes'
    `exit_code` already set): the node that died, its status and its last log lines."""
    first = group[0]
    code = first.exit_code
    if not first.composed:
        return (
            f"run {run_id} failed: node {first.name} exited with {code}; "
            f"last lines of {first.log}:\n{first.tail()}"
        )
    log = process_log(folder, first.process)
    ended = [
        e for e in read_events(log) if e.get("event") == ROLE_EXIT and not e.get("stopped", True)
    ]
    by_name = {n.name: n for n in group}
    culprit = by_name.get(str(ended[0].get("role"))) if ended else None
    others = ", ".join(n.name for n in group if n is not culprit)
    if culprit is not None:
        return (
            f"run {run_id} failed: node {culprit.name} exited with {ended[0].get('code')} "
            f"(process {first.process} exited with {code}, stopping {others}); "
            f"last lines of {culprit.log}:\n{culprit.tail()}\n"
            f"last lines of {log}:\n{tail_of(log)}"
        )
    # Killed from outside: no role ended first; each role's last line says where it was.
    roles = "\n".join(f"{n.name}: {n.tail(2)}" for n in group)
    return (
        f"run {run_id} failed: process {first.process} of {first.host} (nodes {others}) "
        f"exited with {code}; "
        f"last lines of {log}:\n{tail_of(log)}\nlast lines of its nodes:\n{roles}"
    )
