"""CPU budgets for a run's processes: one cgroup per run and node under the kernel's CPU controller.

A node of a scenario may be given a CPU budget in cores (0.5 = half a core): every process the
node runs is put into `edgeloc/<run id>/<node>` under the CPU controller, whose CFS bandwidth
quota caps what they may use together. Both controller layouts are handled:

- cgroup v2 (unified): `cpu.max` holds "<quota us> <period us>" (or "max <period us>");
- cgroup v1: `cpu.cfs_quota_us` / `cpu.cfs_period_us` in the hierarchy mounted with `cpu`.

Usage::

    with CpuBudget(run_id, "av1", cores=0.5) as budget:
        proc = subprocess.Popen(...)
        budget.add(proc.pid)
        ...                      # leaving the block moves any survivors out and removes the group

`find_leftovers(run_id)` / `remove_all(run_id)` let `testbed clean` remove what a crashed run
left; `available()` says whether this host can do any of it, and why not.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from testbed.errors import BadInput, HostError

TREE = "edgeloc"
"""Top-level cgroup holding every run's budgets (one sub-tree per run id)."""

DEFAULT_PERIOD_US = 100_000
"""CFS enforcement period: 100 ms, the kernel's default."""

MIN_QUOTA_US = 1_000
"""The kernel refuses CFS quotas below 1 ms per period."""

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_MOUNTINFO = Path("/proc/self/mountinfo")


@dataclass(frozen=True)
class CpuController:
    """Where the kernel's CPU controller is mounted and which cgroup version speaks there."""

    version: int  # 1 or 2
    mount: Path

    @property
    def tree(self) -> Path:
        """The directory holding this project's budgets (may not exist yet)."""
        return self.mount / TREE

    def describe(self) -> str:
        return f"cgroup v{self.version} cpu controller at {self.mount}"


def _unescape_mount_path(text: str) -> str:
    # mountinfo escapes space, tab, newline and backslash as \ooo octal.
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), text)


def find_controller(mountinfo: Path = _MOUNTINFO) -> CpuController | None:
    """Find the CPU controller from the mount table; cgroup v2 wins when it has `cpu` enabled."""
    v1: CpuController | None = None
    v2: CpuController | None = None
    try:
        lines = mountinfo.read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        left, sep, right = line.partition(" - ")
        if not sep:
            continue
        fields, tail = left.split(), right.split()
        if len(fields) < 5 or len(tail) < 3:
            continue
        mount = Path(_unescape_mount_path(fields[4]))
        fstype, superopts = tail[0], tail[2].split(",")
        if fstype == "cgroup" and "cpu" in superopts and v1 is None:
            v1 = CpuController(1, mount)
        elif fstype == "cgroup2" and v2 is None:
            try:
                controllers = (mount / "cgroup.controllers").read_text().split()
            except OSError:
                continue
            if "cpu" in controllers:
                v2 = CpuController(2, mount)
    return v2 or v1


def available() -> tuple[bool, str]:
    """Can this process create CPU budgets? (True, where) or (False, why not): no side effects."""
    ctl = find_controller()
    if ctl is None:
        return False, (
            "no cgroup CPU controller is mounted (looked in /proc/self/mountinfo for cgroup2 with "
            "'cpu' in cgroup.controllers and for a cgroup v1 hierarchy mounted with 'cpu')"
        )
    target = ctl.tree if ctl.tree.is_dir() else ctl.mount
    if not os.access(target, os.W_OK):
        return False, (
            f"{ctl.describe()} is not writable by uid {os.geteuid()}: run as root or delegate "
            f"{target} to this user"
        )
    return True, ctl.describe()


def _require_controller() -> CpuController:
    ok, why = available()
    ctl = find_controller()
    if not ok or ctl is None:
        raise HostError(f"cannot set CPU budgets: {why}")
    return ctl


def _check_name(what: str, name: str) -> str:
    if not _NAME.match(name) or name in (".", ".."):
        raise BadInput(
            f"{what} {name!r} cannot name a cgroup: use 1-64 letters, digits, '_', '.' or '-', "
            "starting with a letter or digit"
        )
    return name


def quota_us(cores: float, period_us: int = DEFAULT_PERIOD_US) -> int:
    """CFS quota (us per period) for a budget of `cores` CPUs; BadInput when it cannot be set."""
    if isinstance(cores, bool) or not isinstance(cores, int | float) or not math.isfinite(cores):
        raise BadInput(f"CPU budget must be a finite number of cores, got {cores!r}")
    if cores <= 0:
        raise BadInput(f"CPU budget must be > 0 cores, got {cores}")
    quota = round(cores * period_us)
    if quota < MIN_QUOTA_US:
        raise BadInput(
            f"CPU budget {cores} cores is below the kernel's minimum of "
            f"{MIN_QUOTA_US / period_us:g} cores ({MIN_QUOTA_US} us per {period_us} us period)"
        )
    return quota


MAX_PERIOD_US = 1_000_000
"""The longest CFS period the kernel accepts (1 s)."""


def period_for(cores: float) -> int:
    """The CFS period (us) that lets a budget of `cores` have at least the kernel's 1 ms quota.

    100 ms for budgets >= 0.01 cores; longer below (0.005 cores -> 200 ms), up to 1 s (so the
    least budget is 0.001 cores). A longer period means burstier throttling, so it is only
    stretched as far as the quota needs.
    """
    quota_us(cores, MAX_PERIOD_US)  # validates cores, and that 1 s is long enough
    return max(DEFAULT_PERIOD_US, min(MAX_PERIOD_US, math.ceil(MIN_QUOTA_US / cores)))


#: The quota a DNN stage's group gets per period at least: a whole head or tail call (up to
#: ~20 ms of a slow host's CPU, cold), so the kernel rarely stops one midway.
COMPUTE_QUOTA_US = 25_000


def compute_period_for(cores: float) -> int:
    """The CFS period (us) of a DNN stage's group: long enough for `COMPUTE_QUOTA_US` of quota,
    from 100 ms up to 1 s (0.025 cores: 25 ms per 1 s).

    Why not `period_for`'s shortest period: the node paces each job to the budget's speed
    anyway (`nodes.ros.common.ComputeThread`), so the quota only caps throughput, and a thread
    throttled in the middle of a torch call can make almost no progress: on a 2-vCPU VM with
    Linux 6.18 a 4 ms conv3 head, throttled at 2.5 ms per 100 ms, had not finished after 90 s
    (its thread burning its quota all the while); at 25 ms per 1 s it ran at full speed.
    """
    quota_us(cores, MAX_PERIOD_US)
    return max(DEFAULT_PERIOD_US, min(MAX_PERIOD_US, math.ceil(COMPUTE_QUOTA_US / cores)))


def _oserror_text(err: OSError) -> str:
    name = errno.errorcode.get(err.errno or 0, "")
    return f"{err.strerror or err}" + (f" ({name})" if name else "")


def _read_pids(group: Path) -> list[int]:
    try:
        return [int(x) for x in (group / "cgroup.procs").read_text().split()]
    except FileNotFoundError:
        return []


def _write(path: Path, text: str) -> None:
    # One write() per value: cgroup files act on each write, so no buffering surprises.
    fd = os.open(path, os.O_WRONLY)
    try:
        os.write(fd, text.encode())
    finally:
        os.close(fd)


def _evict_and_rmdir(ctl: CpuController, group: Path, timeout_s: float) -> None:
    """Move every process out of `group` (to the controller's root) and remove it.

    The processes keep running, unbudgeted; a supervisor that wants them dead kills them first.
    Exiting processes can keep a group busy for a moment, so rmdir is retried until `timeout_s`.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        for pid in _read_pids(group):
            try:
                _write(ctl.mount / "cgroup.procs", str(pid))
            except ProcessLookupError:
                pass  # exited meanwhile
            except OSError as err:
                raise HostError(
                    f"cannot move pid {pid} out of cgroup {group}: {_oserror_text(err)}"
                ) from None
        try:
            group.rmdir()
            return
        except FileNotFoundError:
            return
        except OSError as err:
            if err.errno not in (errno.EBUSY, errno.ENOTEMPTY) or time.monotonic() > deadline:
                left = _read_pids(group)
                raise HostError(
                    f"cannot remove cgroup {group}: {_oserror_text(err)}"
                    + (f"; processes still inside: {left}" if left else "")
                ) from None
        time.sleep(0.01)


def _rmdir_if_empty(path: Path) -> None:
    # Busy means another node or run still uses it; missing means already gone: both fine.
    with contextlib.suppress(OSError):
        path.rmdir()


class CpuBudget:
    """A CPU allowance for one node of one run: its processes together get at most `cores` CPUs.

    `cores=None` makes a group with no limit (still useful to account for and clean up a node's
    processes). The cgroup exists between `create()` (or entering the `with` block) and `remove()`.
    """

    def __init__(
        self,
        run_id: str,
        node: str,
        cores: float | None,
        *,
        period_us: int = DEFAULT_PERIOD_US,
    ) -> None:
        self.run_id = _check_name("run id", run_id)
        self.node = _check_name("node name", node)
        if not 1_000 <= period_us <= 1_000_000:
            raise BadInput(f"CFS period must be 1000..1000000 us, got {period_us}")
        self.period_us = period_us
        self.cores = cores
        if cores is not None:
            quota_us(cores, period_us)  # validate now, before anything is created
        self._ctl: CpuController | None = None

    def __repr__(self) -> str:
        return f"CpuBudget({self.run_id!r}, {self.node!r}, cores={self.cores})"

    @property
    def controller(self) -> CpuController:
        if self._ctl is None:
            self._ctl = _require_controller()
        return self._ctl

    @property
    def name(self) -> str:
        """The cgroup's name relative to the controller root, e.g. `edgeloc/3fa2c1/av1`."""
        return f"{TREE}/{self.run_id}/{self.node}"

    @property
    def path(self) -> Path:
        return self.controller.mount / self.name

    @property
    def exists(self) -> bool:
        return self.path.is_dir()

    def create(self) -> CpuBudget:
        """Make the cgroup (and its parents) and set the quota; reuses a group left by a crash."""
        ctl = self.controller
        # A concurrent remove() of another node may rmdir an empty parent between our mkdirs.
        for attempt in range(5):
            try:
                self._mkdirs(ctl)
                break
            except FileNotFoundError:
                if attempt == 4:
                    raise HostError(f"cannot create cgroup {self.path}: parent vanished") from None
            except OSError as err:
                raise HostError(f"cannot create cgroup {self.path}: {_oserror_text(err)}") from None
        try:
            self.set_cores(self.cores)
        except HostError:
            self.remove()
            raise
        return self

    def _mkdirs(self, ctl: CpuController) -> None:
        parent = ctl.mount
        for part in (TREE, self.run_id, self.node):
            if ctl.version == 2:
                # v2 only gives a child the cpu.* files if its parent delegates the controller.
                controls = (parent / "cgroup.subtree_control").read_text().split()
                if "cpu" not in controls:
                    _write(parent / "cgroup.subtree_control", "+cpu")
            parent = parent / part
            parent.mkdir(exist_ok=True)

    def set_cores(self, cores: float | None) -> None:
        """Change the budget of a live group (None = unlimited); takes effect at the next period."""
        quota = None if cores is None else quota_us(cores, self.period_us)
        group = self.path
        try:
            if self.controller.version == 2:
                _write(group / "cpu.max", f"{'max' if quota is None else quota} {self.period_us}")
            else:
                # Set the quota to -1 first: a new period must not make the old quota invalid.
                _write(group / "cpu.cfs_quota_us", "-1")
                _write(group / "cpu.cfs_period_us", str(self.period_us))
                _write(group / "cpu.cfs_quota_us", str(-1 if quota is None else quota))
        except OSError as err:
            raise HostError(
                f"cannot set CPU budget {cores} cores on cgroup {group}: {_oserror_text(err)}"
            ) from None
        self.cores = cores

    def limit(self) -> tuple[int | None, int]:
        """(quota us or None for unlimited, period us) as the kernel reports it now."""
        group = self.path
        if self.controller.version == 2:
            quota_text, period_text = (group / "cpu.max").read_text().split()
            return (None if quota_text == "max" else int(quota_text)), int(period_text)
        quota = int((group / "cpu.cfs_quota_us").read_text())
        period = int((group / "cpu.cfs_period_us").read_text())
        return (None if quota < 0 else quota), period

    def add(self, pid: int) -> None:
        """Put process `pid` (all its threads) under this budget; children it forks stay in it."""
        try:
            _write(self.path / "cgroup.procs", str(int(pid)))
        except OSError as err:
            raise HostError(
                f"cannot put pid {pid} into cgroup {self.path}: {_oserror_text(err)}"
            ) from None

    def threads(self) -> list[int]:
        """Thread ids now in the group (v1 `tasks`; v2 `cgroup.threads`)."""
        name = "tasks" if self.controller.version == 1 else "cgroup.threads"
        try:
            return [int(x) for x in (self.path / name).read_text().split()]
        except FileNotFoundError:
            return []

    def pids(self) -> list[int]:
        """Processes (thread-group ids) now in the group."""
        return _read_pids(self.path)

    def stats(self) -> dict[str, int]:
        """The kernel's `cpu.stat` counters (throttling: nr_periods, nr_throttled, ...)."""
        out: dict[str, int] = {}
        for line in (self.path / "cpu.stat").read_text().splitlines():
            key, _, value = line.partition(" ")
            if value.strip().lstrip("-").isdigit():
                out[key] = int(value)
        return out

    def remove(self, timeout_s: float = 2.0) -> None:
        """Move the group's processes out, remove it, and remove the run's directory if empty."""
        ctl = self.controller
        _evict_and_rmdir(ctl, self.path, timeout_s)
        _rmdir_if_empty(ctl.tree / self.run_id)
        _rmdir_if_empty(ctl.tree)

    def __enter__(self) -> CpuBudget:
        return self.create()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.remove()


def run_ids() -> list[str]:
    """Run ids that have a budget sub-tree on this host (live or left by a crash)."""
    ctl = find_controller()
    if ctl is None or not ctl.tree.is_dir():
        return []
    return sorted(p.name for p in ctl.tree.iterdir() if p.is_dir())


def find_leftovers(run_id: str) -> list[Path]:
    """Every cgroup directory of `run_id`, deepest first (the order they must be removed in)."""
    _check_name("run id", run_id)
    ctl = find_controller()
    if ctl is None:
        return []
    root = ctl.tree / run_id
    if not root.is_dir():
        return []
    found = [Path(dirpath) for dirpath, _, _ in os.walk(root)]
    return sorted(found, key=lambda p: (-len(p.parts), str(p)))


def remove_all(run_id: str, timeout_s: float = 2.0) -> list[Path]:
    """Remove every cgroup of `run_id`, moving any processes out first; returns what was removed."""
    leftovers = find_leftovers(run_id)
    if not leftovers:
        return []
    ctl = _require_controller()
    for group in leftovers:
        _evict_and_rmdir(ctl, group, timeout_s)
    _rmdir_if_empty(ctl.tree)
    return leftovers
