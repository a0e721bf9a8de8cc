"""The channel's radio changes reach a real relay: with a recorded radio trace on the air link
(MCS 27, then MCS 0 at the cell edge, then MCS 27 again), a burst of real datagrams from the
vehicle takes as long as each MCS's uplink rate says, while the timeline plays."""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import pytest

from netem.nr.radio import RADIO_PROFILES
from testbed.scenario import load
from testbed.scenario.model import HandoverEvent, SetEvent
from testbed.timeline import TimelinePlayer
from testbed.topology import Net, build

pytestmark = pytest.mark.root

BURST = 40  # datagrams
SIZE = 1200  # bytes each


def _burst_s(net: Net) -> float:
    """Seconds from sending `BURST` datagrams av1 -> gnb1 (over the air link's uplink) at once
    to the last one's arrival."""
    addr = str(net["gnb1"].address_towards("av1"))
    server, client = net["gnb1"].socket(), net["av1"].socket()
    try:
        server.bind((addr, 0))
        server.settimeout(3.0)
        got: list[float] = []

        def receive() -> None:
            while len(got) < BURST:
                try:
                    server.recv(2048)
                except TimeoutError:
                    return
                got.append(time.perf_counter())

        rx = threading.Thread(target=receive)
        rx.start()
        t0 = time.perf_counter()
        for _ in range(BURST):
            client.sendto(b"x" * SIZE, (addr, server.getsockname()[1]))
        rx.join()
    finally:
        server.close()
        client.close()
    assert len(got) == BURST, f"{len(got)} of {BURST} datagrams arrived"
    return got[-1] - t0


def test_the_relay_runs_at_the_mcs_the_trace_gives_at_each_time(
    state_dir: Path, tmp_path: Path
) -> None:
    (tmp_path / "radio.csv").write_text(
        "time_s,ue,rsrp_dbm,sinr_db,mcs\n"
        "0.0,av1,-70,30.0,27\n"
        "1.5,av1,-112,2.0,0\n"  # the cell edge: MCS 0, whose BLER at 2 dB is ~0
        "3.5,av1,-70,30.0,27\n"
    )
    (tmp_path / "s.yaml").write_text(
        "name: t\nseed: 3\nduration: 5s\n"
        "topology:\n  cells:\n    - {gnb: gnb1, core: core1, site: {x: 0, y: 0}}\n"
        "  vehicles:\n    - {name: av1, gnb: gnb1}\n"
        "links:\n  backend: userspace\n  air: {radio: oai-tdd-30k}\n"
        "channel: {trace: radio.csv}\n"
    )
    scenario = load(tmp_path / "s.yaml")
    events = [(e.at_s, e.direction) for e in scenario.timeline]
    assert events == [(1.5, "uplink"), (1.5, "downlink"), (3.5, "uplink"), (3.5, "downlink")]
    fast = dataclasses.replace(RADIO_PROFILES["oai-tdd-30k"], mcs=27, bler=0.0)
    slow_bps = scenario.timeline[0].changes["radio"].goodput_bps("uplink")  # type: ignore[union-attr]
    fast_bps = fast.goodput_bps("uplink")
    with build(scenario, mode="run") as net:
        assert net.control is not None
        player = TimelinePlayer(scenario.timeline, net.control)
        player.start()
        try:
            time.sleep(0.3)
            before = _burst_s(net)
            time.sleep(max(0.0, 1.7 - player.elapsed()))
            edge = _burst_s(net)
            time.sleep(max(0.0, 3.7 - player.elapsed()))
            after = _burst_s(net)
            assert player.wait(3) and player.failure is None
        finally:
            player.stop()
    assert [a.kind for a in player.applied] == ["channel"] * 4
    # At MCS 0 the burst takes what its uplink rate says (SR and first grant aside, which
    # cost a few ms); at MCS 27 many times less, before and after.
    expected_edge = BURST * SIZE * 8 / slow_bps
    assert 0.8 * expected_edge < edge < 1.3 * expected_edge + 0.02, (edge, expected_edge)
    assert before < edge / 5 and after < edge / 5, (before, edge, after, fast_bps)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.e2e
def test_a_run_with_a_channel_records_the_radio_and_the_handover_and_reports_them(
    state_dir: Path, tmp_path: Path
) -> None:
    """`testbed run` of a short drive past two auto-placed cells (scenarios/drive_two_cells
    cut to 12 s: one handover, at ~10 s): every radio change and the handover are applied
    (/links/events, events.jsonl), /radio/av1 holds one RadioState per step and /handover
    the handover, both decoded by rosbags and mcap_ros2; EdgeLoc's requests are answered
    through the target cell after it, by the target's edge server (`edge: follow`); the
    report draws it."""
    import json

    from tests.realrun import REPO, testbed_cli
    from tests.test_recording_root import read_both

    text = (REPO / "scenarios" / "drive_two_cells.yaml").read_text()
    short = tmp_path / "drive.yaml"
    # Without the link self-test (~70 s of the radio links' measurements here), which
    # tests/test_linktest_radio.py and test_linktest_root.py cover against the oracle.
    assert "\nreport:" not in text
    short.write_text(
        text.replace("duration: 90s", "duration: 12s")
        + "\nreport: {link_test: false, compare: false}\n"
    )
    scenario = load(short)
    by_channel = [e for e in scenario.timeline if isinstance(e, SetEvent)]
    [handover] = [e for e in scenario.timeline if isinstance(e, HandoverEvent)]
    assert by_channel and (handover.source, handover.target) == ("gnb1", "gnb2")
    runs = tmp_path / "runs"
    result = testbed_cli("run", str(short), "--runs-dir", str(runs), timeout=400)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert (
        f"0 event(s), {len(by_channel)} radio change(s) from the channel, 1 handover(s)"
        in result.stdout
    )
    assert "handover av1 gnb1 -> gnb2 (40 ms lossless)" in result.stdout
    folder = next(runs.iterdir())
    applied = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
    assert sorted(a["kind"] for a in applied) == ["channel"] * len(by_channel) + ["handover"]
    assert not any(a["error"] for a in applied)
    decoded, _, _ = read_both(folder / "run.mcap")
    radio = decoded["/radio/av1"]
    steps = round(scenario.duration_s / scenario.channel.step_s)  # type: ignore[union-attr]
    assert steps - 2 <= len(radio) <= steps
    from testbed.mobility import plans

    plan = plans(scenario)["av1"]
    for msg, step in zip(radio[::250], plan.steps[::250], strict=False):
        assert (msg.cell, msg.mcs, msg.ul_mcs) == (step.serving, step.mcs, step.ul_mcs)
        assert msg.sinr_db == pytest.approx(step.sinr_db)
    [recorded] = decoded["/handover"]
    assert (recorded.vehicle, recorded.source, recorded.target) == ("av1", "gnb1", "gnb2")
    assert recorded.scheduled_s == pytest.approx(handover.at_s)
    assert recorded.interruption_s == pytest.approx(0.04) and recorded.lossless
    assert 0 <= recorded.lateness_s < 0.05 and recorded.error == ""
    actions = [m.action for m in decoded["/links/events"]]
    assert actions.count("channel") == len(by_channel) and actions.count("handover") == 1

    # Answers kept coming through the target cell after the handover.
    def seconds(stamp: object) -> float:
        return stamp.sec + stamp.nanosec * 1e-9  # type: ignore[attr-defined]

    after = [m for m in decoded["/av1/dnn_answer"] if seconds(m.stamp) > seconds(recorded.stamp)]
    assert len(after) >= 5, len(after)  # frames captured after it, answered
    # `edge: follow`: edge1 answered before the handover, edge2 (the target cell's) after.
    asked = [(seconds(m.stamp) > seconds(recorded.stamp) + 1.0, m.edge)
             for m in decoded["/av1/inference"] if m.ok]  # fmt: skip
    assert {e for late, e in asked if not late} >= {"edge1"}
    assert {e for late, e in asked if late} == {"edge2"}, asked
    summary = json.loads((folder / "summary.json").read_text())
    av1 = summary["radio"]["vehicles"]["av1"]
    assert av1["steps"] == len(radio) and set(av1["cells"]) == {"gnb1", "gnb2"}
    assert len(av1["handovers"]) == 1
    assert [s["name"] for s in summary["radio"]["channel"]["sites"]] == ["gnb1", "gnb2"]
    decisions = summary["learner"]["decisions"]
    assert sum(r["plays"] for r in av1["by_uplink_mcs"]) == decisions > 50
    html = (folder / "report.html").read_text()
    assert "Radio along the route" in html and (folder / "plots" / "radio_av1.png").is_file()
