"""`testbed exec` and `testbed env` on a live run (`testbed up`), and Ctrl-C of a run with apps
and traffic (issue #18): the command runs in the node's namespace with the run's ROS
environment, its exit code comes back, Ctrl-C reaches it, and an interrupted run leaves none of
the processes it started."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.realrun import (
    REPO,
    lines_until_the_timeline,
    processes_mentioning,
    testbed_cli,
    testbed_popen,
)

pytestmark = [pytest.mark.root]

SCENARIO = """
name: attach-test
duration: {duration}
topology:
  cells: [{{gnb: gnb1, upf: upf1, edge: edge1}}]
  vehicles: [{{name: av1, gnb: gnb1}}]
workload: none
{extra}
report: {{link_test: false}}
"""


@pytest.fixture
def live_run(state_dir: Path, tmp_path: Path) -> Iterator[str]:
    path = tmp_path / "attach.yaml"
    path.write_text(SCENARIO.format(duration="10s", extra=""))
    up = testbed_cli("up", str(path))
    assert up.returncode == 0, up.stdout + up.stderr
    run_id = re.search(r"run ([0-9a-f]{6}) is up", up.stdout)
    assert run_id, up.stdout
    try:
        yield run_id.group(1)
    finally:
        down = testbed_cli("down", run_id.group(1))
        assert down.returncode == 0, down.stdout + down.stderr


def test_exec_runs_in_the_nodes_namespace_with_the_runs_ros_environment(live_run: str) -> None:
    from nodes.ros.env import domain_id_for

    probe = (
        "import os, socket, sys; print(os.environ['ROS_DOMAIN_ID'], "
        "os.environ['ROS_STATIC_PEERS'], open('/proc/self/net/dev').read().count(':')); "
        "sys.exit(7)"
    )
    out = testbed_cli("exec", live_run, "av1", "--", "python", "-c", probe)
    assert out.returncode == 7, out.stdout + out.stderr  # the command's own exit code
    domain, peers, _ = out.stdout.split()
    assert int(domain) == domain_id_for(live_run)
    # av1's ROS peers: its edge server (behind the UPF, on N6) and its own namespace.
    assert peers.endswith(";127.0.0.1") and peers.count(";") == 1
    addr = testbed_cli("exec", live_run, "av1", "--", "ip", "-o", "-4", "addr")
    assert "10.45.0.2/32" in addr.stdout  # the UE address: really inside av1

    env = testbed_cli("env", live_run, "edge1")
    assert env.returncode == 0, env.stderr
    assert f"export ROS_DOMAIN_ID={domain_id_for(live_run)}" in env.stdout
    assert f"ip netns exec el-{live_run}-edge1" in env.stdout
    assert "'10.45.0.2;127.0.0.1'" in env.stdout  # the edge's peer: its vehicle's UE address


def test_exec_refuses_an_unknown_node_and_reports_a_missing_program(live_run: str) -> None:
    out = testbed_cli("exec", live_run, "av9", "--", "true")
    assert out.returncode == 2 and "has no node 'av9'" in out.stderr and "av1" in out.stderr
    out = testbed_cli("exec", "abcdef", "av1", "--", "true")
    assert out.returncode == 2 and "no live run 'abcdef'" in out.stderr
    out = testbed_cli("exec", live_run, "av1", "--", "no-such-program-xyz")
    assert out.returncode == 127, out.stderr  # nsenter's "command not found"


def test_ctrl_c_reaches_the_command_of_exec(live_run: str) -> None:
    script = (
        "import signal, sys, time\n"
        "signal.signal(signal.SIGINT, lambda *_: (print('got SIGINT', flush=True), sys.exit(42)))\n"
        "print('waiting', flush=True)\n"
        "time.sleep(60)\n"
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "testbed.cli",
            "exec",
            live_run,
            "av1",
            "--",
            "python",
            "-c",
            script,
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "waiting"
    proc.send_signal(signal.SIGINT)  # what the terminal's Ctrl-C sends the foreground process
    out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 42 and "got SIGINT" in out


def test_ctrl_c_of_a_run_removes_its_apps_and_traffic_generators(
    state_dir: Path, tmp_path: Path
) -> None:
    from netem.netns import list_netns

    path = tmp_path / "attach.yaml"
    extra = """
apps:
  - {name: idle, node: edge1, command: [sleep, "613"]}
traffic:
  - {name: cbr, kind: udp, from: av1, to: edge1, rate: 2mbit}
"""
    path.write_text(SCENARIO.format(duration="60s", extra=extra))
    proc = testbed_popen("run", str(path), "--runs-dir", str(tmp_path), "--no-capacity-check")
    lines = lines_until_the_timeline(proc)
    run_id = next(m.group(1) for x in lines if (m := re.match(r"run ([0-9a-f]{6}):", x)))
    time.sleep(2)
    assert processes_mentioning("sleep 613") and processes_mentioning("nodes.traffic.gen")
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 130, "".join(lines) + out
    assert processes_mentioning("sleep 613") == []
    assert processes_mentioning(str(tmp_path / run_id)) == []
    assert [n for n in list_netns() if n.startswith(f"el-{run_id}-")] == []
