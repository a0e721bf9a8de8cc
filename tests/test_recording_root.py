"""run.mcap of real runs: the nodes record what they publish, the orchestrator the link
counters, and the merge leaves one MCAP that rosbags (AnyReader) and mcap_ros2 decode in full,
with per-topic counts equal to what the nodes say they published. Also when the run is stopped
with Ctrl-C, and when the orchestrator is SIGKILLed and `testbed clean` finalises the file.

Each test runs the smoke scenario cut to a few seconds (no link self-test).
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from tests.realrun import processes_mentioning, short_smoke, testbed_popen

pytestmark = [pytest.mark.root, pytest.mark.ros, pytest.mark.slow, pytest.mark.e2e]

REPO = Path(__file__).resolve().parents[1]


def read_both(path: Path) -> tuple[dict[str, list[Any]], dict[str, int], Any]:
    """Every message decoded by mcap_ros2 (per topic) and counted by rosbags' AnyReader after
    deserialising each; plus the mcap summary. Both must see the same topics and counts."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    decoded: dict[str, list[Any]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        for _, channel, _, msg in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(msg)
    counted: dict[str, int] = {}
    with AnyReader([path]) as bag:
        for conn, _, raw in bag.messages():
            bag.deserialize(raw, conn.msgtype)
            counted[conn.topic] = counted.get(conn.topic, 0) + 1
    assert {t: len(v) for t, v in decoded.items()} == counted
    assert summary is not None and summary.statistics is not None
    by_channel = summary.statistics.channel_message_counts
    assert {summary.channels[c].topic: n for c, n in by_channel.items()} == counted
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
    return decoded, counted, summary


def mcap_extras(path: Path) -> tuple[dict[str, dict[str, str]], set[str]]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        names = {a.name for a in reader.iter_attachments()}
    return meta, names


@pytest.mark.alone  # counts every message to the stop: a node beside another run lags
def test_run_mcap_decodes_fully_and_counts_match_the_nodes(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    from testbed.run import run_scenario
    from testbed.scenario.loader import load

    lines: list[str] = []
    scenario = load(short_smoke(tmp_path, 8, images=True))
    result = run_scenario(scenario, tmp_path, lines.append)
    assert result.ok, "\n".join(lines)
    folder = result.folder
    path = folder / "run.mcap"
    assert path.is_file() and not (folder / "parts").exists(), "\n".join(lines)
    decoded, counts, summary = read_both(path)
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}

    procs = {n: p["stats"] for n, p in result.nodes["processes"].items()}
    sensor, fusion, inference = procs["av1.sensor"], procs["av1.fusion"], procs["av1.inference"]
    frames = sensor["frames"]
    assert frames > 0, sensor
    # Per topic, the recording holds exactly what each node counted as published.
    assert counts["/av1/vo"] == counts["/av1/gt"] == counts["/av1/camera"] == frames
    assert counts["/av1/pose"] == sum(fusion["published"].values())
    assert counts["/av1/split_decision"] == counts["/av1/inference"] == inference["requests"]
    assert counts["/av1/dnn_answer"] == inference["answers"]
    assert counts.get("/av1/detector", 0) == inference["detector_updates"]
    assert counts["/links/events"] == procs["gnb1.link_events"]["published"] == 2
    for name in ("av1.sensor", "av1.fusion", "av1.inference", "gnb1.link_events"):
        for topic, n in procs[name]["recorded"].items():
            assert counts[topic] == n, (name, topic)
    # One sample per direction of each link every 0.5 s (smoke's air, N3 and N6 links: 6; it
    # said 4 and passed only when the run took an even number of samples).
    per_sample = 2 * len(scenario.links.links)
    assert per_sample == 6
    assert counts["/links/counters"] % per_sample == 0, counts["/links/counters"]
    assert counts["/links/counters"] >= per_sample * 8
    last_up = [
        m for m in decoded["/links/counters"] if m.link == "av1-gnb1" and m.direction == "up"
    ]
    assert last_up[-1].bytes_in >= inference["payload_bytes"]
    # Message contents survive the round trip.
    methods = {m.method for m in decoded["/av1/pose"]}
    assert methods == {"vo", "dnn", "kalman", "edgeloc"}
    outcomes = decoded["/av1/inference"]
    assert sum(m.ok for m in outcomes) == inference["answers"]
    assert all(m.latency_s > 0 for m in outcomes if m.ok)
    assert all(math.isnan(m.latency_s) for m in outcomes if not m.ok)
    image = decoded["/av1/camera"][0]
    assert image.encoding == "rgb8" and len(image.data) == image.height * image.step

    meta, attachments = mcap_extras(path)
    run = meta["edgeloc.run"]
    assert run["status"] == "ok" and run["run_id"] == result.run_id and run["seed"] == "7"
    assert run["link_backend"] == result.link_backend
    assert run["ros_distro"] == "jazzy" and run["python"] and run["torch_version"]
    host = json.loads(run["host"])
    assert isinstance(host["sch_netem"], bool) and host["cpus"] >= 1
    nodes = {n: json.loads(v) for n, v in meta["edgeloc.nodes"].items()}
    assert set(nodes) == set(procs)
    assert {n: v.get("process") for n, v in nodes.items() if n.startswith("av1.")} == dict.fromkeys(
        ("av1.fusion", "av1.inference", "av1.sensor"), "av1.vehicle"
    )
    assert all(v["namespace"].startswith(f"el-{result.run_id}-") for v in nodes.values())
    assert nodes["av1.fusion"]["stats"]["published"] == fusion["published"]
    assert meta["edgeloc.timeline"]["applied"] == "2"
    assert meta["edgeloc.linktest"] == {"ran": "false"}
    assert attachments == {
        "scenario.yaml", "links.json", "events.jsonl", "nodes/config.json", "run.json"
    }  # fmt: skip
    links = json.loads((folder / "links.json").read_text())
    assert (
        set(links["links"])
        == set(links["final_profiles"])
        == {"av1-gnb1", "gnb1-upf1", "upf1-edge1"}
    )
    # smoke.yaml's air link is the NR cell: its radio, whole, in both directions
    air = links["links"]["av1-gnb1"]["profiles"]
    assert air["uplink"]["radio"]["slots"] == air["downlink"]["radio"]["slots"] == "DDDSUDDSUU"
    print(f"\nrun {result.run_id}: {path.stat().st_size / 1e6:.2f} MB, topics {counts}")


def _start_run(tmp_path: Path, duration_s: int) -> tuple[subprocess.Popen[str], list[str]]:
    scenario = short_smoke(tmp_path, duration_s)
    proc = testbed_popen("run", str(scenario), "--runs-dir", str(tmp_path))
    lines: list[str] = []
    assert proc.stdout is not None
    for line in proc.stdout:  # until the nodes run and the timeline plays
        lines.append(line)
        if "playing the timeline" in line:
            return proc, lines
    proc.wait()
    pytest.fail("testbed run ended before its timeline started:\n" + "".join(lines))


def test_ctrl_c_mid_run_still_writes_a_valid_run_mcap(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    from testbed import state as st

    proc, lines = _start_run(tmp_path, duration_s=60)
    try:
        (run_id,) = [r.run_id for r in st.list_runs()]
        time.sleep(3)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=40)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    output = "".join(lines) + rest
    assert proc.returncode == 130, output
    folder = tmp_path / run_id
    assert (folder / "run.mcap").is_file() and not (folder / "parts").exists(), output
    _, counts, _ = read_both(folder / "run.mcap")
    assert counts["/av1/pose"] >= 4 and counts["/av1/vo"] >= 1, counts
    assert counts["/links/counters"] >= 4, counts
    meta, attachments = mcap_extras(folder / "run.mcap")
    assert meta["edgeloc.run"]["status"] == "interrupted"
    assert {"scenario.yaml", "links.json", "events.jsonl"} <= attachments
    # the report after Ctrl-C leaves out the split replays, and says how to get them
    skipped = json.loads((folder / "summary.json").read_text())["splits"]["skipped"]
    assert "interrupted" in skipped and "testbed report" in skipped, skipped
    assert st.list_runs() == [] and processes_mentioning(str(folder)) == []


def test_sigkill_of_the_orchestrator_then_clean_finalises_run_mcap(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    from netem.netns import list_netns
    from testbed import recording
    from testbed import state as st

    proc, _ = _start_run(tmp_path, duration_s=60)
    try:
        (run_id,) = [r.run_id for r in st.list_runs()]
        time.sleep(4)  # a few chunks of every part on disk
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    folder = tmp_path / run_id
    assert (folder / "parts").is_dir() and not (folder / "run.mcap").exists()
    clean = subprocess.run(
        [sys.executable, "-m", "testbed.cli", "clean"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    out = clean.stdout + clean.stderr
    assert clean.returncode == 0, out
    assert f"recording of {run_id} finalised" in out, out
    assert not (folder / "parts").exists()
    _, counts, _ = read_both(folder / "run.mcap")
    # The orchestrator's part was cut by the kill: read up to its last chunk.
    assert counts["/links/counters"] >= 4 and counts["/av1/pose"] >= 4, counts
    meta, attachments = mcap_extras(folder / "run.mcap")
    assert meta["edgeloc.run"]["status"] == recording.ORPHANED
    assert meta["edgeloc.run"]["run_id"] == run_id
    assert "scenario.yaml" in attachments and "links.json" in attachments
    # Nothing of the run is left.
    assert [n for n in list_netns() if n.startswith(f"el-{run_id}-")] == []
    assert st.list_runs() == [], out  # clean keeps the state file when something stayed
    assert processes_mentioning(str(folder)) == []
    assert processes_mentioning(f"el-{run_id}-") == []


def test_a_node_that_crashes_fails_the_run_and_run_mcap_names_it(
    state_dir: Path, interfaces: None, tmp_path: Path
) -> None:
    import threading

    from testbed import state as st
    from testbed.errors import TestbedError
    from testbed.run import run_scenario
    from testbed.scenario.loader import load

    killed: list[int] = []

    def kill_fusion(folder: Path) -> None:
        time.sleep(2)
        for line in (folder / "logs" / "av1.fusion.log").read_text().splitlines():
            if '"event": "ready"' in line:
                pid = json.loads(line)["pid"]
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)

    def progress(line: str) -> None:
        if line.startswith("playing the timeline"):
            (run,) = st.list_runs()  # the state file names the run folder
            assert run.folder is not None
            threading.Thread(target=kill_fusion, args=(Path(run.folder),), daemon=True).start()

    # The fusion node's pid is its vehicle's process (`nodes.ros.container`): killed, the run
    # fails naming that process, its vehicle and the nodes it held.
    with pytest.raises(
        TestbedError,
        match=r"process av1\.vehicle of av1 \(nodes av1\.fusion, av1\.inference, "
        r"av1\.sensor\) exited with -9",
    ) as err:
        run_scenario(load(short_smoke(tmp_path, 30)), tmp_path, progress)
    assert killed
    folder = err.value.run_folder  # type: ignore[attr-defined]
    assert (folder / "run.mcap").is_file() and not (folder / "parts").exists()
    _, counts, _ = read_both(folder / "run.mcap")
    assert counts["/av1/pose"] >= 4 and counts["/av1/vo"] >= counts["/av1/pose"] // 4
    meta, _ = mcap_extras(folder / "run.mcap")
    assert meta["edgeloc.run"]["status"].startswith("failed: ")
    assert "process av1.vehicle of av1" in meta["edgeloc.run"]["status"]
    fusion = json.loads(meta["edgeloc.nodes"]["av1.fusion"])
    assert fusion["exit_code"] == -signal.SIGKILL
    assert any('"event": "ready"' in line for line in fusion["log_tail"])
    assert json.loads(meta["edgeloc.nodes"]["av1.sensor"])["exit_code"] is not None
