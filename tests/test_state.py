"""Run state files: round trip, atomic writes, liveness, pid-reuse safety (no root needed)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from testbed import state as st


@pytest.fixture(autouse=True)
def state_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    d = tmp_path / "state"
    monkeypatch.setenv(st.STATE_DIR_ENV, str(d))
    return d


def _dead_process() -> st.ProcessRef:
    """A ProcessRef of a process that has exited and been reaped."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    ref = st.ProcessRef.of(proc.pid, "victim")
    proc.kill()
    proc.wait()
    return ref


def _run(mode: st.Mode = "run", owner: st.ProcessRef | None = None) -> st.RunState:
    run = st.new_run("demo", "/somewhere/demo.yaml", mode, "a1b2c3", "10.200.0.0/16")
    if owner is not None:
        run.owner = owner
    return run


def test_state_dir_follows_env(state_dir: Path) -> None:
    assert st.state_dir() == state_dir


def test_round_trip_keeps_every_field(state_dir: Path) -> None:
    run = _run()
    run.record_namespaces(["el-a1b2c3-av1", "el-a1b2c3-gnb1"])
    run.record_pid(st.ProcessRef.of(os.getpid(), "me"))
    run.record_cgroup("/sys/fs/cgroup/cpu/el-a1b2c3-av1")
    loaded = st.load_run("a1b2c3")
    assert loaded is not None
    assert loaded.to_dict() == run.to_dict()
    on_disk = json.loads((state_dir / "a1b2c3.json").read_text())
    for key in ("run_id", "scenario", "scenario_path", "owner", "mode", "phase", "pool"):
        assert key in on_disk
    assert on_disk["namespaces"] == ["el-a1b2c3-av1", "el-a1b2c3-gnb1"]
    assert on_disk["pids"][0]["pid"] == os.getpid()
    assert on_disk["cgroups"] == ["/sys/fs/cgroup/cpu/el-a1b2c3-av1"]


def test_records_are_written_ahead_and_atomically(state_dir: Path) -> None:
    run = _run()
    run.save()
    run.record_namespaces(["el-a1b2c3-av1"])
    # Every record is on disk at once, and no temp file is left behind.
    assert st.load_run("a1b2c3").namespaces == ["el-a1b2c3-av1"]  # type: ignore[union-attr]
    assert [p.name for p in state_dir.iterdir() if p.name != ".lock"] == ["a1b2c3.json"]
    run.record_namespaces(["el-a1b2c3-av1"])  # recording twice keeps one entry
    assert st.load_run("a1b2c3").namespaces == ["el-a1b2c3-av1"]  # type: ignore[union-attr]


def test_proc_start_time_identifies_a_process() -> None:
    me = st.ProcessRef.of(os.getpid())
    assert me.start > 0 and me.alive()
    assert not st.ProcessRef(os.getpid(), me.start + 1).alive(), "a reused pid must not match"
    assert not _dead_process().alive()


@pytest.mark.parametrize(
    ("mode", "phase", "owner_alive", "expected"),
    [
        ("run", "up", True, "live"),
        ("run", "up", False, "dead"),
        ("run", "building", False, "dead"),
        ("run", "tearing-down", False, "dead"),
        ("up", "building", True, "live"),
        ("up", "building", False, "dead"),
        ("up", "up", False, "detached"),
        ("up", "up", True, "detached"),
        ("up", "tearing-down", False, "dead"),
    ],
)
def test_liveness(mode: st.Mode, phase: st.Phase, owner_alive: bool, expected: str) -> None:
    owner = st.ProcessRef.of(os.getpid()) if owner_alive else _dead_process()
    run = _run(mode, owner)
    run.phase = phase
    assert run.liveness() == expected


def test_list_runs_reads_every_run_and_skips_foreign_files(state_dir: Path) -> None:
    first = _run()
    first.save()
    second = st.new_run("other", None, "up", "0f0f0f", None)
    second.started = first.started + 1
    second.save()
    (state_dir / "notes.json").write_text("{}")  # not a run id
    (state_dir / "abcdef.json").write_text("{broken")  # unreadable
    assert [r.run_id for r in st.list_runs()] == ["a1b2c3", "0f0f0f"]


def test_list_runs_without_a_state_dir_is_empty() -> None:
    assert st.list_runs() == []


def test_describe_is_json_ready() -> None:
    run = _run()
    d = run.describe()
    json.dumps(d)
    assert d["liveness"] == "live" and d["run_id"] == "a1b2c3"
    assert run.started_text() == d["started_text"]


def test_fresh_run_id_is_six_hex_and_avoids_taken(state_dir: Path) -> None:
    _run().save()
    ids = {st.fresh_run_id({"a1b2c3"}) for _ in range(50)}
    assert all(st.RUN_ID_RE.match(i) for i in ids)
    assert "a1b2c3" not in ids


def test_delete_removes_the_file(state_dir: Path) -> None:
    run = _run()
    run.save()
    run.delete()
    run.delete()  # twice is fine
    assert st.load_run("a1b2c3") is None
