"""The report around handovers (`channel.handover`), from synthetic run.mcap files written like
the recorder's: /handover read beside /radio/<vehicle>; what EdgeLoc and its learner did in
the window before and after a handover, worked out by hand; the table, the sentence on the
learner's split and the radio figure; the fallback to /radio's cell changes (and its "not
recorded" note) when /handover is missing; the recorder's own /handover bytes (rclpy,
PartWriter) read by the report and by rosbags, an independent reader."""

from __future__ import annotations

import json
import math
from dataclasses import astuple, fields
from pathlib import Path
from typing import Any

import pytest
from report_synth import SynthRun

from nodes.recording.layout import HANDOVER_TOPIC
from reports.build import build_report, summarize
from reports.mcapread import HandoverRec, read_run
from reports.sections.radio import HANDOVER_WINDOW_S

T0 = 1_700_000_000.0
H = T0 + 6.0  # the handover takes effect here, in the middle of a 12 s drive
ARMS = ["image", "conv1", "conv2", "conv3", "conv4", "fc", "vehicle"]
PAYLOAD = {"image": 36864, "conv3": 2304, "conv4": 768}
SETTINGS = {
    "offset_db": 3.0,
    "hysteresis_db": 1.0,
    "ttt_s": 0.32,
    "filter_k": 4,
    "interruption_s": 0.05,
    "lossless": True,
    "edge": "stay",
}


def ul_mcs_of(k: int) -> int:
    """Uplink MCS of radio step k (t = k / 10 s): falls towards the cell edge, recovers after."""
    return 16 if k < 45 else 4 if k < 60 else 8 if k < 75 else 20


def error_of(f: int) -> float:
    """EdgeLoc's position error of frame f (captured at 0.05 + f / 10 s): 0.4/0.6 (mean 0.5) in
    the 3 s before the handover, 1.9/2.1 (mean 2.0) in the 3 s after, other values outside."""
    wobble = 0.1 if f % 2 else -0.1
    if f < 30:
        return 0.1
    if f < 60:
        return 0.5 + wobble
    if f < 90:
        return 2.0 + wobble
    return 0.2


def split_of(j: int, moves: bool) -> str:
    """The split of play j (decided at 0.1 + 0.2 j s). Away from the handover: image. Before it
    (j 15-29): conv3 12 times, image 3; after it (j 30-44): conv4 9 times, conv3 6."""
    if not moves or j < 15 or j >= 45:
        return "image"
    if j < 30:
        return "image" if j % 5 == 0 else "conv3"
    return "conv3" if j % 5 in (0, 1) else "conv4"


def handover_run(with_topic: bool = True, moves: bool = True) -> SynthRun:
    """One vehicle's 12 s drive from gnb1's cell into gnb2's at 6 s (module doc)."""
    s = SynthRun()
    for f in range(120):
        t = T0 + 0.05 + 0.1 * f
        s.pose("/av1/gt", t, f, "gt", f, 0.0)
        s.pose("/av1/pose", t, f, "edgeloc", f, error_of(f), latency=0.05)
    for k in range(120):
        t = T0 + 0.1 * k
        s.radio(
            t, "gnb1" if k < 60 else "gnb2", ul_mcs_of(k), x=float(k), sinr_db=20 - abs(k - 60) / 5
        )
    for j in range(60):
        t = T0 + 0.1 + 0.2 * j
        split = split_of(j, moves)
        s.decision(t, j, split, ARMS, j)
        after = 30 <= j < 45
        lost = j == 30  # the first request after the handover times out
        latency = 0.25 if after else 0.05 if j >= 15 else 0.04
        if j == 29:  # sent at 5.9 s, in flight through the interruption: answered at 6.2 s
            latency = 0.3
        s.inference(
            t + (0.5 if lost else latency),
            j,
            split,
            ARMS,
            math.nan if lost else latency,
            ok=not lost,
            timed_out=lost,
            payload=PAYLOAD[split],
        )
    if with_topic:
        s.handover(H, "gnb1", "gnb2", scheduled_s=5.98, interruption_s=0.05, lossless=True)
        # another vehicle's handover (it has no radio here): not av1's
        s.handover(T0 + 2.0, "gnb2", "gnb1", 1.9, 0.05, False, vehicle="av2")
    s.channel_run("ho1", {"gnb1": (0.0, 50.0), "gnb2": (120.0, 50.0)}, handover=SETTINGS)
    return s


def write(tmp_path: Path, synth: SynthRun, name: str = "run") -> Path:
    folder = tmp_path / name
    folder.mkdir()
    synth.write(folder / "run.mcap")
    return folder


# The summary's windows before and after the handover (`nodes.edgeloc.bands.around`'s keys
# and the report's own): plays count at their decision and carry their request's latency.
BEFORE = {
    "plays": 15,  # decided at 3.1 ... 5.9 s
    "top_split": "conv3",
    "top_share": 0.8,
    "mean_payload_bytes": (12 * 2304 + 3 * 36864) / 15,
    "mean_latency_s": (14 * 0.05 + 0.3) / 15,  # the last one through the interruption
    "mean_error_m": 0.5,  # frames at 3.05 ... 5.95 s
    "mean_ul_mcs": (15 * 16 + 15 * 4) / 30,  # steps 30-59: 3.0 s up to the handover
    "timed_out": 0,
    "top_split_vs_away": "smaller",
}
AFTER = {
    "plays": 15,  # decided at 6.1 ... 8.9 s
    "top_split": "conv4",
    "top_share": 0.6,
    "mean_payload_bytes": (9 * 768 + 6 * 2304) / 15,
    "mean_latency_s": 0.25,  # the 14 answered ones; the first timed out
    "mean_error_m": 2.0,
    "mean_ul_mcs": (15 * 8 + 15 * 20) / 30,  # steps 60-89
    "timed_out": 1,
    "top_split_vs_away": "smaller",
}


def test_the_recorded_handover_is_read_and_summarised_with_edgeloc_around_it(
    tmp_path: Path,
) -> None:
    data = read_run(write(tmp_path, handover_run()))
    assert data.handovers == [
        HandoverRec(T0 + 2.0, "av2", "gnb2", "gnb1", 1.9, 0.02, 0.05, False, ""),
        HandoverRec(H, "av1", "gnb1", "gnb2", 5.98, 0.02, 0.05, True, ""),
    ]
    av1 = summarize(data, splits=False)["radio"]["vehicles"]["av1"]
    assert HANDOVER_WINDOW_S == 3.0 and av1["handover_window_s"] == 3.0
    assert av1["handovers_source"] == HANDOVER_TOPIC
    t_s = 6.0 - 0.05  # run time counts from the first ground-truth frame
    (ho,) = av1["handovers"]
    assert ho == pytest.approx(
        {
            "t_s": t_s,
            "from": "gnb1",
            "to": "gnb2",
            "interruption_ms": 50.0,
            "lossless": True,
            "lateness_ms": 20.0,
            "error": None,
        }
    )
    assert av1["away_from_handovers"] == pytest.approx(
        {"plays": 30, "top_split": "image", "top_share": 1.0, "mean_payload_bytes": 36864.0}
    )
    (around,) = av1["around_handovers"]
    assert {k: around[k] for k in ho} == ho
    assert around["before"] == pytest.approx(BEFORE, abs=1e-6)
    assert around["after"] == pytest.approx(AFTER, abs=1e-6)
    assert around["smaller_split_near"] is True
    assert av1["cells"] == {"gnb1": 0.5, "gnb2": 0.5}


def test_the_report_shows_the_table_the_sentence_and_the_figure(tmp_path: Path) -> None:
    folder = write(tmp_path, handover_run())
    rep = build_report(folder, splits=False)
    md = (folder / "report.md").read_text()
    section = md.split("## Radio along the route")[1].split("\n## ")[0]
    assert (
        "| time s | from → to | interruption ms | lateness ms | UL MCS before / after | "
        "EdgeLoc error m before / after | top split before / after | "
        "mean latency ms before / after |"
    ) in section
    assert (
        "| 5.95 | gnb1 → gnb2 | 50.0 lossless | 20.0 | 10.0 / 14.0 | 0.50 / 2.00 | "
        "conv3 80% / conv4 60% | 66.7 / 250.0 |"
    ) in section
    assert "Around each handover of av1 (from /handover), the 3 s before it" in section
    assert (
        "The learner moved to a smaller split near most handovers: near 1 of 1 handovers its "
        "most-played split in the 3 s before or after sent less uplink payload per request "
        "than image, its most-played split away from handovers (1 in the window before, 1 in "
        "the window after)."
    ) in section
    assert "Not recorded" not in section
    html = (folder / "report.html").read_text()
    assert "<caption>Around each handover of av1 (from /handover)" in html
    assert "<td>conv3 80% / conv4 60%</td>" in html
    assert "The learner moved to a smaller split near most handovers" in html
    png = (folder / "plots" / "radio_av1.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # 12 x 6.5 in at 100 dpi: the third time panel, EdgeLoc's error, is there (5 in without)
    size = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert size == (1200, 650)
    assert "![Radio of av1 along its route](plots/radio_av1.png)" in section
    assert HANDOVER_TOPIC not in rep.summary["not_recorded"]
    written = json.loads((folder / "summary.json").read_text())["radio"]["vehicles"]["av1"]
    assert (
        written["around_handovers"] == rep.summary["radio"]["vehicles"]["av1"]["around_handovers"]
    )


def test_without_handover_the_cell_changes_stand_in_and_the_report_says_so(
    tmp_path: Path,
) -> None:
    """/handover missing, though the scenario sets channel.handover: the handover is the
    serving cell's change on /radio/av1 (at the same step here, so the same windows), its
    interruption unknown; the report names what was not recorded. A learner that kept its
    split is said not to have moved."""
    folder = write(tmp_path, handover_run(with_topic=False, moves=False))
    rep = build_report(folder, splits=False)
    s = rep.summary
    assert HANDOVER_TOPIC in s["not_recorded"]
    av1 = s["radio"]["vehicles"]["av1"]
    assert av1["handovers_source"] == "/radio/av1"
    unknown = {"interruption_ms": None, "lossless": None, "lateness_ms": None, "error": None}
    (ho,) = av1["handovers"]
    assert ho == pytest.approx({"t_s": 5.95, "from": "gnb1", "to": "gnb2", **unknown})
    (around,) = av1["around_handovers"]
    same = {"top_split": "image", "top_share": 1.0, "top_split_vs_away": "same"}
    assert around["before"] == pytest.approx(
        {**BEFORE, **same, "mean_payload_bytes": 36864.0}, abs=1e-6
    )
    assert around["after"] == pytest.approx(
        {**AFTER, **same, "mean_payload_bytes": 36864.0}, abs=1e-6
    )
    assert around["smaller_split_near"] is False
    md = (folder / "report.md").read_text()
    section = md.split("## Radio along the route")[1].split("\n## ")[0]
    assert (
        "Not recorded: the handovers as applied (/handover, though the scenario sets "
        "channel.handover: the handovers below are the serving cell's changes on "
        "/radio/<vehicle>, without their interruption or lateness)."
    ) in section
    assert (
        "| 5.95 | gnb1 → gnb2 | - | - | 10.0 / 14.0 | 0.50 / 2.00 | image 100% / image 100% |"
        in section
    )
    assert (
        "The learner did not move to a smaller split near most handovers: near 0 of 1 handovers"
    ) in section
    assert (folder / "plots" / "radio_av1.png").is_file()


def test_cell_changes_without_handover_settings_are_not_called_missing(tmp_path: Path) -> None:
    """A channel without `handover` (cells by strongest site): no /handover is expected."""
    synth = handover_run(with_topic=False)
    synth.metadata["edgeloc.run"]["channel"]["handover"] = None
    s = summarize(read_run(write(tmp_path, synth)), splits=False)
    assert HANDOVER_TOPIC not in s["not_recorded"]
    assert s["radio"]["vehicles"]["av1"]["handovers_source"] == "/radio/av1"


@pytest.mark.ros
def test_the_recorders_handover_bytes_read_in_the_report_and_in_rosbags(tmp_path: Path) -> None:
    """A Handover serialized by rclpy and written by the recorder's PartWriter, as
    `testbed.recording.Recording.record_handovers` does: the report's reader and rosbags' AnyReader
    (an independent CDR reader) both read every field back."""
    from edgeloc_interfaces.msg import Handover
    from rclpy.serialization import serialize_message
    from rosbags.highlevel import AnyReader

    from nodes.recording.parts import PartWriter
    from nodes.ros.common import to_stamp

    path = tmp_path / "handover.mcap"
    part = PartWriter(path)
    rows = [
        ("av1", "gnb1", "gnb2", 5.98, 0.013, 0.05, True, ""),
        ("av2", "gnb2", "gnb1", 9.5, 0.2, 0.1, False, "no route"),
    ]
    for k, (vehicle, source, target, scheduled, late, cut, lossless, error) in enumerate(rows):
        t = T0 + 6.0 + k
        msg = Handover(
            stamp=to_stamp(t),
            vehicle=vehicle,
            source=source,
            target=target,
            scheduled_s=scheduled,
            lateness_s=late,
            interruption_s=cut,
            lossless=lossless,
            error=error,
        )
        part.write(
            HANDOVER_TOPIC, "edgeloc_interfaces/msg/Handover", serialize_message(msg), int(t * 1e9)
        )
    part.close()
    data = read_run(path)
    assert data.problems == [] and data.topics == {HANDOVER_TOPIC: 2}
    assert data.handovers == [HandoverRec(T0 + 6.0 + k, *row) for k, row in enumerate(rows)]
    names = [f.name for f in fields(HandoverRec)][1:]  # the message's fields after its stamp
    seen: list[tuple[Any, ...]] = []
    with AnyReader([path]) as bag:
        for conn, _, raw in bag.messages():
            m = bag.deserialize(raw, conn.msgtype)
            stamp = m.stamp.sec + m.stamp.nanosec * 1e-9
            seen.append((stamp, *(getattr(m, n) for n in names)))
    assert seen == [astuple(h) for h in data.handovers]
