"""A sweep's real run under Ray is forked from a fork server (`rayengine._run_apart`), not
started as a fresh interpreter: what it sends back, and that it dies with the worker that
started it even though the fork server, its parent, outlives that worker."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from testbed.errors import BadInput, HostError
from testbed.scenario import load
from testbed.sweep.jobs import Job
from testbed.sweep.rayengine import ANSWER_FILE, PROGRESS_FILE, _run_apart

REPO = Path(__file__).resolve().parents[1]

#: A stand-in for a Ray worker: starts one child through a fork server, as `_run_apart` does,
#: whose target calls `_die_with_worker` and then outlives any test unless it is killed.
WORKER = """
import multiprocessing, os, sys, time
from testbed.sweep import rayengine

def target(pid_file):
    rayengine._die_with_worker()
    with open(pid_file, "w") as f:
        f.write(str(os.getpid()))
    time.sleep(120)

if __name__ == "__main__":
    child = multiprocessing.get_context("forkserver").Process(target=target, args=(sys.argv[1],))
    child.start()
    child.join()
"""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
def test_a_forked_run_dies_with_the_worker_even_though_the_fork_server_lives_on(
    tmp_path: Path,
) -> None:
    script, pid_file = tmp_path / "worker.py", tmp_path / "child.pid"
    script.write_text(WORKER)
    worker = subprocess.Popen(
        [sys.executable, str(script), str(pid_file)], cwd=REPO, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 60
        while not pid_file.is_file() or not pid_file.read_text():
            assert worker.poll() is None, "the stand-in worker ended early"
            assert time.monotonic() < deadline, "the child never started"
            time.sleep(0.1)
        child = int(pid_file.read_text())
        assert _alive(child)
        os.kill(worker.pid, signal.SIGKILL)  # the worker alone, not its process group
        worker.wait()
        deadline = time.monotonic() + 5
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child), "the run outlived the worker that started it"
    finally:
        os.killpg(worker.pid, signal.SIGKILL)  # the fork server, and the child if it lived on
        worker.wait()


@pytest.mark.slow
def test_a_forked_run_sends_back_what_it_raised_through_the_task_folder(
    tmp_path: Path,
) -> None:
    """The run's answer comes back through the task folder: here the BadInput (or, without
    root, HostError) that `testbed run` raises for a results folder that cannot be made."""
    scenario = load(REPO / "scenarios" / "smoke.yaml")
    job = Job(0, 7, "v0-seed7", {"seed": "7"}, scenario, "", "variant 1/1: seed=7")
    (tmp_path / "runs").write_text("a file where the runs folder would go\n")
    lines: list[str] = []
    with pytest.raises((BadInput, HostError)) as err:
        _run_apart(job, tmp_path, lines)
    if os.geteuid() == 0:
        assert isinstance(err.value, BadInput) and "runs" in str(err.value), err.value
    assert (tmp_path / ANSWER_FILE).is_file() and (tmp_path / PROGRESS_FILE).is_file()
    assert (tmp_path / "runs").read_text().startswith("a file")  # untouched: nothing was built
