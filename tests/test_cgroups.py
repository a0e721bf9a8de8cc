"""CPU budgets: the kernel really caps a budgeted process, and removal leaves no cgroup behind."""

from __future__ import annotations

import math
import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from testbed import cgroups
from testbed.cgroups import CpuBudget, CpuController
from testbed.errors import BadInput, HostError

BUSY = "while True: pass"
CLK_TCK = os.sysconf("SC_CLK_TCK")


def _cpu_seconds(pid: int) -> float:
    """utime + stime of a process from /proc (independent of the cgroup's own accounting)."""
    stat = Path(f"/proc/{pid}/stat").read_text()
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def _cgroup_of(pid: int, ctl: CpuController) -> str:
    """The pid's cgroup path in the CPU controller's hierarchy, from /proc/<pid>/cgroup."""
    for line in Path(f"/proc/{pid}/cgroup").read_text().splitlines():
        _, controllers, path = line.split(":", 2)
        if (ctl.version == 2 and controllers == "") or "cpu" in controllers.split(","):
            return path
    raise AssertionError(f"pid {pid} has no cpu cgroup")


@pytest.fixture
def run_id() -> Iterator[str]:
    ok, why = cgroups.available()
    if not ok:
        pytest.skip(f"no usable cgroup CPU controller: {why}")
    rid = f"elchk-{secrets.token_hex(4)}"
    try:
        yield rid
    finally:
        cgroups.remove_all(rid)


@pytest.fixture
def procs() -> Iterator[list[subprocess.Popen[bytes]]]:
    """Child processes a test starts; all killed and reaped at the end."""
    started: list[subprocess.Popen[bytes]] = []
    try:
        yield started
    finally:
        for p in started:
            if p.poll() is None:
                p.send_signal(signal.SIGKILL)
            p.wait()


def _spawn(procs: list[subprocess.Popen[bytes]], code: str) -> subprocess.Popen[bytes]:
    p = subprocess.Popen([sys.executable, "-S", "-c", code])
    procs.append(p)
    return p


@pytest.mark.root
def test_budget_caps_a_busy_loop(run_id: str, procs: list[subprocess.Popen[bytes]]) -> None:
    limited = CpuBudget(run_id, "limited", 0.2)
    free = CpuBudget(run_id, "free", None)
    with limited, free:
        assert limited.limit() == (20_000, 100_000)
        assert free.limit() == (None, 100_000)
        slow, fast = _spawn(procs, BUSY), _spawn(procs, BUSY)
        limited.add(slow.pid)
        free.add(fast.pid)
        assert limited.pids() == [slow.pid]
        assert _cgroup_of(slow.pid, limited.controller).endswith(f"/{run_id}/limited")
        time.sleep(0.2)  # let both interpreters start
        t0, s0, f0 = time.monotonic(), _cpu_seconds(slow.pid), _cpu_seconds(fast.pid)
        time.sleep(1.5)
        wall = time.monotonic() - t0
        slow_share = (_cpu_seconds(slow.pid) - s0) / wall
        fast_share = (_cpu_seconds(fast.pid) - f0) / wall
        throttled = limited.stats().get("nr_throttled", 0)
        for p in (slow, fast):
            p.kill()
            p.wait()
        paths = [limited.path, free.path]
    print(f"0.2-core budget: {slow_share:.0%} of a core; unlimited: {fast_share:.0%}")
    assert 0.10 <= slow_share <= 0.35, f"budgeted loop used {slow_share:.0%} of a core"
    # The unlimited loop competes with whatever else runs on the host, so only ask for a clear
    # margin over the budget rather than a full core.
    assert fast_share > 1.5 * slow_share, f"unlimited loop used only {fast_share:.0%}"
    assert throttled > 0
    for path in paths:
        assert not path.exists()
    assert not (paths[0].parent).exists()  # the run's directory went with its last node
    assert cgroups.find_leftovers(run_id) == []


@pytest.mark.root
def test_remove_moves_live_processes_out(run_id: str, procs: list[subprocess.Popen[bytes]]) -> None:
    budget = CpuBudget(run_id, "av1", 0.5).create()
    sleeper = _spawn(procs, "import time; time.sleep(60)")
    budget.add(sleeper.pid)
    budget.remove()
    assert not budget.path.exists()
    assert sleeper.poll() is None, "remove() must not kill the process"
    assert run_id not in _cgroup_of(sleeper.pid, budget.controller)


@pytest.mark.root
def test_set_cores_changes_a_live_budget(run_id: str) -> None:
    with CpuBudget(run_id, "gnb", 1.5, period_us=50_000) as budget:
        assert budget.limit() == (75_000, 50_000)
        budget.set_cores(0.25)
        assert budget.limit() == (12_500, 50_000)
        budget.set_cores(None)
        assert budget.limit() == (None, 50_000)
    assert not budget.exists


@pytest.mark.root
def test_remove_all_cleans_what_a_crash_left(
    run_id: str, procs: list[subprocess.Popen[bytes]]
) -> None:
    # A "crashed" run: two budgets created, a process inside one, nothing removed.
    a = CpuBudget(run_id, "av1", 0.3).create()
    CpuBudget(run_id, "core", 1.0).create()
    sleeper = _spawn(procs, "import time; time.sleep(60)")
    a.add(sleeper.pid)
    leftovers = cgroups.find_leftovers(run_id)
    assert [p.name for p in leftovers[:2]] == sorted(["av1", "core"])
    assert leftovers[-1].name == run_id  # deepest first, the run's directory last
    assert run_id in cgroups.run_ids()

    removed = cgroups.remove_all(run_id)
    assert removed == leftovers
    assert cgroups.find_leftovers(run_id) == []
    assert run_id not in cgroups.run_ids()
    assert all(not p.exists() for p in removed)
    assert sleeper.poll() is None


@pytest.mark.root
def test_adding_a_dead_pid_is_a_clear_error(run_id: str) -> None:
    gone = subprocess.Popen([sys.executable, "-S", "-c", "pass"])
    gone.wait()
    with (
        CpuBudget(run_id, "av1", 0.5) as budget,
        pytest.raises(HostError, match=rf"cannot put pid {gone.pid} into cgroup"),
    ):
        budget.add(gone.pid)


@pytest.mark.parametrize(
    ("cores", "message"),
    [
        (0, "must be > 0 cores"),
        (-1.0, "must be > 0 cores"),
        (math.nan, "finite number of cores"),
        (math.inf, "finite number of cores"),
        (True, "finite number of cores"),
        ("half", "finite number of cores"),
        (0.005, "below the kernel's minimum of 0.01 cores"),
    ],
)
def test_bad_budgets_are_refused_before_anything_is_made(cores: object, message: str) -> None:
    with pytest.raises(BadInput, match=message):
        CpuBudget("elchk-00000000", "av1", cores)  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ["", "a/b", "..", ".hidden", "x" * 65, "sp ace"])
def test_names_that_cannot_be_a_cgroup_are_refused(name: str) -> None:
    with pytest.raises(BadInput, match="cannot name a cgroup"):
        CpuBudget("elchk-00000000", name, 0.5)
    with pytest.raises(BadInput, match="cannot name a cgroup"):
        cgroups.find_leftovers(name)


def test_quota_from_cores() -> None:
    assert cgroups.quota_us(0.5) == 50_000
    assert cgroups.quota_us(2) == 200_000
    assert cgroups.quota_us(0.2, period_us=10_000) == 2_000


def test_find_controller_reads_v1_and_v2_mounts(tmp_path: Path) -> None:
    v1 = tmp_path / "cpu,cpuacct"
    v2 = tmp_path / "unified dir"
    v2.mkdir()
    (v2 / "cgroup.controllers").write_text("memory pids\n")
    info = tmp_path / "mountinfo"
    escaped_v2 = str(v2).replace(" ", "\\040")
    info.write_text(
        f"30 25 0:26 / {escaped_v2} rw,relatime shared:4 - cgroup2 cgroup2 rw\n"
        f"31 25 0:27 / {v1} rw,relatime shared:5 - cgroup cgroup rw,cpu,cpuacct\n"
        "32 25 0:28 / /sys/fs/cgroup/cpuset rw - cgroup cgroup rw,cpuset\n"
    )
    # v2 without the cpu controller enabled: the v1 hierarchy carries it.
    assert cgroups.find_controller(info) == CpuController(1, v1)
    (v2 / "cgroup.controllers").write_text("cpu memory pids\n")
    assert cgroups.find_controller(info) == CpuController(2, v2)
    assert cgroups.find_controller(tmp_path / "missing") is None
