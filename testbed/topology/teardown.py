"""Taking a run's network down: its processes stopped, its VXLAN tunnels, cgroups and namespaces
removed (`down`, the end of `run`), and what dead runs left behind found and removed (`clean`)."""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from netem.netns import delete_netns, list_netns, netns_identity
from testbed import cgroups
from testbed import state as st
from testbed.errors import BadInput
from testbed.links import linkstate
from testbed.namespaces import Netns, require_root
from testbed.topology.names import OWNER_TAG, RUN_NETNS_RE, STOP_GRACE_S

# pyroute2, the namespaces' netlink and the VXLAN module are imported where a tunnel or an
# orphan is looked for: `down` of a run on one host needs none of them (a fifth of a second).


@dataclass
class Removed:
    """What a teardown removed."""

    run_id: str
    namespaces: int = 0
    processes: int = 0
    cgroups: int = 0
    tunnels: int = 0  # VXLAN devices of links across hosts
    problems: list[str] = field(default_factory=list)

    def summary(self) -> str:
        tunnels = f"{self.tunnels} VXLAN tunnel(s), " if self.tunnels else ""
        text = (
            f"{self.namespaces} namespace(s), {tunnels}{self.processes} process(es), "
            f"{self.cgroups} cgroup(s) removed"
        )
        if self.problems:
            text += "; could not remove: " + "; ".join(self.problems)
        return text


# ---- teardown, down, clean -----------------------------------------------------------------


def _processes_in(identities: set[tuple[int, int]]) -> list[st.ProcessRef]:
    """Every process (but us) whose network namespace is one of `identities`."""
    found = []
    me = os.getpid()
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == me:
            continue
        try:
            s = os.stat(f"/proc/{entry}/ns/net")
        except OSError:
            continue
        if (s.st_dev, s.st_ino) in identities:
            found.append(st.ProcessRef.of(int(entry), "in namespace"))
    return found


def _stop(refs: Sequence[st.ProcessRef], children: Sequence[subprocess.Popen[Any]] = ()) -> int:
    """SIGTERM the processes that are still the ones recorded, SIGKILL what is left after a
    grace period, reap our own children. Returns how many were running."""
    alive = [r for r in refs if r.alive()]
    for r in alive:
        with contextlib.suppress(ProcessLookupError):
            os.kill(r.pid, signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    pending = list(alive)
    while pending and time.monotonic() < deadline:
        for c in children:
            c.poll()  # reap, so a dead child stops looking alive
        pending = [r for r in pending if r.alive()]
        if pending:
            time.sleep(0.01)
    for r in pending:
        if r.alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(r.pid, signal.SIGKILL)
    for c in children:
        with contextlib.suppress(subprocess.TimeoutExpired):
            c.wait(timeout=STOP_GRACE_S)
    return len(alive)


#: How long `clean` waits for killed tasks to be reaped before a cgroup counts as stuck.
CGROUP_RMDIR_WAIT_S = 5.0


def _remove_cgroup(path: str) -> str | None:
    """rmdir a recorded cgroup after killing what is in it; only under /sys/fs/cgroup."""
    p = Path(path)
    if not p.is_absolute() or Path("/sys/fs/cgroup") not in p.parents:
        return f"cgroup {path} (not under /sys/fs/cgroup; left alone)"
    if not p.is_dir():
        return None
    # children first (a backend may nest), then this one
    for sub in sorted((d for d in p.rglob("*") if d.is_dir()), key=lambda d: -len(d.parts)):
        problem = _remove_cgroup(str(sub))
        if problem:
            return problem
    try:
        pids = [int(x) for x in (p / "cgroup.procs").read_text().split()]
    except OSError:
        pids = []
    _stop([st.ProcessRef.of(pid, "in cgroup") for pid in pids])
    # A killed task keeps its cgroup busy until it is reaped (kernels >= 5.0 keep zombies in
    # their cgroup); an orphan waits for init to reap it, so give that a moment.
    deadline = time.monotonic() + CGROUP_RMDIR_WAIT_S
    while True:
        try:
            p.rmdir()
            return None
        except OSError as err:
            if err.errno != errno.EBUSY or time.monotonic() > deadline:
                return f"cgroup {path} ({err.strerror})"
        time.sleep(0.05)


def _remove_namespaces(
    names: Sequence[str], removed: Removed, open_ns: Sequence[Netns], vxlan: bool = True
) -> None:
    identities = {i for i in (netns_identity(n) for n in names) if i is not None}
    # Link relays live in the host namespace with TUN ends in ours: found by command line.
    relays = [st.ProcessRef.of(pid, "link relay") for pid in linkstate.relay_pids(list(names))]
    if identities or relays:
        removed.processes += _stop([*(_processes_in(identities) if identities else []), *relays])
    for ns in open_ns:
        ns.close()  # our sockets keep a namespace alive after it is unregistered
    if vxlan:
        _remove_tunnels(names, removed)
    for name in names:
        try:
            if delete_netns(name):
                removed.namespaces += 1
        except OSError as err:
            removed.problems.append(f"namespace {name} ({err.strerror})")


def _remove_tunnels(names: Sequence[str], removed: Removed) -> None:
    """Delete the VXLAN devices in these namespaces now: a namespace is freed in the
    background once unregistered, and until then its tunnels would keep their VNIs and the
    underlay's UDP socket (a quick `up` again would find its VNI taken)."""
    from pyroute2.netlink.exceptions import NetlinkError as PyNetlinkError

    from testbed.topology import vxlan

    for name in names:
        try:
            ns = Netns.open(name)
        except OSError:
            continue  # gone already, or never made
        with ns:
            try:
                removed.tunnels += vxlan.remove_all(ns)
            except PyNetlinkError as err:
                removed.problems.append(f"VXLAN tunnels in {name} ({err.args[-1]})")


def remove_run(
    state: st.RunState,
    children: Sequence[subprocess.Popen[Any]] = (),
    open_ns: Sequence[Netns] = (),
) -> Removed:
    """Remove exactly what `state` records, then its state file (kept if something stayed)."""
    removed = Removed(state.run_id)
    if state.path.exists():
        state.set_phase("tearing-down")
    removed.processes += _stop(state.pids, children)
    _remove_namespaces(state.namespaces, removed, open_ns, vxlan=state.vxlan)
    for cg in reversed(state.cgroups):
        problem = _remove_cgroup(cg)
        if problem:
            removed.problems.append(problem)
        elif not Path(cg).exists():
            removed.cgroups += 1
    # The run's cgroup parent (`edgeloc/<run>`) is not recorded itself; remove the whole tree.
    removed.cgroups += len(cgroups.remove_all(state.run_id))
    linkstate.remove_link_state(state.run_id)  # relay sockets and logs
    if not removed.problems:
        state.delete()
    return removed


def _describe_runs(runs: Sequence[st.RunState]) -> str:
    return ", ".join(f"{r.run_id} ({r.liveness()}, {r.scenario})" for r in runs) or "none"


def teardown_run(run_id: str | None) -> Removed:
    """`testbed down`: tear down one run (default: the only one that is not dead)."""
    require_root()
    runs = st.list_runs()
    alive = [r for r in runs if r.liveness() != "dead"]
    if run_id is None:
        if not alive:
            dead = [r for r in runs if r.liveness() == "dead"]
            hint = (
                f" (dead runs: {_describe_runs(dead)}; `testbed clean` removes them)"
                if dead
                else ""
            )
            raise BadInput("no live run to tear down" + hint)
        if len(alive) > 1:
            raise BadInput(
                f"several live runs: {_describe_runs(alive)}; name one: testbed down <run id>"
            )
        target = alive[0]
    else:
        found = [r for r in runs if r.run_id == run_id]
        if not found:
            raise BadInput(f"no run {run_id!r}; live runs: {_describe_runs(alive)}")
        target = found[0]
    if target.liveness() == "live" and target.owner.pid != os.getpid():
        raise BadInput(
            f"run {target.run_id} is being used by process {target.owner.pid} "
            f"({target.mode}, {target.phase}); stop that process (Ctrl-C) instead"
        )
    return remove_run(target)


def _owner_tag(name: str) -> str | None:
    """The state file path written on lo of a run namespace, or None if it carries none."""
    from pyroute2.netlink.exceptions import NetlinkError as PyNetlinkError

    try:
        ns = Netns.open(name)
    except OSError:
        return None
    try:
        links = ns.ipr.get_links(1)
        alias = links[0].get_attr("IFLA_IFALIAS") if links else None
    except PyNetlinkError:
        alias = None
    finally:
        ns.close()
    if alias and alias.startswith(OWNER_TAG):
        return alias[len(OWNER_TAG) :]
    return None


def _is_orphan(name: str, claimed: set[str]) -> bool:
    """A run-named namespace that no state file owns: none of ours claims it, and its owner tag
    (if any) names a state file that no longer exists."""
    if name in claimed or not RUN_NETNS_RE.match(name):
        return False
    owner = _owner_tag(name)
    return owner is None or not Path(owner).exists()


def clean(include_detached: bool = False) -> str:
    """`testbed clean`: remove dead runs (and detached ones with `include_detached`), then
    namespaces named like ours that no state file claims. Never touches anything else."""
    require_root()
    runs = st.list_runs()
    targets = [
        r
        for r in runs
        if r.liveness() == "dead" or (include_detached and r.liveness() == "detached")
    ]
    totals = Removed("*")
    for run in targets:
        r = remove_run(run)
        totals.namespaces += r.namespaces
        totals.processes += r.processes
        totals.cgroups += r.cgroups
        totals.tunnels += r.tunnels
        totals.problems += r.problems
    claimed = {n for r in st.list_runs() for n in r.namespaces}
    orphans = [n for n in list_netns() if _is_orphan(n, claimed)]
    orphan_removed = Removed("orphans")
    _remove_namespaces(orphans, orphan_removed, ())
    totals.processes += orphan_removed.processes
    totals.tunnels += orphan_removed.tunnels
    totals.problems += orphan_removed.problems
    # Budget trees of runs that neither a state file nor a namespace claims any more.
    live_ids = {r.run_id for r in st.list_runs()} | {
        m.group(1) for n in list_netns() if (m := RUN_NETNS_RE.match(n))
    }
    for run_id in cgroups.run_ids():
        if st.RUN_ID_RE.match(run_id) and run_id not in live_ids:
            totals.cgroups += len(cgroups.remove_all(run_id))
    from testbed import check

    preflight = check.remove_leftovers()  # what a SIGKILLed `testbed check` left
    _remove_stale_temp_files()
    left = [r for r in st.list_runs() if r.liveness() == "detached"]
    text = (
        f"cleaned {len(targets)} run(s), {orphan_removed.namespaces} orphan namespace(s) and "
        f"{len(preflight)} preflight leftover(s): " + totals.summary()
    )
    if left:
        text += (
            f"; {len(left)} detached run(s) left up ({', '.join(r.run_id for r in left)}): "
            "`testbed clean --all` or `testbed down <id>` removes them"
        )
    return text


def _remove_stale_temp_files() -> None:
    """Temp files of state writes interrupted by a kill (`.<id>.json.<pid>.tmp`)."""
    directory = st.state_dir()
    if not directory.is_dir():
        return
    for tmp in directory.glob(".*.json.*.tmp"):
        pid = tmp.name.split(".")[-2]
        if pid.isdigit() and st.proc_start_time(int(pid)) is None:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
