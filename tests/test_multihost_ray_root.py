"""`testbed up FILE --engine ray` and `testbed down ID --engine ray` (issue #20 part 3) on two
"host" namespaces joined by a veth underlay (`tests/test_multihost_root.py`'s), each running a
Ray node of its own inside it, as two machines would: the head in host a with the resource
`testbed-host-a`, a worker in host b joining it over the underlay with `testbed-host-b`.

What must hold: one `up --engine ray` from host a builds each host's part on that host's node
(av1 on host a reaches core1 on host b through the tunnel, with the backhaul's delay); one
`down --engine ray` leaves nothing of the run in either host; a host without a node is a clear
error before anything is built; and a host whose `up` fails fails the command, with the host
that came up taken down again.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from netem.netns import delete_netns, list_netns
from testbed.namespaces import Netns
from tests import test_multihost_root as mh

pytestmark = [pytest.mark.root, pytest.mark.alone]

pytest.importorskip(
    "ray", reason="Ray is the optional extra: pip install '.[ray]' (make test installs it)"
)

#: The two hosts (namespaces, underlay, private state dirs), made and removed by that module.
hosts = mh.hosts
#: The port of the head's GCS, in host a's namespace (nothing else listens there).
PORT = 6390
ADDRESS = f"{mh.UNDERLAY_A}:{PORT}"


@pytest.fixture(autouse=True)
def _no_ray_tokens(monkeypatch: pytest.MonkeyPatch) -> None:
    """As tests/test_sweep_ray.py: these clusters go without Ray's token authentication, so
    that they neither depend on nor leave a token in the home folder."""
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")


class RayNodes:
    """Ray nodes started inside host namespaces, each `ray start --block` in its own process
    group, with the host's state dir in its environment (Ray's workers, and the testbed
    processes they start, inherit it: each host keeps its own runs, as on its own machine)."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.procs: list[tuple[str, subprocess.Popen[bytes]]] = []

    def start(self, host: mh.Host, address: str, *args: str) -> None:
        env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
        env.update(EDGELOC_STATE_DIR=str(host.state), RAY_AUTH_MODE="disabled")
        resources = json.dumps({f"testbed-host-{host.name}": 1})
        with open(self.logs / f"ray-{host.name}.log", "wb") as log:
            proc = subprocess.Popen(
                ["nsenter", f"--net=/run/netns/{host.netns}", "--",
                 sys.executable, "-m", "ray.scripts.scripts", "start", "--block",
                 "--node-ip-address", address, "--resources", resources, "--num-cpus", "1",
                 "--object-store-memory", str(100 * 2**20), "--disable-usage-stats", *args],
                stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True,
            )  # fmt: skip
        self.procs.append((host.name, proc))
        deadline = time.monotonic() + 120
        while b"Ray runtime started" not in (self.logs / f"ray-{host.name}.log").read_bytes():
            assert proc.poll() is None, (self.logs / f"ray-{host.name}.log").read_text()
            assert time.monotonic() < deadline, f"Ray did not start in host {host.name}"
            time.sleep(0.5)

    def wait_alive(self, host: mh.Host, count: int) -> None:
        """Until the cluster has `count` live nodes (asked from inside `host`)."""
        code = (
            f"import ray; ray.init(address={ADDRESS!r}, logging_level='ERROR'); "
            "print(sum(1 for n in ray.nodes() if n['Alive']))"
        )
        deadline = time.monotonic() + 60
        while True:
            probe = subprocess.run(
                ["nsenter", f"--net=/run/netns/{host.netns}", "--", sys.executable, "-c", code],
                capture_output=True, text=True, timeout=60,
            )  # fmt: skip
            if probe.returncode == 0 and int(probe.stdout.split()[-1]) >= count:
                return
            assert time.monotonic() < deadline, probe.stdout + probe.stderr
            time.sleep(1)

    def stop(self) -> None:
        """The worker first, then the head: SIGTERM to `ray start` alone (with the head's GCS
        still up, its drain is quick; SIGTERM to the whole group kills the GCS first and makes
        the drain wait out its 30 s), then SIGKILL to whatever of its group is left."""
        for _, proc in reversed(self.procs):
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(40)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
        # `ray start --head` leaves its address for a later bare `ray.init()` to join.
        current = Path(tempfile.gettempdir()) / "ray" / "ray_current_cluster"
        with contextlib.suppress(OSError):
            if current.read_text().strip() == ADDRESS:
                current.unlink()


@pytest.fixture
def ray_nodes(hosts: tuple[mh.Host, mh.Host], tmp_path: Path) -> Iterator[RayNodes]:
    nodes = RayNodes(tmp_path)
    try:
        yield nodes
    finally:
        nodes.stop()


def _run_namespaces(run_id: str) -> list[str]:
    return sorted(n for n in list_netns() if n.startswith(f"el-{run_id}-"))


def test_one_up_and_one_down_through_ray_build_and_remove_every_hosts_part(
    hosts: tuple[mh.Host, mh.Host], ray_nodes: RayNodes, tmp_path: Path
) -> None:
    a, b = hosts
    path = mh._scenario(tmp_path, mh.DELAY_MS)
    ray_nodes.start(a, mh.UNDERLAY_A, "--head", "--port", str(PORT),
                    "--include-dashboard", "false")  # fmt: skip

    # Only host a has a node: nothing is built, and the error says how to start b's.
    early = secrets.token_hex(3)
    out = a.testbed("up", str(path), "--engine", "ray", "--address", ADDRESS, "--run-id", early)
    assert out.returncode == 3, out.stdout + out.stderr
    assert "no Ray node for host(s) b of topology.hosts" in out.stderr
    assert """--resources='{"testbed-host-b": 1}'""" in out.stderr
    assert _run_namespaces(early) == []

    ray_nodes.start(b, mh.UNDERLAY_B, "--address", ADDRESS)
    ray_nodes.wait_alive(a, 2)

    run_id = secrets.token_hex(3)
    t0 = time.monotonic()
    up = a.testbed("up", str(path), "--engine", "ray", "--address", ADDRESS, "--run-id", run_id)
    up_s = time.monotonic() - t0
    print(f"\n`testbed up --engine ray` on two hosts: {up_s:.1f} s\n{up.stdout}{up.stderr}")
    try:
        assert up.returncode == 0, up.stdout + up.stderr
        # Each part on its own host's node, with that host's state dir.
        assert "host a (" in up.stdout and f"{mh.UNDERLAY_A}): up in" in up.stdout
        assert f"{mh.UNDERLAY_B}): up in" in up.stdout
        assert f"run {run_id} is up on host b: 1 namespaces" in up.stdout
        assert f"run {run_id} is up on 2 hosts (a, b)" in up.stdout
        assert "build the other hosts' parts" not in up.stdout
        for host in hosts:
            assert (host.state / f"{run_id}.json").is_file(), f"no state file on {host.name}"
        assert f"el-{run_id}-vx-gnb1-core1" in list_netns()
        _, before = mh._tunnel_of_core1(run_id)
        rtts = mh._rtts_ms(run_id, count=10)
        print(f"av1 -> core1 across the tunnel: RTT median {mh._median(rtts):.2f} ms")
        assert mh._median(rtts) >= 2 * mh.DELAY_MS
        assert mh._tunnel_of_core1(run_id)[1] >= before + 10
    finally:
        t0 = time.monotonic()
        down = a.testbed("down", run_id, "--engine", "ray", "--address", ADDRESS)
        print(f"`testbed down --engine ray`: {time.monotonic() - t0:.1f} s\n{down.stdout}")
    assert down.returncode == 0, down.stdout + down.stderr
    assert down.stdout.count(f"run {run_id} is down") == 2
    assert down.stdout.count("1 VXLAN tunnel(s)") == 2
    mh._assert_nothing_left(hosts, run_id)

    # A run no host has: said so, exit 2.
    none = a.testbed("down", run_id, "--engine", "ray", "--address", ADDRESS)
    assert none.returncode == 2, none.stdout + none.stderr
    assert f"no host of the Ray cluster (a, b) has run {run_id}" in none.stderr

    # Host b's `up` fails (its namespace of the run exists already): the command fails with
    # b's exit code, and host a, which came up, is taken down again.
    bad = secrets.token_hex(3)
    squatter = Netns.create(f"el-{bad}-core1")
    squatter.close()
    try:
        out = a.testbed("up", str(path), "--engine", "ray", "--address", ADDRESS, "--run-id", bad)
        print(out.stdout + out.stderr)
        assert out.returncode == 2, out.stdout + out.stderr
        assert "host b (" in out.stderr and "`testbed up` failed (exit 2)" in out.stderr
        assert f"run id {bad} is already in use on this host" in out.stdout
        assert f"host a: taken down again: run {bad} is down" in out.stdout
        assert _run_namespaces(bad) == [f"el-{bad}-core1"]
        for host in hosts:
            assert mh._vxlan_devices(host.netns) == []
            assert not (host.state / f"{bad}.json").exists()
    finally:
        delete_netns(f"el-{bad}-core1")
