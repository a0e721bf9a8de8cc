"""Several EdgeLoc nodes in one process, as a ROS 2 component container runs its components.

    python -m nodes.ros.container av1.fusion=fusion_node@logs/av1.fusion.log --config c.json \
        --vehicle av1 --edge edge1 --stats nodes/av1.fusion.json -- \
        av1.sensor=vehicle_sensor@logs/av1.sensor.log --config c.json --vehicle av1 ...

Each role is `NAME=MODULE[@LOG]` followed by that module's own command line, roles separated by
`--`. A vehicle's three nodes as three processes cost three Python interpreters, three rclpy
contexts (three DDS participants, each discovering every peer) and their frames copied between
processes; on a host with a few cores and several vehicles that, not the emulated cell, set the
latency. Here one process holds one rclpy context (one participant) and every role runs its
module's `main(argv)` in its own thread, unchanged: one node per role, an executor and its
thread per role (`nodes.ros.common.ros_node`), its own stats file, MCAP part and log file (the
READY and MATCHED lines the supervisor waits for), and the DNN thread of `inference_request`
still joins the `.dnn` cgroup by thread id (`ComputeThread`). What the roles share, they share
through `nodes.ros.common.Composed`.

Lifecycle: the main thread installs the one SIGTERM/SIGINT handler (`Stop`), which every role
polls; each role joins its executor and destroys its node; once every role thread is joined
the container calls `rclpy.shutdown()`, once (Jazzy aborts at exit otherwise). A role that
ends before the stop (an error, a bad command line) stops the others, and the container exits
with that role's status after logging `role-exit` lines on its own stdout: the supervisor names
the role from them (`testbed.supervisor`).
"""

from __future__ import annotations

import contextlib
import importlib
import re
import sys
import threading
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from nodes.ros.common import COMPOSED, Composed, Stop, call_main, emit, start_thread

#: The modules a container can run (each has `main(argv)` and writes its own stats).
ROLES = ("vehicle_sensor", "inference_request", "fusion_node", "edge_inference")
#: Separates one role's command line from the next.
SEPARATOR = "--"
#: The container's line for each role that ended: `{"event": "role-exit", "role", "code",
#: "stopped"}` (`stopped` false: it ended on its own, which fails the container).
ROLE_EXIT = "role-exit"
#: Seconds the container waits for each role thread after the stop; the supervisor kills it
#: at 10 s (`testbed.supervisor.STOP_GRACE_S`), so a stuck role still leaves its line first.
JOIN_S = 8.0
#: Exit status when a role ended on its own with status 0 (it must run until stopped).
ENDED_EARLY = 1

_SPEC = re.compile(r"^(?:(?P<name>[A-Za-z0-9_.-]+)=)?(?P<module>[a-z_]+)(?:@(?P<log>.+))?$")


class BadRoles(ValueError):
    """A container command line that names no role, an unknown module or a role twice."""


@dataclass(frozen=True)
class RoleSpec:
    """One role of a container: its name, module (`nodes.ros.<module>`), log and arguments."""

    name: str
    module: str
    log: Path | None = None
    argv: tuple[str, ...] = ()

    def words(self) -> list[str]:
        spec = f"{self.name}={self.module}" + (f"@{self.log}" if self.log is not None else "")
        return [spec, *self.argv]


def container_argv(roles: Sequence[RoleSpec]) -> list[str]:
    """The container's command line for `roles` (what `parse_roles` reads back)."""
    out: list[str] = []
    for i, role in enumerate(roles):
        if any(a == SEPARATOR for a in role.argv):
            raise BadRoles(f"role {role.name}: an argument may not be {SEPARATOR!r}")
        out += ([SEPARATOR] if i else []) + role.words()
    return out


def parse_roles(argv: Sequence[str]) -> list[RoleSpec]:
    """The roles of a container command line (see the module doc)."""
    groups: list[list[str]] = [[]]
    for word in argv:
        if word == SEPARATOR:
            groups.append([])
        else:
            groups[-1].append(word)
    roles: list[RoleSpec] = []
    for group in groups:
        if not group:
            raise BadRoles(f"an empty role (two {SEPARATOR!r} in a row, or none at all)")
        m = _SPEC.match(group[0])
        if m is None or m["module"] not in ROLES:
            raise BadRoles(
                f"{group[0]!r} is not NAME=MODULE[@LOG] with MODULE one of {', '.join(ROLES)}"
            )
        name = m["name"] or m["module"]
        if any(r.name == name for r in roles):
            raise BadRoles(f"role {name} given twice")
        log = Path(m["log"]) if m["log"] else None
        roles.append(RoleSpec(name, m["module"], log, tuple(group[1:])))
    return roles


@dataclass
class Role:
    """A role while it runs: its spec, log stream, thread and exit status."""

    spec: RoleSpec
    log: TextIO
    thread: threading.Thread | None = None
    code: int | None = None
    #: Whether the stop flag was set when the role ended (False: it ended on its own).
    stopped: bool = False
    done: threading.Event = field(default_factory=threading.Event)


def _run_role(role: Role, main: Any, stop: Stop) -> None:
    """A role's thread: its module's `main(argv)` with the role's `Composed` set; whatever way
    it ends, its status is kept and its end stops the other roles."""
    COMPOSED.set(Composed(role.spec.name, role.log, stop))
    try:
        role.code = call_main(main, role.spec.argv)
    except SystemExit as err:  # argparse: the role's command line was refused
        role.code = err.code if isinstance(err.code, int) else 2
        emit("error", message=f"exited with {err.code}")
    except BaseException as err:
        role.code = 1
        role.log.write(traceback.format_exc())
        emit("error", message=f"{type(err).__name__}: {err}")
    finally:
        role.stopped = bool(stop)
        role.log.flush()
        role.done.set()
        stop.set()


def main(argv: Sequence[str] | None = None) -> int:
    try:
        specs = parse_roles(sys.argv[1:] if argv is None else argv)
    except BadRoles as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 2
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    # Imported here, one after another: a role thread importing torch would hold the import
    # lock while the others wait on it anyway, and a module that fails to import is one line.
    mains = {s.name: importlib.import_module(f"nodes.ros.{s.module}").main for s in specs}
    stop = Stop()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    with contextlib.ExitStack() as logs:
        roles = [
            Role(s, logs.enter_context(open(s.log, "a")) if s.log is not None else sys.stdout)
            for s in specs
        ]
        return _run(roles, mains, stop, rclpy)


def _run(roles: list[Role], mains: dict[str, Any], stop: Stop, rclpy: Any) -> int:
    """Run every role until the stop; the container's exit status."""
    for role in roles:
        role.thread = start_thread(
            lambda role=role: _run_role(role, mains[role.spec.name], stop),
            f"role-{role.spec.name}",
        )
    emit("container", roles={r.spec.name: r.spec.module for r in roles})
    while not stop.wait(0.5):  # a bounded wait: the signal handler runs between two
        pass
    for role in roles:
        role.done.wait(JOIN_S)
    alive = [r.spec.name for r in roles if not r.done.is_set()]
    for role in roles:
        emit(ROLE_EXIT, role=role.spec.name, code=role.code, stopped=role.stopped)
    if alive:
        # A role still running holds its node: shutting rclpy down under it would abort.
        emit("error", message=f"role(s) {', '.join(alive)} did not end within {JOIN_S:g} s")
        return ENDED_EARLY
    rclpy.shutdown()
    failed = [r for r in roles if not r.stopped]
    if failed:
        return failed[0].code or ENDED_EARLY
    return next((r.code for r in roles if r.code), 0)


if __name__ == "__main__":
    sys.exit(main())
