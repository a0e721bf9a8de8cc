"""EdgeLoc for real: `run_scenario` starts every node as its own rclpy process in its namespace,
inference requests cross the emulated air link, the vehicle publishes fused poses at the frame
rate, and teardown leaves nothing. Plus the paper's fault tolerance: when the edge server dies,
the vehicle keeps publishing fused poses (VO dead-reckoning) and charges the learner the
timeout.

Each test writes its own short scenario (the default one, 15 s, no link self-test). Figures
(pose rate, requests/s, bytes on the air link) are printed with `-s`.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest

from tests.realrun import lines_until_the_timeline, processes_mentioning, testbed_popen

pytestmark = [pytest.mark.root, pytest.mark.ros, pytest.mark.slow, pytest.mark.e2e]

REPO = Path(__file__).resolve().parents[1]
DURATION_S = 15
RATE_HZ = 20


def short_scenario(folder: Path, duration_s: int = DURATION_S) -> Path:
    """The default scenario cut to `duration_s` with a squeeze half-way, no link self-test."""
    text = (REPO / "scenarios" / "default.yaml").read_text()
    start = text.index("timeline:")
    end = text.index("workload:")
    text = (
        text[:start]
        + "timeline:\n"
        + "  - {at: 0s, shape: av1, uplink: 40mbit}\n"
        + f"  - {{at: {duration_s // 2}s, shape: av1, uplink: 8mbit}}\n\n"
        + text[end:]
    )
    text = text.replace("duration: 90s", f"duration: {duration_s}s")
    text = text.replace("name: default", "name: e2e-short")
    text = text.replace("link_test: true", "link_test: false")
    text = text.replace("images: false}", "images: false, pcap: [av1-gnb1]}")
    assert f"duration: {duration_s}s" in text and "link_test: false" in text
    assert "pcap: [av1-gnb1]" in text
    path = folder / "short.yaml"
    path.write_text(text)
    return path


def _ready_lines(log: Path) -> dict[str, Any]:
    import json

    for line in log.read_text().splitlines():
        if line.startswith("{") and '"event": "ready"' in line:
            return json.loads(line)
    raise AssertionError(f"no ready line in {log}")


def _temp_entries() -> set[str]:
    return set(os.listdir(tempfile.gettempdir()))


@pytest.mark.alone  # counts every message to the stop: a node beside another run lags
def test_run_starts_every_node_and_leaves_nothing(
    state_dir: Path, interfaces: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from netem.netns import list_netns
    from testbed import cgroups
    from testbed.run import run_scenario
    from testbed.scenario.loader import load

    # Files only under the run folder: the working directory stays empty, and what the run
    # keeps elsewhere while it lives (its state file, the relays' control sockets in a private
    # temp dir) is gone afterwards.
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    temp_before = _temp_entries()
    lines: list[str] = []
    t0 = time.monotonic()
    scenario = load(short_scenario(tmp_path))
    result = run_scenario(scenario, tmp_path / "runs", lines.append)
    wall = time.monotonic() - t0
    assert list(cwd.iterdir()) == []
    assert not [e for e in _temp_entries() - temp_before if e.startswith("netem-relay-")]
    assert not list(state_dir.glob(f"{result.run_id}*"))
    folder = result.folder
    assert result.ok, "\n".join(lines)
    procs = result.nodes["processes"]
    assert set(procs) == {"edge1.edge", "av1.fusion", "av1.inference", "av1.sensor",
                          "gnb1.link_events"}  # fmt: skip
    for name, p in procs.items():
        assert p["exit_code"] == 0, (name, (folder / p["log"]).read_text()[-2000:])
        assert p["stats"], f"{name} wrote no stats"

    # Each node ran in its own run namespace: the vehicle's three share one, the edge and the
    # gNB have others, and none is the host's.
    ready = {n: _ready_lines(folder / p["log"]) for n, p in procs.items()}
    netns = {n: line["netns"] for n, line in ready.items()}
    host = os.stat("/proc/self/ns/net").st_ino
    assert netns["av1.fusion"] == netns["av1.inference"] == netns["av1.sensor"]
    assert len({netns["av1.fusion"], netns["edge1.edge"], netns["gnb1.link_events"], host}) == 4
    # ... and one process, the vehicle's container, whose own log saw each role end on the stop;
    # the edge and the link events are processes of their own.
    vehicle = ("av1.fusion", "av1.inference", "av1.sensor")
    assert result.nodes["containers"] == {
        "av1.vehicle": {"host": "av1", "nodes": list(vehicle), "exit_code": 0,
                        "log": "logs/av1.vehicle.log"}
    }  # fmt: skip
    assert len({ready[n]["pid"] for n in vehicle}) == 1
    assert len({ready[n]["pid"] for n in ("av1.fusion", "edge1.edge", "gnb1.link_events")}) == 3
    ends = [json.loads(line) for line in (folder / "logs" / "av1.vehicle.log").read_text()
            .splitlines() if '"event": "role-exit"' in line]  # fmt: skip
    assert {e["role"]: e["stopped"] for e in ends} == dict.fromkeys(vehicle, True)
    for n in vehicle:  # each role its own MCAP part, merged into run.mcap
        assert procs[n]["stats"]["recorded"], (n, procs[n]["stats"])
    # The sensor read the frames rendered ahead, and the file went with the nodes.
    assert procs["av1.sensor"]["stats"]["prerendered_frames"] >= RATE_HZ * DURATION_S
    assert procs["av1.sensor"]["stats"]["rendered_here"] == 0
    assert not (folder / "nodes" / "frames.npy").exists()

    fusion = procs["av1.fusion"]["stats"]
    inference = procs["av1.inference"]["stats"]
    edge = procs["edge1.edge"]["stats"]
    # Fused poses at the frame rate for the whole timeline (every method, every frame).
    fused = fusion["published"]["edgeloc"]
    assert fused >= 0.8 * RATE_HZ * DURATION_S, fusion
    assert fusion["published"] == {m: fused for m in ("vo", "dnn", "kalman", "edgeloc")}
    # Inference requests went to the edge and came back; answers were fused.
    # (The head runs at 0.01 cores, so deep splits wait for their quota: a few requests per s.)
    assert inference["requests"] >= 2 * DURATION_S, inference
    assert inference["answers"] >= 0.9 * inference["requests"], inference
    assert edge["goals"] >= inference["answers"] and edge["ok"] == edge["goals"]
    assert edge["payload_bytes"] <= inference["payload_bytes"]
    # Every answer reached the fusion node (but the last, which may cross the stop signal).
    assert inference["answers"] - 2 <= fusion["answers"] <= inference["answers"]
    assert fusion["applied_edgeloc"] + fusion["gated"].get("edgeloc", 0) >= 0.9 * fusion["answers"]
    # The learner decided: every request was a play, and every split was explored (>= 2 each).
    plays = inference["split_plays"]
    assert sum(plays.values()) == inference["requests"]
    assert set(plays) == {"image", "conv3", "vehicle"} and min(plays.values()) >= 2, plays
    # The activations crossed the emulated air link: the relay carried at least the payload
    # bytes up, plus bounded DDS/action overhead per request (and discovery).
    air = result.link_counters["during_nodes"]["av1-gnb1"]
    total = result.link_counters["since_link_creation"]["av1-gnb1"]
    assert total["uplink"]["bytes_in"] >= air["uplink"]["bytes_in"]
    up, down = air["uplink"]["bytes_in"], air["downlink"]["bytes_in"]
    payload = inference["payload_bytes"]
    assert up >= payload, (up, payload)
    assert up <= payload + 6000 * inference["requests"] + 1_000_000, (up, payload)
    assert down <= 6000 * inference["requests"] + 1_000_000, (down, inference["requests"])
    # The drive started at the timeline's 0 s: frame 0 was published at that instant, so a
    # `set` at 2 s reaches the drive at its 2 s (`nodes.ros.start`).
    sensor = procs["av1.sensor"]["stats"]
    assert sensor["start_s"] == pytest.approx(result.timeline["started_epoch_s"], abs=0.002)
    # The timeline's events reached ROS as LinkEvent messages.
    assert procs["gnb1.link_events"]["stats"]["published"] == result.timeline["applied"] == 2
    # CPU budgets: the scenario's tiny budget for av1 is floored for real processes ...
    budgets = result.nodes["cpu_budgets"]
    cores = scenario.topology.vehicles[0].cpu
    assert cores is not None and cores < 0.05
    assert budgets["av1"]["requested_cores"] == cores
    assert budgets["av1"]["applied_cores"] >= 0.5
    # ... while the DNN head alone runs under exactly that budget: its thread joined the
    # vehicle's compute group (cores x period of quota, at least the kernel's 1 ms), which
    # the kernel then throttled, and its jobs were paced to that speed.
    assert budgets["av1"]["compute_cores"] == cores, budgets["av1"]
    assert budgets["av1"]["compute_period_us"] == cgroups.compute_period_for(cores)
    assert inference["compute_budget"]["joined"], inference["compute_budget"]
    period = cgroups.compute_period_for(cores)
    assert inference["compute_budget"]["cpu.cfs_quota_us"] == cgroups.quota_us(cores, period)
    assert inference["compute_budget"]["paced_cores"] == pytest.approx(cores, rel=0.01)
    assert budgets["av1"]["compute_cpu_stat"]["nr_periods"] > 0, budgets["av1"]
    assert set(inference["head_s"]) <= {"image", "conv3", "vehicle"}
    assert len(inference["decisions"]) == inference["requests"]
    # The core has no core_cpu: its tail thread runs unbudgeted, and says why.
    assert budgets["edge1"]["compute_cgroup"] is None and budgets["edge1"]["compute_reason"]
    assert not edge["compute_budget"]["joined"]

    # Teardown left nothing: no namespace, no node process, no cgroup of this run.
    assert not [n for n in list_netns() if n.startswith(f"el-{result.run_id}-")]
    assert processes_mentioning(str(folder)) == []
    assert cgroups.find_leftovers(result.run_id) == []
    assert (folder / "run.json").is_file() and (folder / "logs" / "av1.fusion.log").is_file()

    # record.pcap: the air link's packets as it delivered them, both directions; tshark reads
    # the file and finds the DDS (RTPS) traffic of the nodes in it.
    cap = result.captures["av1-gnb1"]
    pcap = folder / cap["path"]
    assert cap["path"] == "pcap/av1-gnb1.pcapng" and pcap.is_file(), cap
    assert min(cap["packets"].values()) > 100, cap
    assert any("capturing av1-gnb1" in line for line in lines), lines
    tshark = shutil.which("tshark")
    if tshark is not None:
        counts = subprocess.run(
            [tshark, "-r", str(pcap), "-T", "fields", "-e", "frame.interface_name"],
            capture_output=True, text=True, check=True, timeout=120,
        ).stdout.splitlines()  # fmt: skip
        assert counts.count("av1-gnb1 uplink") == cap["packets"]["uplink"]
        assert counts.count("av1-gnb1 downlink") == cap["packets"]["downlink"]
        rtps = subprocess.run(
            [tshark, "-r", str(pcap), "-Y", "rtps", "-T", "fields", "-e", "frame.number"],
            capture_output=True, text=True, check=True, timeout=120,
        ).stdout.splitlines()  # fmt: skip
        assert len(rtps) > 10, len(rtps)

    span = fusion["last_pose_s"] - fusion["first_pose_s"]
    req_span = inference["end_s"] - inference["start_s"]
    print(
        f"\nrun {result.run_id}: {wall:.1f} s wall; fused poses {fused} in {span:.1f} s "
        f"({fused / span:.1f} Hz); {inference['requests']} requests "
        f"({inference['requests'] / req_span:.1f}/s), {inference['answers']} answers, "
        f"splits {plays}, mean latency {inference['mean_latency_s']}; air uplink "
        f"{up / 1e6:.2f} MB for {payload / 1e6:.2f} MB of activations, downlink "
        f"{down / 1e6:.2f} MB; errors {fusion['errors']}; head time per split (s) "
        f"{inference['head_s']}; DNN-stage cgroup {budgets['av1']['compute_cpu_stat']}"
    )


def test_uplink_cut_moves_the_split_to_a_smaller_activation(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    """default.yaml's 40 -> 2 Mbit/s cut in a 36 s real run: the decisions recorded on the
    decision topic move from the raw frame to a split that sends fewer bytes. (At 2 Mbit/s a
    frame takes ~150 ms to send, conv3's activation ~11 ms for ~60 ms more head compute.)"""
    from collections import Counter

    from reports.mcapread import read_run
    from testbed.run import run_scenario
    from testbed.scenario.loader import load

    path = short_scenario(tmp_path, duration_s=36)
    path.write_text(path.read_text().replace("uplink: 8mbit}", "uplink: 2mbit}"))
    lines: list[str] = []
    result = run_scenario(load(path), tmp_path / "runs", lines.append)
    assert result.ok, "\n".join(lines[-30:])
    data = read_run(result.folder / "run.mcap")
    cut = [e.t for e in data.link_events if e.scheduled_s == 18]  # short_scenario: half-way
    assert len(cut) == 1, data.link_events
    decisions = data.vehicles["av1"].decisions
    assert decisions and {d.chosen for d in decisions} <= {"image", "conv3", "vehicle"}
    # the learner's settled choice in each phase: after 3 s (exploration, the window turning over)
    before = Counter(d.chosen for d in decisions if data.t0 + 3 <= d.t < cut[0])
    after = Counter(d.chosen for d in decisions if d.t >= cut[0] + 6)
    print(f"\nplays before the cut {dict(before)}, after {dict(after)}")
    top_before, n_before = before.most_common(1)[0]
    top_after, n_after = after.most_common(1)[0]
    assert top_before == "image" and n_before >= 0.6 * sum(before.values()), before
    assert top_after in ("conv3", "vehicle") and n_after >= 0.6 * sum(after.values()), after


def test_vehicle_keeps_publishing_fused_poses_when_the_edge_dies(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    from testbed.errors import TestbedError
    from testbed.scenario.loader import load
    from testbed.supervisor import Supervisor
    from testbed.topology import build

    # 20 s of frames: 8 s of answers before the kill (a budgeted head can stall for a quota
    # period, and under a loaded suite 4 s once gave a single request), 6 s after it.
    scenario = load(short_scenario(tmp_path, duration_s=20))
    with build(scenario, mode="run") as net:
        folder = tmp_path / "runs" / net.run_id
        nodes = Supervisor(net, folder, print)
        try:
            nodes.start()
            time.sleep(8.0)
            nodes.check()  # all alive, requests flowing
            edge = next(n for n in nodes.nodes if n.name == "edge1.edge")
            os.kill(edge.proc.pid, signal.SIGKILL)  # type: ignore[union-attr]
            killed_at = time.time()
            time.sleep(6.0)
            # In a run, the watcher would fail it now, quoting the dead node's log.
            with pytest.raises(TestbedError, match=r"node edge1\.edge exited with -9") as err:
                nodes.check()
            assert '"event": "ready"' in str(err.value)
        finally:
            summary = nodes.stop()
    procs = summary["processes"]
    fusion = procs["av1.fusion"]["stats"]
    inference = procs["av1.inference"]["stats"]
    for name in ("av1.fusion", "av1.inference", "av1.sensor"):
        assert procs[name]["exit_code"] == 0, (name, (folder / procs[name]["log"]).read_text())
    assert procs["edge1.edge"]["exit_code"] == -signal.SIGKILL
    # Before the kill the edge answered; after it, requests timed out and were charged.
    # (A 2-vCPU VM answers about one request a second here: 7-11 before the kill.)
    assert inference["answers"] >= 4, inference
    assert inference["lost"] >= 1, inference
    # The real-time thread never waited on the network: after the kill (from the next whole
    # second on) the fused pose kept its frame rate, second by second.
    per_second = fusion["frames_per_second"]
    kill_second = int(killed_at - fusion["first_pose_s"])
    after = per_second[kill_second + 1 : -1]
    assert len(after) >= 4, per_second
    assert min(after) >= 0.8 * RATE_HZ, per_second
    print(
        f"\nedge killed at second {kill_second}; fused poses per second {per_second}; "
        f"requests {inference['requests']}, answers {inference['answers']}, "
        f"lost {inference['lost']}"
    )


def test_a_killed_vehicle_process_fails_the_run_naming_the_vehicle_and_its_nodes(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    """The vehicle's three nodes share one process: killed from outside, the watcher names that
    process, its vehicle and the nodes it held; the edge, a process of its own, stops cleanly."""
    from testbed.errors import TestbedError
    from testbed.scenario.loader import load
    from testbed.supervisor import Supervisor
    from testbed.topology import build

    scenario = load(short_scenario(tmp_path, duration_s=10))
    with build(scenario, mode="run") as net:
        folder = tmp_path / "runs" / net.run_id
        nodes = Supervisor(net, folder, print)
        try:
            nodes.start()
            vehicle = [n for n in nodes.nodes if n.host == "av1"]
            assert len(vehicle) == 3 and len({n.proc.pid for n in vehicle}) == 1  # type: ignore[union-attr]
            nodes.check()
            os.kill(vehicle[0].proc.pid, signal.SIGKILL)  # type: ignore[union-attr]
            deadline = time.monotonic() + 10
            with pytest.raises(TestbedError) as err:
                while time.monotonic() < deadline:
                    nodes.check()
                    time.sleep(0.1)
            text = str(err.value)
            assert "process av1.vehicle of av1" in text and "exited with -9" in text, text
            assert all(n in text for n in ("av1.fusion", "av1.inference", "av1.sensor")), text
        finally:
            summary = nodes.stop()
    procs = summary["processes"]
    assert procs["edge1.edge"]["exit_code"] == 0
    assert {procs[n]["exit_code"] for n in ("av1.fusion", "av1.inference", "av1.sensor")} == {-9}
    assert summary["containers"]["av1.vehicle"]["exit_code"] == -signal.SIGKILL


def test_ctrl_c_mid_run_tears_everything_down(
    interfaces: None, state_dir: Path, tmp_path: Path
) -> None:
    """SIGINT to `testbed run` while the nodes run: exit 130, teardown in a few seconds, and
    no namespace, relay, node process or state file left behind."""
    import json

    from netem.netns import list_netns
    from testbed import state as st

    scenario = short_scenario(tmp_path, duration_s=60)
    runs = tmp_path / "runs"
    proc = testbed_popen("run", str(scenario), "--runs-dir", str(runs))
    try:
        lines = lines_until_the_timeline(proc)
        (run_id,) = [r.run_id for r in st.list_runs()]
        time.sleep(2)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGINT)
        # Teardown is over when the run's state file is gone (it goes last); the partial
        # report is built after that, so the exit comes later.
        while st.list_runs() and time.monotonic() - t0 < 30:
            time.sleep(0.05)
        teardown = time.monotonic() - t0
        rest, _ = proc.communicate(timeout=60)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    print(f"\nCtrl-C: teardown {teardown:.2f} s, exit (partial report built) {took:.2f} s")
    assert proc.returncode == 130, "".join(lines) + rest
    assert teardown < 5, f"teardown took {teardown:.1f} s"
    summary = json.loads((runs / run_id / "summary.json").read_text())
    assert summary["status"].startswith("interrupted"), summary["status"]
    assert (runs / run_id / "report.html").is_file() and "report:" in rest
    assert [n for n in list_netns() if n.startswith(f"el-{run_id}-")] == []
    assert st.list_runs() == []
    assert processes_mentioning(f"el-{run_id}-") == []
    assert processes_mentioning(str(runs)) == []
