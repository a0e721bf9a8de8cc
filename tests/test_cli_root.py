"""The CLI as a user runs it: `testbed up`, `down`, `run`, and `clean` after a SIGKILL.

Each test runs the real `testbed` executable in a subprocess with a private state directory
(EDGELOC_STATE_DIR), so it only ever sees and removes runs it made itself.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest

from netem.netns import list_netns
from testbed import state as st
from testbed.capacity import CACHE_FILE
from testbed.namespaces import Netns
from tests.realrun import TESTBED, testbed_cli

pytestmark = pytest.mark.root

REPO = Path(__file__).resolve().parents[1]


def _ours(run_id: str) -> list[str]:
    return [n for n in list_netns() if n.startswith(f"el-{run_id}-")]


def _big_scenario(path: Path, vehicles: int, cells: int) -> Path:
    cell_lines = "".join(f"    - {{gnb: gnb{c}, core: core{c}}}\n" for c in range(cells))
    veh_lines = "".join(f"    - {{name: av{v}, gnb: gnb{v % cells}}}\n" for v in range(vehicles))
    path.write_text(
        "name: big\nseed: 1\nduration: 10s\ntopology:\n  cells:\n"
        + cell_lines
        + "  vehicles:\n"
        + veh_lines
        + "links:\n  air:\n    uplink: {rate: 50mbit}\n    downlink: {rate: 100mbit}\n"
        "  backhaul:\n    uplink: {rate: 1gbit}\n    downlink: {rate: 1gbit}\n"
    )
    return path


def test_up_carries_packets_and_down_leaves_nothing(state_dir: Path) -> None:
    links_before = os.listdir("/sys/class/net")
    up = testbed_cli("up", "scenarios/smoke.yaml")
    assert up.returncode == 0, up.stderr
    run_id = re.search(r"run ([0-9a-f]{6}) is up", up.stdout).group(1)
    assert re.search(r"link backend: (userspace|tc) \(auto: ", up.stdout)
    names = _ours(run_id)
    assert len(names) == 4  # av1, gnb1, upf1, edge1
    # A datagram from the vehicle's namespace reaches the edge server's through the gNB, the
    # GTP-U tunnel on N3 and the UPF, from the UE's pool address.
    run = st.load_run(run_id)
    assert run is not None and run.liveness() == "detached"
    av1 = next(n for n in names if n.endswith("-av1"))
    edge1 = next(n for n in names if n.endswith("-edge1"))
    with Netns.open(edge1) as edge, Netns.open(av1) as vehicle:
        edge_ip = edge.ipr.get_addr(label="upf1")[0].get_attr("IFA_ADDRESS")
        srv = edge.socket()
        cli = vehicle.socket()
        try:
            srv.bind((edge_ip, 0))
            srv.settimeout(2)
            cli.sendto(b"through the gnb", (edge_ip, srv.getsockname()[1]))
            data, sender = srv.recvfrom(64)
            assert (data, sender[0]) == (b"through the gnb", "10.45.0.2")
        finally:
            srv.close()
            cli.close()
    assert os.listdir("/sys/class/net") == links_before  # nothing in the host namespace

    down = testbed_cli("down", run_id)
    assert down.returncode == 0, down.stderr
    assert _ours(run_id) == []
    assert st.list_runs() == []
    assert os.listdir("/sys/class/net") == links_before
    status = testbed_cli("status")
    assert status.stdout.strip() == "no runs"


def test_sigkill_of_up_midway_then_clean_leaves_nothing(state_dir: Path, tmp_path: Path) -> None:
    scenario = _big_scenario(tmp_path / "big.yaml", vehicles=20, cells=4)
    proc = subprocess.Popen(
        [*TESTBED, "up", str(scenario)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    run_id = None
    deadline = time.monotonic() + 30
    try:
        # Kill it once some, but not all, of its 28 namespaces exist.
        while time.monotonic() < deadline and proc.poll() is None:
            runs = st.list_runs()
            if runs:
                run_id = runs[0].run_id
                if 0 < len(_ours(run_id)) < 28:
                    break
            time.sleep(0.001)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert run_id is not None, "testbed up never wrote its state file"
    assert st.load_run(run_id).liveness() in ("dead", "detached")
    cleaned = testbed_cli("clean", "--all")
    assert cleaned.returncode == 0, cleaned.stderr
    assert _ours(run_id) == []
    assert st.list_runs() == []


def test_run_leaves_a_run_folder_and_no_namespaces(state_dir: Path, tmp_path: Path) -> None:
    (state_dir / CACHE_FILE).unlink(missing_ok=True)  # conftest's copy: this run measures it
    # The smoke scenario, shortened to 3 s with its second uplink phase at 2 s.
    short = tmp_path / "smoke-short.yaml"
    short.write_text(
        (REPO / "scenarios/smoke.yaml")
        .read_text()
        .replace("duration: 20s", "duration: 3s")
        .replace("at: 10s", "at: 2s")
    )
    runs = tmp_path / "runs"
    result = testbed_cli("run", str(short), "--runs-dir", str(runs))
    assert result.returncode == 0, result.stdout + result.stderr
    (folder,) = runs.iterdir()
    run = json.loads((folder / "run.json").read_text())
    assert run["ok"] is True and run["run_id"] == folder.name
    assert run["link_backend"].startswith(("userspace (", "tc ("))
    # Before the network is built: the link rates against this host's data plane (measured
    # now: the state dir is fresh), in run.json too.
    assert run["capacity"]["backend"] == run["link_backend"]
    lines = result.stdout.splitlines()
    built = next(i for i, line in enumerate(lines) if line.startswith(f"run {folder.name}: "))
    if run["link_backend"].startswith("userspace"):
        assert run["capacity"]["data_plane"]["tcp_bps"] > 0
        assert "measuring this host's userspace data plane" in "\n".join(lines[:built])
        assert any(line.startswith("host data plane: TCP ") for line in lines[:built])
    assert run["timeline"]["applied"] == 2 and run["timeline"]["lateness"]["count"] == 2
    events = [json.loads(x) for x in (folder / "events.jsonl").read_text().splitlines()]
    assert [(e["kind"], e["scheduled_s"]) for e in events] == [("shape", 0.0), ("shape", 2.0)]
    assert "shape av1 uplink 8 Mbit/s" in result.stdout
    echoes = json.loads((folder / "connectivity.json").read_text())
    assert [(e["src"], e["dst"], e["received"]) for e in echoes] == [("av1", "edge1", 5)]
    assert (folder / "scenario.yaml").read_text() == short.read_text()
    assert _ours(folder.name) == []
    assert st.list_runs() == []


def test_up_dry_run_prints_ip_and_link_commands(state_dir: Path) -> None:
    result = testbed_cli("up", "--dry-run", "scenarios/smoke.yaml")
    assert result.returncode == 0, result.stderr
    assert "ip netns add el-" in result.stdout
    # tc lines where the kernel has netem, relay command lines where it does not
    assert "tc -n el-" in result.stdout or "-m netem.relay --netns-a el-" in result.stdout
    assert st.list_runs() == []


@pytest.mark.alone  # compares every el- namespace of the host before and after
def test_bad_scenario_exits_2_and_creates_nothing(state_dir: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        (REPO / "scenarios/smoke.yaml")
        .read_text()
        .replace("{name: av1, gnb: gnb1}", "{name: av1, gnb: gnb9}")
    )
    before = [n for n in list_netns() if n.startswith("el-")]
    result = testbed_cli("up", str(bad))
    assert result.returncode == 2
    assert "bad.yaml:" in result.stderr and "gnb9" in result.stderr
    assert [n for n in list_netns() if n.startswith("el-")] == before
    assert st.list_runs() == []
