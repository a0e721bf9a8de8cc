"""`testbed up FILE --engine ray` and `testbed down ID --engine ray`: a topology across hosts
(`topology.hosts`) built and torn down by one command, each host's part by that host itself.

The parts are what `testbed up FILE --host NAME --run-id ID` and `testbed down ID` build and
remove on one host (`testbed.topology.vxlan`); this module only gets them run on the right
machines, through Ray, the engine `testbed sweep --engine ray` already uses (no SSH keys, no
host list to keep besides the scenario's):

- Each host runs a Ray node offering one unit of the custom resource `testbed-host-<name>`
  (`<name>` as in `topology.hosts`): a task asking for it can run on that host's node only.
  Before anything is built, every host of the scenario must have such a node, or nothing is.
- A host's task runs the testbed CLI in a fresh interpreter (this interpreter, the checkout as
  its working folder), not in the worker (building forks, and a forked copy of a Ray worker is
  unsafe; a sweep's real run is forked from a server of its own, `rayengine._run_apart`),
  with its output as the task's answer. It runs in the network namespace of its Ray node, the
  host's underlay, where `up --host` must run (the tunnels' UDP sockets stay there). It gets a
  session of its own, so that what `up` leaves running (relays, GTP-U ends) is in no process
  group of the Ray worker; the CLI process itself dies with the worker.
- The scenario file goes with the task as text (`Shipped`): a host with the same file at the
  same place (the same path inside its checkout, or the same absolute path outside it) runs
  that; else a hidden copy of the text is written next to where the file would be, so that
  relative paths in it (traces, datasets) resolve as on the caller, and removed after `up`;
  where that folder does not exist either, the copy is made in a temporary folder (and says
  so: relative paths resolve there).
- Every host gets the same run id (the caller picks one when not given): the tunnels' VNIs
  come from it. When a host fails, the hosts that came up are taken down again, and the
  command fails with that host's exit code.
- `down --engine ray` runs `testbed down ID` on every node of the cluster that offers a
  `testbed-host-*` resource; a host without that run says so. `testbed clean` stays per host.

Starting the nodes (the resource names the host as in `topology.hosts`):
  sudo .venv/bin/ray start --head --port=6379 --resources='{"testbed-host-a": 1}'          # a
  sudo .venv/bin/ray start --address=192.168.1.10:6379 --resources='{"testbed-host-b": 1}' # b
  sudo .venv/bin/testbed up my.yaml --engine ray --address 192.168.1.10:6379   # both parts
  sudo .venv/bin/testbed down 4a2cf3 --engine ray --address 192.168.1.10:6379
A host without a node is an error before anything is built (exit 3, with the `ray start` line it
needs). Token authentication is as for sweeps (`testbed.sweep.rayengine`).
tests/test_multihost_ray_root.py starts a Ray head inside host namespace a and a worker inside
host namespace b (each with its own state folder) and runs both commands from a: on a 2-core VM
`up --engine ray` took 2.5 s in all (1.4 s from the connection on; host a's part 1.0 s, host b's
0.5 s, side by side) and `down --engine ray` 2.8 s. Not built yet: a `testbed run` across hosts
(ROS nodes, timeline and recording on several machines) and starting the other hosts' parts over
SSH without Ray.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from testbed.errors import BadInput, HostError

#: A host's Ray node offers one unit of this + the host's name in `topology.hosts`.
HOST_RESOURCE_PREFIX = "testbed-host-"
#: How long one host's `testbed up` / `testbed down` may take.
UP_TIMEOUT_S = 300.0
DOWN_TIMEOUT_S = 120.0
#: How long cancelled tasks get to end after Ctrl-C, before the hosts are taken down.
CANCEL_WAIT_S = 15.0
#: The hidden copy of a shipped scenario next to the host's own (see the module doc).
COPY_PREFIX = ".testbed-up-"
#: The checkout this module runs from: the same path on every host.
CHECKOUT = Path(__file__).resolve().parent.parent


def host_resource(host: str) -> str:
    """The Ray resource that marks the node of `host` (a name in `topology.hosts`)."""
    return f"{HOST_RESOURCE_PREFIX}{host}"


def start_command(host: str, head: str = "HEAD:6379") -> str:
    """How to start `host`'s Ray node (for error messages)."""
    return f"ray start --address={head} --resources='{{\"{host_resource(host)}\": 1}}'"


# ---- the scenario file, shipped --------------------------------------------------------------


@dataclass(frozen=True)
class Shipped:
    """A scenario file as the caller has it: its text, and where it is (relative to the checkout
    when inside it, else absolute), so that a host finds its own copy at the same place."""

    text: str
    path: str

    @classmethod
    def of(cls, file: Path, checkout: Path = CHECKOUT) -> Shipped:
        where = file.resolve()
        with contextlib.suppress(ValueError):
            where = where.relative_to(checkout)
        return cls(file.read_text(), str(where))


@contextlib.contextmanager
def placed(shipped: Shipped, checkout: Path = CHECKOUT) -> Iterator[tuple[Path, str | None]]:
    """The scenario file this host runs (see the module doc), and a note when it is a copy of
    the shipped text rather than the host's own file; a copy is removed on exit."""
    own = checkout / shipped.path  # an absolute `path` stays itself
    same = False
    with contextlib.suppress(OSError, UnicodeDecodeError):
        same = own.is_file() and own.read_text() == shipped.text
    if same:
        yield own, None
        return
    why = "differs from the caller's" if own.is_file() else "is not on this host"
    folder: Path | None = None
    try:
        fd, name = tempfile.mkstemp(prefix=COPY_PREFIX, suffix=own.suffix, dir=own.parent)
        note = f"{own} {why}: built from the caller's text, copied next to it (removed after)"
    except OSError:  # no such folder here (or not writable)
        folder = Path(tempfile.mkdtemp(prefix="edgeloc-up-"))
        name = str(folder / own.name)
        fd = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        note = (
            f"{own} {why}: built from the caller's text in {folder} (paths in it relative to "
            "the scenario resolve there)"
        )
    copy = Path(name)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(shipped.text)
        yield copy, note
    finally:
        copy.unlink(missing_ok=True)
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


# ---- one host's part: the task ---------------------------------------------------------------


@dataclass
class Part:
    """What one host's `testbed up` or `testbed down` did."""

    host: str
    #: The machine that ran it: its hostname and Ray node address ("?" when the task died).
    machine: str
    #: The command's exit code (the CLI's meanings), 1 when the task itself died.
    code: int
    #: Its output, stdout then stderr, blank lines left out.
    lines: list[str] = field(default_factory=list)
    seconds: float = 0.0
    #: `down`: this host has no state file of the run (nothing of it here).
    absent: bool = False

    @property
    def ok(self) -> bool:
        return self.code == 0

    def result(self) -> list[str]:
        """The lines that say what was built or removed (`up`'s advice on how to build the
        other hosts and how to tear down is left out: this command does both)."""
        out = []
        for line in self.lines:
            if line.startswith(("build the other hosts' parts", "tear down with:")):
                break
            out.append(line)
        return out


def _machine() -> str:
    try:
        import ray.util

        return f"{socket.gethostname()} {ray.util.get_node_ip_address()}"
    except Exception:  # not in a Ray worker (tests call the tasks directly)
        return socket.gethostname()


def _testbed(args: list[str], timeout_s: float) -> tuple[int, list[str]]:
    """The testbed CLI on this host in a fresh interpreter (see the module doc for why); its
    exit code and output lines."""
    from netem.proc import die_with_parent

    try:
        done = subprocess.run(
            [sys.executable, "-m", "testbed.cli", *args],
            cwd=CHECKOUT,
            env={**os.environ, "CI": "1"},  # plain lines
            capture_output=True,
            text=True,
            timeout=timeout_s,
            preexec_fn=die_with_parent,  # only a prctl between fork and exec
            start_new_session=True,
            check=False,
        )
    except subprocess.TimeoutExpired as err:
        said = [str(x) for x in (err.stdout, err.stderr) if x]
        lines = [x for x in "\n".join(said).splitlines() if x.strip()]
        return 1, [*lines, f"error: `testbed {args[0]}` took more than {timeout_s:g} s: killed"]
    lines = [x for x in (done.stdout + done.stderr).splitlines() if x.strip()]
    return done.returncode, lines


def up_part(host: str, shipped: Shipped, run_id: str) -> Part:
    """The task on `host`'s node: `testbed up FILE --host HOST --run-id RUN_ID`."""
    t0 = time.monotonic()
    with placed(shipped) as (path, note):
        code, lines = _testbed(["up", str(path), "--host", host, "--run-id", run_id], UP_TIMEOUT_S)
    if note is not None:
        lines.insert(0, f"note: {note}")
    return Part(host, _machine(), code, lines, time.monotonic() - t0)


def down_part(host: str, run_id: str) -> Part:
    """The task on `host`'s node: `testbed down RUN_ID`, when this host has that run."""
    from testbed import state as st

    t0 = time.monotonic()
    if st.load_run(run_id) is None:
        return Part(host, _machine(), 0, [f"no run {run_id} here"], absent=True)
    code, lines = _testbed(["down", run_id], DOWN_TIMEOUT_S)
    return Part(host, _machine(), code, lines, time.monotonic() - t0)


# ---- the caller ------------------------------------------------------------------------------


@dataclass
class UpOutcome:
    """`up --engine ray`: each host's `up`, and the `down` of those that came up when another
    failed."""

    run_id: str
    parts: list[Part]
    undone: list[Part]
    seconds: float

    @property
    def failed(self) -> list[Part]:
        return [p for p in self.parts if not p.ok]


def _connect(address: str) -> Any:
    from testbed.sweep.rayengine import LOCAL, RayOptions, connect

    if address == LOCAL:
        raise BadInput(
            "--address local starts a one-host Ray cluster; a topology across hosts needs each "
            "host's own Ray node: give the cluster's address (auto or HOST:PORT)"
        )
    resource = f"--resources='{{\"{host_resource('<name>')}\": 1}}'"
    how = (
        f"start a Ray node on each host, with its host's resource: `ray start --head {resource}` "
        f"on one and `{start_command('<name>')}` on the others (see the README)"
    )
    ray, _ = connect(RayOptions(address=address), how_to_start=how)
    return ray


def hosts_offered(nodes: list[dict[str, Any]]) -> set[str]:
    """The hosts whose node is in the cluster: the names of the `testbed-host-*` resources
    that a live node offers a whole unit of."""
    return {
        name.removeprefix(HOST_RESOURCE_PREFIX)
        for node in nodes
        if node.get("Alive")
        for name, units in node.get("Resources", {}).items()
        if name.startswith(HOST_RESOURCE_PREFIX) and units >= 1
    }


def check_hosts(hosts: list[str], nodes: list[dict[str, Any]]) -> None:
    """Every host of the scenario has a node in the cluster, or a HostError that says which
    have not and how to start them."""
    offered = hosts_offered(nodes)
    missing = [h for h in hosts if h not in offered]
    if not missing:
        return
    starts = "; ".join(f"on host {h}: `{start_command(h)}`" for h in missing)
    there = ", ".join(sorted(offered)) or "none"
    raise HostError(
        f"no Ray node for host(s) {', '.join(missing)} of topology.hosts: start one ({starts}). "
        f"Hosts with a node in the cluster: {there}"
    )


def _submit(ray: Any, task: Callable[..., Part], host: str, *args: Any) -> Any:
    return (
        ray.remote(task)
        .options(num_cpus=0, resources={host_resource(host): 1}, max_retries=0)
        .remote(host, *args)
    )


def _gather(ray: Any, refs: dict[Any, str], timeout_s: float) -> list[Part]:
    """Each task's Part, as they finish; a task that died or did not answer in time is a
    failed Part of its host."""
    deadline = time.monotonic() + timeout_s
    parts: dict[str, Part] = {}
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(
            pending, num_returns=1, timeout=max(0.1, deadline - time.monotonic())
        )
        if not ready:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
                parts[refs[ref]] = Part(refs[ref], "?", 1, [f"no answer within {timeout_s:g} s"])
            break
        ref = ready[0]
        try:
            parts[refs[ref]] = ray.get(ref)
        except Exception as err:  # the task died (its worker, its node)
            why = str(err).strip().splitlines()[0][:200] if str(err).strip() else ""
            parts[refs[ref]] = Part(
                refs[ref], "?", 1, [f"its Ray task died: {type(err).__name__}: {why}"]
            )
    return [parts[h] for h in refs.values()]


def up_on_ray(
    file: Path,
    hosts: list[str],
    run_id: str | None,
    address: str,
    progress: Callable[[str], None],
) -> UpOutcome:
    """Build each host's part of the scenario in `file` on that host's Ray node (see the module
    doc); raises BadInput/HostError before anything is built."""
    from testbed import state as st

    if run_id is None:
        run_id = st.fresh_run_id(set())
    elif not st.RUN_ID_RE.match(run_id):
        raise BadInput(f"run id {run_id!r} must be 6 lowercase hex characters")
    shipped = Shipped.of(file)
    ray = _connect(address)
    t0 = time.monotonic()
    try:
        check_hosts(hosts, ray.nodes())
        progress(f"run {run_id}: building on hosts {', '.join(hosts)} through Ray")
        refs = {_submit(ray, up_part, h, shipped, run_id): h for h in hosts}
        try:
            parts = _gather(ray, refs, UP_TIMEOUT_S + 60)
        except KeyboardInterrupt:
            _interrupted(ray, refs, run_id, progress)
            raise
        came_up = [p.host for p in parts if p.ok]
        undone: list[Part] = []
        if came_up and len(came_up) < len(parts):
            progress(f"a host failed: taking down the hosts that came up ({', '.join(came_up)})")
            undone = _down(ray, came_up, run_id)
        return UpOutcome(run_id, parts, undone, time.monotonic() - t0)
    finally:
        ray.shutdown()


def _interrupted(
    ray: Any, refs: dict[Any, str], run_id: str, progress: Callable[[str], None]
) -> None:
    """Ctrl-C during `up`: cancel the tasks, then take down every host whose `up` did not fail
    by itself (a host whose `up` failed removed what it built; the run id may be another
    run's there)."""
    progress("interrupted: cancelling the hosts' `up` and taking down what came up")
    failed = set()
    for ref, host in refs.items():
        with contextlib.suppress(Exception):
            ready, _ = ray.wait([ref], timeout=0)
            if ready and not ray.get(ref).ok:
                failed.add(host)
                continue
        with contextlib.suppress(Exception):
            ray.cancel(ref, force=True)
    with contextlib.suppress(Exception):
        ray.wait(list(refs), num_returns=len(refs), timeout=CANCEL_WAIT_S)
    for part in _down(ray, [h for h in refs.values() if h not in failed], run_id):
        progress(f"  host {part.host}: " + (part.lines[-1] if part.lines else f"exit {part.code}"))


def _down(ray: Any, hosts: list[str], run_id: str) -> list[Part]:
    refs = {_submit(ray, down_part, h, run_id): h for h in hosts}
    return _gather(ray, refs, DOWN_TIMEOUT_S + 60)


def down_on_ray(run_id: str, address: str) -> list[Part]:
    """`testbed down RUN_ID` on every host's node of the cluster (see the module doc)."""
    from testbed import state as st

    if not st.RUN_ID_RE.match(run_id):
        raise BadInput(f"run id {run_id!r} must be 6 lowercase hex characters")
    ray = _connect(address)
    try:
        hosts = sorted(hosts_offered(ray.nodes()))
        if not hosts:
            raise HostError(
                f"no node of the Ray cluster offers a {HOST_RESOURCE_PREFIX}<name> resource: "
                f"no host to take run {run_id} down on (each host's node starts with "
                f"`{start_command('<name>')}`)"
            )
        return _down(ray, hosts, run_id)
    finally:
        ray.shutdown()
