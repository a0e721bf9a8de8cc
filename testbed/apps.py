"""Apps: the processes a researcher brings (`apps:`), run in the run's namespaces, watched, stopped.

Nouns:
- `Readiness`: when an app counts as started: a log line matches, a port listens in its
  namespace, or a ROS topic publishes (a `nodes.ros.topic_probe` in its namespace, with the
  run's ROS environment, waits for one message).
- `AppProcess`: one app of a run: its spec, log `logs/app.<name>.log`, process, readiness,
  exit code and resource use (user/system CPU and peak memory from `wait4`, the cgroup's
  throttling counters when it has a `cpu` budget).
- `Apps`: all of a run's apps. Those that start at 0 s start once the EdgeLoc nodes are ready
  and the run waits for their readiness before the timeline plays; later ones start on the
  timeline (`tick`), which also stops each at its `stop` (SIGTERM, then SIGKILL after a grace)
  and fails the run when a required app exits non-zero or misses its readiness timeout, with
  its last log lines. An app that exits 0 has finished: that is recorded, not a failure.

Every process starts through `Node.popen`, so the run's state file lists it and `testbed
down`/`clean` (or a Ctrl-C teardown) stop it like a built-in node.

Exit codes, readiness time, CPU time and peak memory (and cgroup throttling with `cpu:`) go to
run.json and the report's Apps table. Paths in `command` are relative to the scenario file, and
`python` is the testbed's interpreter. Everything a scenario names is checked before anything is
built (a shell string, an unknown node, a `ready` without `timeout`, a program that is not found:
file:line:column). `record.topics` starts a recorder inside the named namespace that records
those topics, of any installed message type, with their full ros2msg schemas; a type whose
package is not installed is named, with the wheel to install.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nodes.ros.env import RosEnv
from testbed import cgroups
from testbed.cgroups import CpuBudget
from testbed.errors import TestbedError
from testbed.scenario.model import App
from testbed.topology import Net

Progress = Callable[[str], None]

#: How long a stopped app may take to exit before it is killed.
STOP_GRACE_S = 5.0
#: Log lines quoted when an app fails.
TAIL_LINES = 15
#: TCP state LISTEN in /proc/net/tcp.
_TCP_LISTEN = "0A"
LOOPBACK = "127.0.0.1"


def log_path(folder: Path, name: str) -> Path:
    return folder / "logs" / f"app.{name}.log"


def listening(pid: int, port: int, protocol: str) -> bool:
    """Whether a socket in `pid`'s network namespace listens on TCP `port` or is bound to UDP
    `port` (read from /proc/<pid>/net, which shows the namespace of that process)."""
    states = (_TCP_LISTEN,) if protocol == "tcp" else None
    for table in (protocol, f"{protocol}6"):
        try:
            lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) < 4:
                continue
            local, state = fields[1], fields[3]
            if int(local.rsplit(":", 1)[1], 16) == port and (states is None or state in states):
                return True
    return False


class Readiness:
    """Whether an app's `ready` condition holds yet (see the module doc)."""

    def __init__(self, app: AppProcess, start_probe: Callable[[AppProcess], subprocess.Popen[Any]]):
        self.app, self.spec = app, app.spec.ready
        self._start_probe = start_probe
        self._offset = 0
        self._partial = ""
        self._pattern = (
            re.compile(str(self.spec.value)) if self.spec and self.spec.kind == "log" else None
        )
        self.probe: subprocess.Popen[Any] | None = None
        self.probe_log = app.log.with_suffix(".ready.log")

    def check(self) -> bool | str:
        """True once ready; a message when it can no longer become ready; else False."""
        spec = self.spec
        if spec is None:
            return True
        if spec.kind == "log":
            return self._log_matches()
        if spec.kind == "port":
            pid = self.app.pid
            return pid is not None and listening(pid, int(spec.value), spec.protocol)
        if self.probe is None:
            self.probe = self._start_probe(self.app)
        code = self.probe.poll()
        if code is None:
            return False
        if code == 0:
            return True
        return f"{spec.text()}: " + _tail(self.probe_log, 3)

    def _log_matches(self) -> bool:
        assert self._pattern is not None
        try:
            with open(self.app.log, "rb") as f:
                f.seek(self._offset)
                data = f.read()
        except OSError:
            return False
        self._offset += len(data)
        text = self._partial + data.decode(errors="replace")
        lines = text.split("\n")
        self._partial = lines.pop()  # an unfinished line waits for its end
        return any(self._pattern.search(line) for line in lines) or bool(
            self._partial and self._pattern.search(self._partial)
        )

    def stop(self) -> None:
        if self.probe is not None and self.probe.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.probe.kill()
            self.probe.wait(timeout=5)


@dataclass
class AppProcess:
    """One app of a run (see the module doc)."""

    spec: App
    log: Path
    proc: subprocess.Popen[Any] | None = None
    started_at: float | None = None  # timeline time it started at
    ready_at: float | None = None
    stopped_by_us: bool = False
    exit_code: int | None = None
    rusage: dict[str, float] = field(default_factory=dict)
    peak_rss_kb: int = 0
    budget: CpuBudget | None = None
    cpu_stat: dict[str, int] = field(default_factory=dict)
    readiness: Readiness | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    @property
    def running(self) -> bool:
        return self.proc is not None and self.exit_code is None

    def reap(self) -> bool:
        """Collect the exit status (and resource use) if the process ended; True if it has."""
        if self.proc is None:
            return False
        if self.exit_code is not None:
            return True
        try:
            pid, status, ru = os.wait4(self.proc.pid, os.WNOHANG)
        except ChildProcessError:  # reaped elsewhere (Popen.wait): its code is there
            self.exit_code = self.proc.returncode if self.proc.returncode is not None else -1
            return True
        if pid == 0:
            return False
        self.exit_code = os.waitstatus_to_exitcode(status)
        self.proc.returncode = self.exit_code  # so Popen does not wait for it again
        # Not ru_maxrss: Linux carries it over exec(), so it would be this (large) process's.
        self.rusage = {
            "user_s": round(ru.ru_utime, 3),
            "system_s": round(ru.ru_stime, 3),
            "peak_rss_kb": self.peak_rss_kb,
        }
        return True

    def sample_memory(self) -> None:
        """Keep the largest VmHWM (peak resident memory since exec) seen while it runs."""
        if self.proc is None or self.exit_code is not None:
            return
        try:
            status = Path(f"/proc/{self.proc.pid}/status").read_text()
        except OSError:
            return
        for line in status.splitlines():
            if line.startswith("VmHWM:"):
                self.peak_rss_kb = max(self.peak_rss_kb, int(line.split()[1]))

    def tail(self, lines: int = TAIL_LINES) -> str:
        return _tail(self.log, lines)

    def to_dict(self, folder: Path) -> dict[str, Any]:
        s = self.spec
        return {
            "node": s.node,
            "command": list(s.command),
            "ros": s.ros,
            "required": s.required,
            "start_s": s.start_s,
            "stop_s": s.stop_s,
            "started_at_s": self.started_at,
            "ready_at_s": self.ready_at,
            "ready": s.ready.text() if s.ready else None,
            "exit_code": self.exit_code,
            "stopped_by_testbed": self.stopped_by_us,
            "log": str(self.log.relative_to(folder)),
            "resources": self.rusage,
            "cpu_cores": s.cpu,
            "cpu_stat": self.cpu_stat,
        }


def _tail(path: Path, lines: int) -> str:
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return "(no log)"
    return "\n".join(text.splitlines()[-lines:]) or "(empty log)"


class Apps:
    """The apps of one run (see the module doc). `peers(node)` gives the ROS unicast peers of a
    process in that namespace (`nodes.ros.env`)."""

    def __init__(
        self,
        net: Net,
        folder: Path,
        env: RosEnv,
        peers: Callable[[str], list[str]],
        progress: Progress,
    ) -> None:
        self.net, self.folder, self.env, self.peers = net, Path(folder), env, peers
        self.progress = progress
        self.apps = [AppProcess(a, log_path(self.folder, a.name)) for a in net.scenario.apps]
        self.stopping = False
        self.failure: str | None = None
        scenario = net.scenario
        self.default_cwd = scenario.source.parent if scenario.source is not None else Path.cwd()

    def __bool__(self) -> bool:
        return bool(self.apps)

    # ---- start -------------------------------------------------------------------------

    def environ(self, app: App) -> dict[str, str]:
        env = self.env.environ(self.peers(app.node)) if app.ros else dict(os.environ)
        env["PYTHONUNBUFFERED"] = "1"  # a Python app's log lines arrive as it prints them
        env.update(dict(app.env))
        return env

    def _argv(self, app: App) -> list[str]:
        first = sys.executable if app.command[0] == "python" else app.command[0]
        return [first, *app.command[1:]]

    def _start(self, a: AppProcess, now: float) -> None:
        spec = a.spec
        a.log.parent.mkdir(parents=True, exist_ok=True)
        if spec.cpu is not None:
            ok, why = cgroups.available()
            if ok:
                a.budget = CpuBudget(self.net.run_id, f"app.{spec.name}", spec.cpu)
                self.net.record_cgroup(a.budget.path)
                a.budget.create()
            else:
                self.progress(f"  warning: app {spec.name} runs without its CPU budget ({why})")
        try:
            with open(a.log, "w") as log:
                a.proc = self.net[spec.node].popen(
                    self._argv(spec),
                    what=f"{spec.node}: app {spec.name}",
                    env=self.environ(spec),
                    cwd=str(spec.cwd or self.default_cwd),
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    stdin=subprocess.DEVNULL,
                    start_new_session=True,  # Ctrl-C on the terminal reaches the testbed alone
                )
        except OSError as err:
            raise TestbedError(f"app {spec.name}: cannot start {spec.command[0]}: {err}") from None
        if a.budget is not None:
            a.budget.add(a.proc.pid)  # nsenter exec()s: the pid is the app itself
        a.started_at = now
        a.readiness = Readiness(a, self._probe)
        shown = " ".join(spec.command)
        self.progress(f"  app {spec.name} started in {spec.node}: {shown}")

    def _probe(self, a: AppProcess) -> subprocess.Popen[Any]:
        """A `topic_probe` in the app's namespace, with the run's ROS environment."""
        spec = a.spec
        assert spec.ready is not None
        readiness = a.readiness
        assert readiness is not None
        argv = [
            sys.executable,
            "-m",
            "nodes.ros.topic_probe",
            "--topic",
            str(spec.ready.value),
            "--timeout",
            f"{spec.ready.timeout_s:g}",
        ]
        with open(readiness.probe_log, "w") as log:
            return self.net[spec.node].popen(
                argv,
                what=f"{spec.node}: ready probe of app {spec.name}",
                env=self.env.environ(self.peers(spec.node)),
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )

    def start_first(self, timeout_floor_s: float = 0.0) -> None:
        """Start the apps due at 0 s and wait until each is ready (or fail the run)."""
        first = [a for a in self.apps if a.spec.start_s == 0]
        if not first:
            return
        for a in first:
            self._start(a, 0.0)
        t0 = time.monotonic()
        while any(a.ready_at is None for a in first):
            self._watch(first, time.monotonic() - t0, before_timeline=True)
            time.sleep(0.05)
        waited = time.monotonic() - t0
        names = ", ".join(a.name for a in first)
        if any(a.spec.ready is not None for a in first):
            self.progress(f"  apps ready in {waited:.1f} s: {names}")

    # ---- watch -------------------------------------------------------------------------

    def tick(self, elapsed: float) -> None:
        """Start the apps due by `elapsed`, stop those past their stop, check every one;
        raises TestbedError when the run must fail."""
        for a in self.apps:
            if a.proc is None and a.spec.start_s <= elapsed:
                self._start(a, elapsed)
            stop = a.spec.stop_s
            if stop is not None and elapsed >= stop and a.running and not a.stopped_by_us:
                self.progress(f"  app {a.name} stopped at its stop time ({stop:g} s)")
                self._terminate(a)
        self._watch(self.apps, elapsed)

    def _watch(self, apps: list[AppProcess], now: float, before_timeline: bool = False) -> None:
        if self.stopping:
            return
        for a in apps:
            if a.proc is None:
                continue
            a.sample_memory()
            if a.reap() and not a.stopped_by_us:
                self._exited(a)
            if a.ready_at is not None or a.readiness is None:
                continue
            since = now - (0.0 if before_timeline else (a.started_at or 0.0))
            state = a.readiness.check() if a.exit_code is None else False
            if state is True:
                a.ready_at = now
                a.readiness.stop()
                if not before_timeline and a.spec.ready is not None:
                    self.progress(f"  app {a.name} ready at t={now:.1f} s")
            elif isinstance(state, str) or (
                a.spec.ready is not None and since > a.spec.ready.timeout_s
            ):
                why = state if isinstance(state, str) else a.spec.ready.missed()  # type: ignore[union-attr]
                raise TestbedError(
                    f"run {self.net.run_id} failed: app {a.name} ({a.spec.node}) not ready: "
                    f"{why}; last lines of {a.log}:\n{a.tail()}"
                )

    def _exited(self, a: AppProcess) -> None:
        code = a.exit_code
        if code == 0:
            if a.ready_at is None and a.spec.ready is not None:
                raise TestbedError(
                    f"run {self.net.run_id} failed: app {a.name} ({a.spec.node}) exited before "
                    f"it was ready ({a.spec.ready.text()}); last lines of {a.log}:\n{a.tail()}"
                )
            self.progress(f"  app {a.name} finished (exit code 0)")
            a.stopped_by_us = True  # nothing left to watch
            return
        if a.spec.required:
            raise TestbedError(
                f"run {self.net.run_id} failed: app {a.name} ({a.spec.node}) exited with "
                f"{code}; last lines of {a.log}:\n{a.tail()}"
            )
        self.progress(f"  warning: app {a.name} exited with {code} (required: false, run goes on)")
        a.stopped_by_us = True

    # ---- stop --------------------------------------------------------------------------

    def _terminate(self, a: AppProcess) -> None:
        a.stopped_by_us = True
        if a.proc is not None and a.exit_code is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(a.proc.pid, signal.SIGTERM)

    def stop(self, grace_s: float = STOP_GRACE_S) -> dict[str, Any]:
        """SIGTERM every app still running, SIGKILL after `grace_s`, collect exit codes and
        resource use, remove the budgets. Returns what run.json records."""
        self.stopping = True
        for a in self.apps:
            if a.readiness is not None:
                a.readiness.stop()
            if a.running:
                a.sample_memory()
                self._terminate(a)
        deadline = time.monotonic() + grace_s
        for a in self.apps:
            if a.proc is None:
                continue
            while not a.reap() and time.monotonic() < deadline:
                time.sleep(0.05)
            if not a.reap():
                self.progress(f"  warning: app {a.name} did not stop in {grace_s:g} s; killed")
                with contextlib.suppress(ProcessLookupError):
                    a.proc.kill()
                while not a.reap():
                    time.sleep(0.02)
            if a.budget is not None and a.budget.exists:
                with contextlib.suppress(OSError):
                    a.cpu_stat = a.budget.stats()
                a.budget.remove()
        return self.summary()

    def summary(self) -> dict[str, Any]:
        return {a.name: a.to_dict(self.folder) for a in self.apps}
