"""The report (`reports/`, `testbed report`) from synthetic run.mcap files written like the
recorder's: figures checked against values computed by hand, partial and damaged files,
missing channels, a failed node, a silent edge server, rebuilds and the CLI's exit codes."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from mcap.writer import Writer
from report_synth import SynthRun, stamp
from typer.testing import CliRunner

from reports.build import build_report, summarize
from reports.mcapread import ReportInputError, read_run
from testbed.cli import app

T0 = 1_700_000_000.0
runner = CliRunner()

LINKTEST = {
    "backend": "userspace (test)",
    "quick": True,
    "ok": True,
    "seconds": 3.5,
    "tolerances": {"delay_ms": 0.5, "rate_fraction": 0.05, "loss_pp": 0.5},
    "links": [
        {
            "link": "av1-gnb1",
            "rtt_median_ms": 16.2,
            "rtt_p99_ms": 19.9,
            "directions": [
                {
                    "link": "av1-gnb1",
                    "direction": "uplink",
                    "src": "av1",
                    "dst": "gnb1",
                    "profile": {"rate_mbit": 50.0, "delay_ms": 8.0},
                    "baseline_ms": 0.1,
                    "owd_median_ms": 8.11,
                    "owd_p99_ms": 12.5,
                    "jitter_sd_ms": 2.0,
                    "loss_pct": 0.1,
                    "loss_packets": 10000,
                    "tcp_mbit": 47.5,
                    "udp_mbit": None,
                    "verdicts": [
                        {
                            "what": "delay ms",
                            "measured": 8.11,
                            "expected": 8.1,
                            "tolerance": "±0.5 ms",
                            "ok": True,
                        }
                    ],
                    "ok": True,
                }
            ],
            "ok": True,
        }
    ],
}


def small_run(status: str = "ok") -> SynthRun:
    """10 frames at 10 Hz of one vehicle; every figure below is worked out by hand.

    Ground truth x = frame, y = 0. Position errors: vo 1.0 (and 2° of heading), dnn 0.5,
    kalman 0.4, edgeloc 0.1·frame with frame 7 never published. EdgeLoc's pose of frame 5 is
    published 0.25 s after capture (late at 10 Hz). Requests: image 50 ms and 70 ms, conv3
    30 ms and a timeout. One detector reset at 0.5 s."""
    s = SynthRun()
    for f in range(10):
        t = T0 + 0.1 * f
        s.pose("/av1/gt", t, f, "gt", f, 0.0, log_t=t + 0.001)
        s.pose("/av1/vo", t, f, "vo", f, 1.0, math.radians(2.0), log_t=t + 0.002)
        s.pose("/av1/pose", t, f, "vo", f, 1.0, math.radians(2.0), log_t=t + 0.01)
        s.pose("/av1/pose", t, f, "dnn", f + 0.5, 0.0, latency=0.05, log_t=t + 0.01)
        s.pose("/av1/pose", t, f, "kalman", f, -0.4, latency=0.05, log_t=t + 0.01)
        if f != 7:
            late = 0.25 if f == 5 else 0.01
            lat = 0.04 if f < 5 else 0.08
            s.pose("/av1/pose", t, f, "edgeloc", f, 0.1 * f, latency=lat, log_t=t + late)
    for k in range(1, 10):
        s.pose("/av1/dnn_answer", T0 + 0.1 * k - 0.05, k, "dnn", k, 0.5, latency=0.05)
    arms = ["image", "conv3", "vehicle"]
    reqs = [
        ("image", 0.05, True, False, 1000),
        ("image", 0.07, True, False, 1000),
        ("conv3", 0.03, True, False, 500),
        ("conv3", math.nan, False, True, 700),
    ]
    for k, (split, lat, ok, timed_out, size) in enumerate(reqs):
        t = T0 + 0.2 * k
        s.decision(t, 2 * k, split, arms, k, rule="explore" if k < 2 else "ucb")
        error = "" if ok else "timeout after 0.5 s"
        s.inference(t + 0.1, 2 * k, split, arms, lat, ok, timed_out, error, size, head_s=0.002)
    for k, reset in ((1, False), (2, True)):
        t = T0 + 0.25 * k
        s.add(
            t,
            "/av1/detector",
            "DetectorEvent",
            {
                "stamp": stamp(t),
                "vehicle": "av1",
                "arm": "conv3",
                "kl": 2.5 if reset else 0.2,
                "threshold": 1.0,
                "consecutive": 3 if reset else 0,
                "required": 3,
                "reset": reset,
                "at_play": k,
            },
        )
    for k in range(3):
        t = T0 + 0.5 * k
        s.add(
            t,
            "/links/counters",
            "LinkCounters",
            {
                "stamp": stamp(t),
                "link": "av1-gnb1",
                "direction": "up",
                "backend": "userspace",
                "packets_in": 100 * k,
                "bytes_in": 125_000 * k,
                "packets_out": 100 * k,
                "bytes_out": 125_000 * k,  # 1 Mbit per 0.5 s: 2 Mbit/s
                "packets_dropped": k,
                "bytes_dropped": 1000 * k,
                "queue_packets": 0,
            },
        )
    s.add(
        T0 + 0.3,
        "/links/events",
        "LinkEvent",
        {
            "stamp": stamp(T0 + 0.3),
            "scheduled_s": 0.3,
            "lateness_s": 0.002,
            "action": "shape",
            "target": "av1",
            "direction": "up",
            "keys": ["detail"],  # as nodes/ros/link_events.py publishes it
            "values": ["uplink 8 Mbit/s"],
        },
    )
    s.add(
        T0 + 0.6,
        "/links/events",
        "LinkEvent",
        {
            "stamp": stamp(T0 + 0.6),
            "scheduled_s": 0.6,
            "lateness_s": 0.001,
            "action": "outage",
            "target": "av1-gnb1",
            "direction": "both",
            "keys": ["detail"],
            "values": ["for 2 s"],
        },
    )
    s.metadata["edgeloc.run"] = {
        "run_id": "123456",  # digits only: must stay a string
        "scenario": "synthetic",
        "seed": "1",
        "link_backend": "userspace (test)",
        "status": status,
        "duration_s": "1.000",
        "host": json.dumps({"netem": False}),
    }
    s.metadata["edgeloc.nodes"] = {
        "av1.fusion": {"namespace": "el-x-av1", "exit_code": 0, "stats": {"answers": 9}},
        "core1.edge": {"namespace": "el-x-core1", "exit_code": 0, "stats": {"goals": 4}},
    }
    s.metadata["edgeloc.linktest"] = {"ran": "true", "ok": "true", "file": "linktest.json"}
    s.attachments["linktest.json"] = json.dumps(LINKTEST).encode()
    s.attachments["scenario.yaml"] = b"name: synthetic\nworkload:\n  rate_hz: 10\n"
    return s


def write_run(tmp_path: Path, synth: SynthRun, name: str = "run", **kw: object) -> Path:
    folder = tmp_path / name
    folder.mkdir()
    synth.write(folder / "run.mcap", **kw)  # type: ignore[arg-type]
    return folder


# ---- figures by hand ------------------------------------------------------------------------


def test_summary_matches_hand_computed_figures(tmp_path: Path) -> None:
    s = summarize(read_run(write_run(tmp_path, small_run())))
    assert s["partial"] is False and s["status"] == "ok"
    assert s["run"]["run_id"] == "123456"
    m = s["methods"]
    assert list(m) == ["vo", "dnn", "kalman", "edgeloc"]
    assert m["vo"]["position_m"]["total"] == pytest.approx(10.0)
    assert m["vo"]["heading_deg"]["mean"] == pytest.approx(2.0)
    assert m["dnn"]["position_m"]["total"] == pytest.approx(5.0)
    assert m["kalman"]["position_m"]["rmse"] == pytest.approx(0.4)
    e = m["edgeloc"]
    errs = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 0.9]  # frame 7 missing
    assert e["frames"] == 9 and e["missing_frames"] == 1
    p = e["position_m"]
    assert p["total"] == pytest.approx(3.8)
    assert p["mean"] == pytest.approx(3.8 / 9)
    assert p["median"] == pytest.approx(0.4)
    assert p["rmse"] == pytest.approx(math.sqrt(sum(x * x for x in errs) / 9))
    assert p["p95"] == pytest.approx(0.8 + 0.6 * 0.1)  # rank 0.95 * 8 = 7.6
    assert p["max"] == pytest.approx(0.9)
    red = {r["versus"]: r["ours_pct"] for r in s["paper_comparison"]["reductions"]}
    assert red == pytest.approx({"vo": 62.0, "dnn": 24.0, "kalman": 5.0})
    paper = {t["method"]: t["paper"] for t in s["paper_comparison"]["totals"]}
    assert paper["edgeloc"] == 2676.35
    assert s["headline"].startswith("run 123456: EdgeLoc total error 3.8 m; reduction 62.00% vs VO")

    lat = s["latency"]["per_split"]
    assert list(lat) == ["image", "conv3"]
    assert lat["image"]["requests"] == 2 and lat["image"]["answers"] == 2
    assert lat["image"]["latency_s"]["mean"] == pytest.approx(0.06)
    assert lat["image"]["latency_s"]["max"] == pytest.approx(0.07)
    assert lat["conv3"]["answers"] == 1 and lat["conv3"]["timed_out"] == 1
    assert lat["conv3"]["errors"] == 1
    assert lat["conv3"]["mean_payload_bytes"] == pytest.approx(600.0)
    av1 = s["per_vehicle"]["av1"]  # the vehicle's own requests, every split
    assert (av1["requests"], av1["answers"]) == (4, 3)
    assert av1["latency_s"]["median"] == pytest.approx(0.05)

    lr = s["learner"]
    assert lr["decisions"] == 4 and lr["switches"] == 1
    assert lr["split_share"] == {"image": 0.5, "conv3": 0.5}
    assert lr["rules"] == {"explore": 2, "ucb": 2}
    assert lr["detector_updates"] == 2
    assert [(r["t_s"], r["arm"], r["kl"]) for r in lr["resets"]] == [(0.5, "conv3", 2.5)]

    rt = s["realtime"]["vehicles"]["av1"]
    assert rt["rate_hz"] == 10.0 and rt["rate_source"] == "scenario"
    assert (rt["frames_expected"], rt["poses"], rt["missing"], rt["late"]) == (10, 9, 1, 1)
    assert rt["miss_pct"] == pytest.approx(20.0)
    assert rt["delay_s"]["max"] == pytest.approx(0.25, abs=1e-6)

    acc = s["accuracy_vs_latency"]
    assert acc["frames"] == 9
    # Quartile edges 0.04, 0.04, 0.08, 0.08, 0.08 collapse to one bin [0.04, 0.08]: all frames.
    assert [b["frames"] for b in acc["bins"]] == [9]
    assert acc["pearson_r"] > 0.8  # later frames: older answers and larger errors

    links = s["links"]
    assert links["backend"] == "userspace (test)"
    (rate,) = links["rates"]
    assert rate["mean_mbit"] == pytest.approx(2.0) and rate["packets_dropped"] == 2
    assert links["events"][0]["changes"] == {"detail": "uplink 8 Mbit/s"}
    assert links["events"][0]["t_s"] == pytest.approx(0.3)
    assert links["caps"] == {"av1": [{"t_s": 0.3, "uplink_mbit": 8.0, "downlink_mbit": None}]}
    assert links["outages"] == [{"link": "av1-gnb1", "start_s": 0.6, "end_s": 2.6}]
    assert links["linktest"]["links"][0]["link"] == "av1-gnb1"
    assert s["dnn_gaps"]["av1"]["gaps"] == []
    assert s["failures"] == []
    assert s["not_recorded"] == []


def test_report_files_and_contents(tmp_path: Path) -> None:
    folder = write_run(tmp_path, small_run())
    rep = build_report(folder)
    names = {p.relative_to(folder).as_posix() for p in rep.files}
    assert {"summary.json", "report.md", "report.html"} <= names
    for tum in ("gt", "vo", "dnn", "kalman", "edgeloc"):
        assert f"trajectories/av1/{tum}.tum" in names
    plots = sorted(n for n in names if n.startswith("plots/"))
    assert plots == [
        "plots/accuracy_vs_latency.png",
        "plots/error_boxplot.png",
        "plots/errors_over_time.png",
        "plots/latency_per_split.png",
        "plots/link_rates.png",
        "plots/realtime.png",
        "plots/split_av1.png",
        "plots/trajectory_av1.png",
    ]
    for p in plots:
        assert (folder / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    html = (folder / "report.html").read_text()
    # Self-contained: every figure inline, nothing fetched from elsewhere.
    assert html.count('src="data:image/png;base64,') == len(plots)
    assert "http://" not in html and "https://" not in html and "<script" not in html
    md = (folder / "report.md").read_text()
    for text in (
        "EdgeLoc total error 3.8 m",
        "| edgeloc | 9 | 1 | 3.800 |",  # frames, missing, total
        "| vo | 67.75 | 62.00 |",  # reduction beside the paper's
        "Link backend that ran: userspace (test)",
        "link self-test (every link within tolerance",
        "| av1-gnb1 | uplink | 16.20/19.90 |",
        "| av1 | edgeloc | 10 | 10 | 9 | 1 | 1 | 20.00 |",
        "![Split point over time, av1](plots/split_av1.png)",
    ):
        assert text in md, text
    assert "PARTIAL" not in md
    # The TUM file round-trips the edgeloc poses (evo reads the same format).
    from nodes.edgeloc.metrics import read_tum

    stamps, poses = read_tum(folder / "trajectories/av1/edgeloc.tum")
    assert len(stamps) == 9 and poses[9 - 1][1] == pytest.approx(0.9)


def test_rebuild_gives_identical_summary(tmp_path: Path) -> None:
    folder = write_run(tmp_path, small_run())
    first = build_report(folder)
    before = (folder / "summary.json").read_bytes()
    copy = tmp_path / "elsewhere"
    copy.mkdir()
    shutil.copyfile(folder / "run.mcap", copy / "run.mcap")  # from the MCAP alone
    second = build_report(copy, plots=False)  # figures do not feed the summary
    assert (copy / "summary.json").read_bytes() == before
    assert second.headline == first.headline
    build_report(folder, plots=False)
    assert (folder / "summary.json").read_bytes() == before
    json.loads(before)  # strict JSON: no NaN
    # Without figures the trajectories are still there (TUM files), not "not recorded".
    trajectories = (folder / "report.md").read_text().split("## Trajectories")[1].split("\n## ")[0]
    assert "Not recorded" not in trajectories and "TUM files for evo" in trajectories


# ---- damaged, partial, missing -----------------------------------------------------------------


def long_run(frames: int = 400) -> SynthRun:
    s = SynthRun()
    for f in range(frames):
        t = T0 + 0.05 * f
        s.pose("/av1/gt", t, f, "gt", f, 0.0)
        for m in ("vo", "dnn", "kalman", "edgeloc"):
            s.pose("/av1/pose", t, f, m, f, 0.2, latency=0.05)
    s.metadata["edgeloc.run"] = {"run_id": "long", "status": "ok"}
    return s


def test_unfinished_recording_gives_a_partial_report(tmp_path: Path) -> None:
    # A recorder killed mid-run: chunks written so far, no summary, no footer.
    folder = write_run(tmp_path, long_run(), chunk_size=4096, finish=False)
    data = read_run(folder / "run.mcap")
    assert not data.complete and data.partial
    assert "no MCAP footer" in data.problems[0]
    n = len(data.vehicles["av1"].tracks["gt"])
    assert 0 < n < 400
    rep = build_report(folder, plots=False)
    assert rep.partial and rep.headline.endswith("[partial]")
    assert rep.summary["methods"]["edgeloc"]["frames"] <= n
    assert "PARTIAL REPORT" in (folder / "report.html").read_text()
    assert "PARTIAL REPORT" in (folder / "report.md").read_text()


def test_truncated_file_gives_a_partial_report(tmp_path: Path) -> None:
    folder = write_run(tmp_path, long_run(), chunk_size=4096)
    path = folder / "run.mcap"
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])  # cut inside a chunk
    rep = build_report(folder, plots=False)
    s = rep.summary
    assert s["partial"] and not s["recording"]["complete"]
    assert any("ends early" in p for p in s["recording"]["problems"])
    assert 0 < s["methods"]["vo"]["frames"] < 400


def test_interrupted_run_is_partial_even_with_a_complete_file(tmp_path: Path) -> None:
    rep = build_report(write_run(tmp_path, small_run(status="interrupted")), plots=False)
    assert rep.partial and rep.summary["recording"]["complete"]


def test_missing_channels_are_named_not_fatal(tmp_path: Path) -> None:
    s = SynthRun()
    for f in range(5):
        s.pose("/av1/gt", T0 + f, f, "gt", f, 0.0)
        s.pose("/av1/pose", T0 + f, f, "edgeloc", f, 0.3)
    folder = write_run(tmp_path, s)  # no metadata, no learner, links or inference topics
    rep = build_report(folder, plots=False)
    sm = rep.summary
    assert sm["methods"]["edgeloc"]["position_m"]["total"] == pytest.approx(1.5)
    assert {r["versus"]: r["ours_pct"] for r in sm["paper_comparison"]["reductions"]} == {
        "vo": None,
        "dnn": None,
        "kalman": None,
    }
    for topic in ("/av1/inference", "/av1/split_decision", "/links/events", "/links/counters"):
        assert topic in sm["not_recorded"]
    assert "metadata edgeloc.run" in sm["not_recorded"]
    assert sm["latency"] == {"source": None, "per_split": {}}
    md = (folder / "report.md").read_text()
    assert "Not recorded: inference results (/<vehicle>/inference)." in md
    assert "Not recorded: split decisions" in md
    assert "Link backend: not recorded." in md


def test_empty_recording_still_builds(tmp_path: Path) -> None:
    s = SynthRun()
    s.metadata["edgeloc.run"] = {"run_id": "e", "status": "failed: nothing ran"}
    rep = build_report(write_run(tmp_path, s), plots=False)
    assert rep.summary["methods"] == {}
    assert "EdgeLoc total error n/a" in rep.headline
    md = (rep.folder / "report.md").read_text()
    assert "The run FAILED: nothing ran" in md
    assert "Not recorded" in md.split("## Trajectories")[1].split("\n## ")[0]


def test_not_an_mcap_is_refused(tmp_path: Path) -> None:
    (tmp_path / "run.mcap").write_text("hello")
    with pytest.raises(ReportInputError, match="not an MCAP file"):
        build_report(tmp_path)
    with pytest.raises(ReportInputError, match=r"no run\.mcap"):
        build_report(tmp_path / "nothing")
    (tmp_path / "run.mcap").write_bytes(b"\x89MCAP0\r\n")  # a recorder killed at once
    with pytest.raises(ReportInputError, match=r"no records in this MCAP \(the file ends early"):
        build_report(tmp_path)
    with open(tmp_path / "run.mcap", "wb") as f:  # finished, with nothing in it
        writer = Writer(f)
        writer.start()
        writer.finish()
    with pytest.raises(ReportInputError, match=r"no records in this MCAP \(an empty recording\)"):
        build_report(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


# ---- what issue #8 asks the report to show ---------------------------------------------------


def test_failed_node_is_named_with_its_last_log_lines(tmp_path: Path) -> None:
    s = small_run(status="failed: node av1.fusion exited with code 1")
    s.metadata["edgeloc.nodes"]["av1.fusion"] = {
        "namespace": "el-x-av1",
        "exit_code": 1,
        "stats": {},
        "log_tail": ["starting", "Traceback (most recent call last):", "ZeroDivisionError: boom"],
    }
    folder = write_run(tmp_path, s)
    rep = build_report(folder, plots=False)
    (fail,) = rep.summary["failures"]
    assert fail["process"] == "av1.fusion" and fail["exit_code"] == 1
    md = (folder / "report.md").read_text()
    assert "## Failed nodes" in md
    assert "av1.fusion (namespace el-x-av1) exited with code 1." in md
    assert "ZeroDivisionError: boom" in md
    assert "ZeroDivisionError: boom" in (folder / "report.html").read_text()


def test_silent_edge_server_shows_as_a_gap_while_poses_continue(tmp_path: Path) -> None:
    s = SynthRun()
    for f in range(100):  # 5 s at 20 Hz, fused poses throughout
        t = T0 + 0.05 * f
        s.pose("/av1/gt", t, f, "gt", f, 0.0, log_t=t)
        s.pose("/av1/pose", t, f, "edgeloc", f, 0.1, latency=0.05, log_t=t + 0.01)
    for k in [*range(20), *range(35, 50)]:  # answers every 0.1 s, none from 1.95 s to 3.55 s
        t = T0 + 0.05 + 0.1 * k
        s.pose("/av1/dnn_answer", t - 0.04, k, "dnn", k, 0.0, latency=0.04, log_t=t)
    rep = build_report(write_run(tmp_path, s), plots=False)
    g = rep.summary["dnn_gaps"]["av1"]
    assert g["answers"] == 35
    (gap,) = g["gaps"]
    assert gap["where"] == "middle"
    assert gap["start_s"] == pytest.approx(1.95) and gap["end_s"] == pytest.approx(3.55)
    # Fused poses published at 0.05·f + 0.01 s strictly inside the gap: f = 39 … 70.
    assert gap["fused_poses"] == 32
    md = (rep.folder / "report.md").read_text()
    assert "| middle | 1.95 | 3.55 | 1.60 | 32 |" in md


# ---- the CLI --------------------------------------------------------------------------------


def test_cli_report_builds_and_prints_the_headline(tmp_path: Path) -> None:
    folder = write_run(tmp_path, small_run())
    result = runner.invoke(app, ["report", str(folder), "--no-plots"])
    assert result.exit_code == 0, result.output
    assert "run 123456: EdgeLoc total error 3.8 m" in result.output
    assert f"report: {folder / 'report.html'}" in result.output
    only_json = runner.invoke(app, ["report", str(folder), "--formats", "json"])
    assert only_json.exit_code == 0, only_json.output
    assert f"report: {folder / 'summary.json'}" in only_json.output


def test_cli_report_exit_codes(tmp_path: Path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(app, ["report", str(empty)])
    assert result.exit_code == 2
    assert "no run.mcap here" in result.output
    assert runner.invoke(app, ["report", str(tmp_path / "nope")]).exit_code == 2
    (empty / "parts").mkdir()  # a run whose orchestrator was killed before the merge
    unmerged = runner.invoke(app, ["report", str(empty)])
    assert unmerged.exit_code == 2 and "testbed clean" in unmerged.output
    folder = write_run(tmp_path, small_run())
    bad = runner.invoke(app, ["report", str(folder), "--formats", "pdf"])
    assert bad.exit_code == 2 and "unknown pdf" in bad.output
    helped = runner.invoke(app, ["report", "--help"])
    assert helped.exit_code == 0 and "testbed report runs/" in helped.output


# ---- `testbed run` ends with the report ---------------------------------------------------------

SMOKE = Path(__file__).resolve().parent.parent / "scenarios" / "smoke.yaml"


def _fake_run(folder: Path, outcome: BaseException | None) -> object:
    """A stand-in for `testbed.run.run_scenario` that leaves `folder` with its run.mcap."""

    def run_scenario(
        scenario: object, runs_dir: Path, progress: object, capacity_check: bool = False
    ) -> object:
        if outcome is not None:
            outcome.run_folder = folder  # type: ignore[attr-defined]
            raise outcome
        return SimpleNamespace(
            run_id="123456",
            folder=folder,
            ok=True,
            timings_s={"up": 0.2, "down": 0.1},
            captures={},
        )

    return run_scenario


def test_run_ends_with_the_headline_and_the_report_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import testbed.run

    folder = write_run(tmp_path, small_run())
    monkeypatch.setattr(testbed.run, "run_scenario", _fake_run(folder, None))
    result = runner.invoke(app, ["run", str(SMOKE), "--runs-dir", str(tmp_path)])
    assert result.exit_code == 0, result.output
    *_, headline, path = result.output.strip().splitlines()
    assert headline.startswith("run 123456: EdgeLoc total error 3.8 m")
    assert path.startswith(f"report: {folder}/report.") and "(partial)" not in path
    assert (folder / "summary.json").is_file()


def test_failed_run_still_reports_and_exits_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import testbed.run
    from testbed.errors import TestbedError

    s = small_run(status="failed: node av1.fusion exited with code 1")
    s.metadata["edgeloc.nodes"]["av1.fusion"] = {"exit_code": 1, "log_tail": ["boom"]}
    folder = write_run(tmp_path, s)
    err = TestbedError("run 123456 failed: node av1.fusion exited with code 1")
    monkeypatch.setattr(testbed.run, "run_scenario", _fake_run(folder, err))
    result = runner.invoke(app, ["run", str(SMOKE), "--runs-dir", str(tmp_path)])
    assert result.exit_code == 1
    assert "node av1.fusion exited with code 1" in result.output
    assert f"report: {folder}/report." in result.output
    assert "## Failed nodes" in (folder / "report.md").read_text()


def test_interrupted_run_gets_a_partial_report_and_exits_130(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import testbed.run

    folder = write_run(tmp_path, long_run(), chunk_size=4096, finish=False)
    monkeypatch.setattr(testbed.run, "run_scenario", _fake_run(folder, KeyboardInterrupt()))
    result = runner.invoke(app, ["run", str(SMOKE), "--runs-dir", str(tmp_path)])
    assert result.exit_code == 130
    assert f"report: {folder}/report." in result.output and "(partial)" in result.output
    assert json.loads((folder / "summary.json").read_text())["partial"] is True


def test_every_summary_key_is_documented(tmp_path: Path) -> None:
    import importlib
    import pkgutil

    import reports.build
    import reports.sections

    s = summarize(read_run(write_run(tmp_path, small_run())))
    names = [m.name for m in pkgutil.iter_modules(reports.sections.__path__)]
    docs = [reports.build.__doc__] + [
        importlib.import_module(f"reports.sections.{n}").__doc__ for n in names
    ]
    doc = "\n".join(d or "" for d in docs)
    undocumented = [k for k in s if f"`{k}`" not in doc]
    assert not undocumented, (
        "document these summary.json keys in the reports/sections/ module that computes "
        f"them (or reports/build.py): {undocumented}"
    )


def test_vehicles_are_pooled_and_kept_apart(tmp_path: Path) -> None:
    s = SynthRun()
    for v, err in (("av1", 0.2), ("av2", 0.4)):
        for f in range(5):
            t = T0 + 0.05 * f
            s.pose(f"/{v}/gt", t, f, "gt", f, 0.0, vehicle=v)
            s.pose(f"/{v}/pose", t, f, "vo", f, 1.0, vehicle=v)
            s.pose(f"/{v}/pose", t, f, "edgeloc", f, err, vehicle=v)
    rep = build_report(write_run(tmp_path, s), plots=False)
    sm = rep.summary
    assert sm["vehicles"] == ["av1", "av2"]
    assert sm["methods"]["edgeloc"]["position_m"]["total"] == pytest.approx(3.0)
    assert sm["methods"]["edgeloc"]["frames"] == 10
    per = sm["per_vehicle"]
    assert per["av1"]["methods"]["edgeloc"]["position_m"]["total"] == pytest.approx(1.0)
    assert (per["av1"]["requests"], per["av1"]["latency_s"]) == (0, None)  # no inference
    assert per["av2"]["methods"]["edgeloc"]["position_m"]["max"] == pytest.approx(0.4)
    red = {r["versus"]: r["ours_pct"] for r in sm["paper_comparison"]["reductions"]}
    assert red["vo"] == pytest.approx(70.0)
    md = (rep.folder / "report.md").read_text()
    assert "*av1*" in md and "*av2*" in md  # one table per vehicle besides the pooled one


def test_a_topic_of_another_type_is_counted_not_fatal(tmp_path: Path) -> None:
    s = long_run(frames=5)
    event = {"stamp": stamp(T0), "action": "shape", "target": "av1", "keys": [], "values": []}
    s.add(T0 + 0.5, "/av2/pose", "LinkEvent", event)  # a LinkEvent where poses are expected
    rep = build_report(write_run(tmp_path, s), plots=False)
    rec = rep.summary["recording"]
    assert rec["decode_errors"] == 1
    assert "/av2/pose: 1 message(s) could not be decoded" in rec["problems"]
    assert rep.summary["methods"]["edgeloc"]["frames"] == 5


def test_learner_phases_between_timeline_events(tmp_path: Path) -> None:
    s = SynthRun()
    s.pose("/av1/gt", T0, 0, "gt", 0.0, 0.0)  # run time starts here
    arms = ["image", "conv3"]
    plays = [(0.1, "image"), (0.2, "image"), (0.3, "conv3"), (0.4, "image")]
    plays += [(1.1 + 0.1 * k, "conv3") for k in range(4)]
    for t, split in plays:
        s.add(
            T0 + t,
            "/av1/split_decision",
            "SplitDecision",
            {"stamp": stamp(T0 + t), "chosen": split, "arm_names": arms, "rule": "ucb"},
        )
    answers = [(0.15, "image", 0.05), (0.25, "image", 0.06), (0.35, "conv3", 0.02)]
    answers += [(0.45, "image", 0.07), (0.5, "conv3", 0.04)]  # phase 1: conv3 fastest
    answers += [(1.15, "conv3", 0.08), (1.25, "conv3", 0.1), (1.3, "image", 0.05)]
    answers += [(1.45, "image", 0.05)]  # phase 2: image fastest
    for t, split, lat in answers:
        s.add(
            T0 + t,
            "/av1/inference",
            "InferenceResult",
            {"stamp": stamp(T0 + t), "split": split, "latency_s": lat, "ok": True},
        )
    # the starting shape (scheduled at 0 s) lands after the first plays: it opens phase 1
    for t, scheduled in ((0.25, 0.0), (1.0, 1.0)):
        event = {"stamp": stamp(T0 + t), "action": "shape", "target": "av1", "keys": []}
        event |= {"values": [], "scheduled_s": scheduled}
        s.add(T0 + t, "/links/events", "LinkEvent", event)
    first, second = summarize(read_run(write_run(tmp_path, s)))["learner"]["phases"]
    assert (first["start_s"], first["end_s"], second["end_s"]) == pytest.approx((0, 1.0, 1.45))
    assert first["plays"] == 4 and first["chosen"] == "image"
    assert first["share"] == {"image": 0.75, "conv3": 0.25}
    assert first["best_in_hindsight"] == "conv3"
    assert first["mean_latency_s"] == pytest.approx({"image": 0.06, "conv3": 0.03})
    assert first["share_best"] == 0.25 and first["share_best_second_half"] == 0.5
    assert second["chosen"] == "conv3" and second["best_in_hindsight"] == "image"
    assert second["share_best"] == 0.0


def test_evo_reads_the_trajectories(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    folder = write_run(tmp_path, small_run())
    build_report(folder, formats=("json",))
    gt = file_interface.read_tum_trajectory_file(str(folder / "trajectories/av1/gt.tum"))
    est = file_interface.read_tum_trajectory_file(str(folder / "trajectories/av1/edgeloc.tum"))
    assert gt.num_poses == 10 and est.num_poses == 9
    assert est.positions_xyz[-1] == pytest.approx([9.0, 0.9, 0.0])


def test_the_cli_and_the_report_print_one_link_test_table() -> None:
    """`testbed link-test`'s text and the report's table come from one function of
    linktest.json (`nodes.recording.linktable`): same columns, same cells."""
    from nodes.recording import linktable
    from testbed.linktest import DirectionResult, LinkResult, LinkTestReport, Verdict

    d = DirectionResult("av1-gnb1", "uplink", "av1", "gnb1", {}, baseline_ms=0.0123)
    d.owd_median_ms, d.owd_p99_ms, d.tcp_mbit, d.loss_pct, d.loss_packets = 5.1, 6.2, 9.5, 0.1, 10
    d.verdicts = [Verdict("tcp Mbit/s", 9.5, 10.0, "5%", True)]
    report = LinkTestReport("userspace", True, [LinkResult("av1-gnb1", 10.2, 11.0, [d])])
    rows = linktable.rows(report.to_dict())
    assert rows[0][:4] == ["av1-gnb1", "uplink", "10.20/11.00", "0.012"]
    assert report.text().splitlines()[0].split("  ")[0] == linktable.HEADERS[0]
    assert all(cell in report.text() for cell in rows[0] if cell)


def test_a_radio_link_test_shows_its_cdfs_beside_the_oracle(tmp_path: Path) -> None:
    """The radio figures `testbed link-test` keeps reach the report: a table of each radio
    direction's W1, KS, tolerance, CDF points, HARQ shares and per-slot goodput, and a figure
    of the two CDFs."""
    import copy
    import random

    from netem.nr.radio import RADIO_PROFILES
    from testbed.linktest import harq_shares, oracle_comparison

    oracle = RADIO_PROFILES["oai-tdd-30k"].oracle("uplink", size_bytes=92)
    rng = random.Random(2)
    radio = oracle_comparison([oracle.quantile(rng.random()) * 1000 for _ in range(200)], oracle)
    radio.update(tolerance_ms=1.0, host_tolerance_ms=0.4, sampling_tolerance_ms=0.6)
    before = {"retransmissions": [0, 0, 0, 0, 0, 0]}
    radio["harq"] = harq_shares(before, {"retransmissions": [900, 90, 9, 1, 0, 0]}, 0.1, 4)
    radio["slots"] = {
        "blocks": 970,
        "occasions": 1078,
        "bytes_per_occasion": 4600.0,
        "expected_bytes_per_occasion": 4618.8,
        "bytes_per_block": 5112.0,
        "block_bytes": 5132.0,
        "occasions_per_s": 600.0,
        "seconds": 2.0,
        "used_share": 0.898,
    }
    lt = copy.deepcopy(LINKTEST)
    lt["links"][0]["directions"][0]["radio"] = radio  # type: ignore[index]
    lt["timer_floor"] = {"p50_ms": 0.057, "p99_ms": 0.198, "max_ms": 0.4, "count": 300}
    synth = small_run()
    synth.attachments["linktest.json"] = json.dumps(lt).encode()
    folder = write_run(tmp_path, synth)
    build_report(folder)
    assert (folder / "plots/radio_cdfs.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    md = (folder / "report.md").read_text()
    p50 = radio["measured_ms"][49], radio["oracle_ms"][49]
    for text in (
        "radio directions against the closed-form oracle",
        f"| av1-gnb1 | uplink | 200 | {radio['w1_ms']:.3f} | {radio['ks']:.3f} |",
        "1.000 (0.400 host + 0.600 chance)",
        f"{p50[0]:.2f} / {p50[1]:.2f}",
        "blocks 1000: +0 90% (90), +1 9% (9)",
        "4600 B per occasion (4619 expected: a 5132 B block less the resends), 5112 B per "
        "new block, 1078 occasions at saturation, 90% of the 600/s in 2.00 s",
        "timer floor: p50 0.057 ms, p99 0.198 ms over 300 timed wake-ups",
        "![Radio delays against the oracle](plots/radio_cdfs.png)",
    ):
        assert text in md, text


def _folder(path: Path) -> SimpleNamespace:
    """What the report's sections read of a run (`RunData`): where its run.mcap is, and its
    run.json (the folder's: nothing is attached here)."""
    from reports.mcapread import read_run_json

    return SimpleNamespace(path=path / "run.mcap", run_json=read_run_json(path, {}))


def test_the_recording_section_lists_the_runs_captures(tmp_path: Path) -> None:
    import json

    from reports.document import Section, Table
    from reports.sections.run import _captures

    (tmp_path / "pcap").mkdir()
    (tmp_path / "pcap" / "av1-gnb1.pcapng").write_bytes(b"\0" * 2000)
    (tmp_path / "pcap" / "gnb1-core1.pcapng.part").write_bytes(b"\0")  # unfinished: not listed
    captures = {"av1-gnb1": {"packets": {"uplink": 7, "downlink": 5},
                             "dropped": {"uplink": 2, "downlink": 0}}}  # fmt: skip
    (tmp_path / "run.json").write_text(json.dumps({"captures": captures}))
    sec = Section("Recording")
    _captures(sec, _folder(tmp_path))
    (table,) = [b for b in sec.blocks if isinstance(b, Table)]
    assert table.rows == [["pcap/av1-gnb1.pcapng", "0.00", "7 / 2", "5 / 0"]]
    # Both renderings link the file, relative to the report in the run folder.
    from reports.document import Document, to_markdown
    from reports.html import to_html

    doc = Document("t", "h", [sec])
    assert "| [pcap/av1-gnb1.pcapng](pcap/av1-gnb1.pcapng) | 0.00 |" in to_markdown(doc)
    html = to_html(doc, tmp_path)
    assert '<td><a href="pcap/av1-gnb1.pcapng">pcap/av1-gnb1.pcapng</a></td>' in html


def test_the_path_section_shows_each_vehicles_tunnel_edge_and_hops(tmp_path: Path) -> None:
    import json

    from reports.document import Para, Table
    from reports.sections.core_path import paths_section

    hops = [
        {"link": "av1-gnb1", "kind": "air", "uplink_delay_ms": 8.0, "downlink_delay_ms": 8.0},
        {"link": "gnb1-upf1", "kind": "n3", "uplink_delay_ms": 1.0, "downlink_delay_ms": 1.0},
        {"link": "upf1-edge1", "kind": "n6", "uplink_delay_ms": 5.0, "downlink_delay_ms": 5.0},
    ]
    path = {"vehicle": "av1", "address": "10.45.0.2", "gnb": "gnb1", "upf": "upf1",
            "edge": "edge1", "edge_address": "10.200.0.6", "placement": "core",
            "tunnel": {"ul_teid": "0x00001001", "dl_teid": "0x00002001"}, "hops": hops}  # fmt: skip
    core = {"gtp_overhead_bytes_per_packet": 44, "gtp_overhead_bytes": 440_000,
            "n3_bytes": 4_400_000, "gtp_overhead_share": 0.1,
            "ue_pool": "10.45.0.0/16",
            "qos_flows": "QFI 2 for DDS discovery; QFI 1 for the rest",
            "endpoints": {"gnb1": {"qfi_sent": {"1": 900, "2": 40}},
                          "upf1/gnb1": {"qfi_sent": {"1": 800, "2": 38}}}}  # fmt: skip
    assert paths_section(_folder(tmp_path)) is None  # no run.json: no section
    (tmp_path / "run.json").write_text(json.dumps({"paths": [path], "core_path": core}))
    per_vehicle = {"av1": {"requests": 40, "answers": 38, "latency_s": {"median": 0.0623},
                           "methods": {"edgeloc": {"position_m": {"mean": 1.234}}}}}  # fmt: skip
    sec = paths_section(_folder(tmp_path), per_vehicle)
    assert sec is not None
    (table,) = [b for b in sec.blocks if isinstance(b, Table)]
    (row,) = table.rows
    assert row[7:] == ["38 / 40", "62.3", "1.23"]  # what the path gave, beside it
    assert row[:5] == ["av1", "10.45.0.2", "gnb1", "upf1", "UL 0x00001001 / DL 0x00002001"]
    assert row[5] == "edge1 10.200.0.6 (core)"
    assert row[6] == "av1-gnb1 (air, 8/8 ms) + gnb1-upf1 (n3, 1/1 ms) + upf1-edge1 (n6, 5/5 ms)"
    para, qos = [b for b in sec.blocks if isinstance(b, Para)]
    assert "44 bytes per packet" in para.text and "(10.0%)" in para.text
    # With the link self-test's one-way medians, each tested hop shows them net of its path.
    linktest = {"links": [{"link": "gnb1-upf1", "directions": [
        {"direction": "uplink", "owd_median_ms": 1.154, "baseline_ms": 0.084},
        {"direction": "downlink", "owd_median_ms": 1.212, "baseline_ms": 0.1}]}]}  # fmt: skip
    measured = paths_section(_folder(tmp_path), per_vehicle, linktest)
    assert measured is not None
    (table,) = [b for b in measured.blocks if isinstance(b, Table)]
    assert table.rows[0][6] == (
        "av1-gnb1 (air, 8/8 ms) + gnb1-upf1 (n3, 1/1 ms; measured 1.07/1.11) + "
        "upf1-edge1 (n6, 5/5 ms)"
    )
    assert table.headers[6] == "hops (up/down delay, measured by the link self-test)"
    assert qos.text == (
        "QoS flows: QFI 2 for DDS discovery; QFI 1 for the rest. G-PDUs sent: uplink QFI 1: "
        "900, QFI 2: 40; downlink QFI 1: 800, QFI 2: 38."
    )


def test_run_json_is_read_from_the_folder_or_else_from_run_mcap(tmp_path: Path) -> None:
    """What the orchestrator wrote (run.json) comes with the recording: a report rebuilt from
    run.mcap alone shows it; without it anywhere, the report says what is left out."""
    from reports.sections.run import NO_RUN_JSON

    bare = write_run(tmp_path, small_run(), "bare")
    build_report(bare, formats=("md",), plots=False, splits=False)
    assert NO_RUN_JSON in (bare / "report.md").read_text()

    synth = small_run()
    flow = {"kind": "udp", "from": "av1", "to": "core1", "sent_bps": 1e6, "goodput_bps": 9e5,
            "loss": 0.1, "delay_p50_ms": 12.0, "stats": {}}  # fmt: skip
    synth.attachments["run.json"] = json.dumps({"traffic": {"cbr": flow}}).encode()
    attached = write_run(tmp_path, synth, "attached")
    build_report(attached, formats=("md",), plots=False, splits=False)
    md = (attached / "report.md").read_text()
    assert NO_RUN_JSON not in md and "## Cross-traffic" in md and "| cbr |" in md
    # the folder's own copy wins over the attached one
    (attached / "run.json").write_text(json.dumps({"traffic": {}}))
    build_report(attached, formats=("md",), plots=False, splits=False)
    assert "## Cross-traffic" not in (attached / "report.md").read_text()


def test_the_headline_says_what_the_air_link_was() -> None:
    """A run over an NR radio says so after its figures (and before `[partial]`); a plain pipe
    says nothing more. `air_link` reads it from the links' radios."""
    from netem.nr.radio import RADIO_PROFILES
    from reports.build import air_link
    from reports.sections.accuracy import headline, paper_comparison

    comparison = paper_comparison({"edgeloc": 2.0, "vo": 4.0, "dnn": 3.0, "kalman": 2.5})
    comparison = comparison.to_dict()
    plain = headline(comparison, "abc123")
    assert "over" not in plain
    radio = RADIO_PROFILES["public-n78-cicv5g"]
    both = {("av1-gnb1", "downlink"): radio, ("av1-gnb1", "uplink"): radio}
    air = air_link(SimpleNamespace(link_radios=both))  # type: ignore[arg-type]
    assert air == "NR DDDSUDDSUU 273 PRB, sr uplink (av1-gnb1)"
    line = headline(comparison, "abc123", partial=True, air=air)
    assert line.startswith(plain) and line.endswith(f"; over {air} [partial]")
    assert air_link(SimpleNamespace(link_radios={})) is None  # type: ignore[arg-type]
