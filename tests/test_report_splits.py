"""The split comparison in a real run's report (`reports.splits`, the report's "Split points"
section and figure), from synthetic run.mcap files written like the recorder's: the drive is a
short synthetic one whose ground truth the recording carries, the nodes' settings are
attached, and the requests of two of three configured splits were measured."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from report_synth import SynthRun

from nodes.edgeloc.dataset import open_dataset
from nodes.edgeloc.settings import LearnerSettings, ReplayConfig, config_to_dict
from nodes.recording.layout import NODE_CONFIG_FILE
from reports.build import build_report, report_after_run, summarize
from reports.mcapread import Decision, Inference, VehicleData, read_run
from reports.splits import measured_requests, split_comparison

T0 = 1_700_000_000.0
ARMS = ["image", "conv3", "vehicle"]
CONFIG = ReplayConfig(
    name="splits-test",
    seed=3,
    duration_s=10.0,
    rate_hz=10.0,
    splits=tuple(ARMS),
    learner=LearnerSettings(window=20),
    phases=(0.0, 5.0),
)
#: Measured own latency per split and phase: image is fast, then slow; conv3 always 80 ms.
LATENCY = {("image", 0): 0.04, ("image", 1): 0.15, ("conv3", 0): 0.08, ("conv3", 1): 0.08}


def run_with_splits(config: ReplayConfig | None = CONFIG, edgeloc_offset: float = 0.5) -> SynthRun:
    """The config's drive (ground truth and an EdgeLoc track `edgeloc_offset` m off), and a
    request every 0.25 s alternating image and conv3; one conv3 request times out, and the
    last request is the one the node was stopped in (not a lost request)."""
    cfg = config or CONFIG
    ds = open_dataset("synthetic", seed=cfg.seed, rate_hz=cfg.rate_hz, duration_s=cfg.duration_s)
    s = SynthRun()
    for i in range(len(ds)):
        t = T0 + ds.timestamp(i)
        x, y, yaw = (float(v) for v in ds.gt_pose(i))
        s.pose("/av1/gt", t, i, "gt", x, y, yaw)
        s.pose("/av1/pose", t, i, "edgeloc", x + edgeloc_offset, y, yaw, latency=0.05)
    requests = 38
    for k in range(requests):
        start = T0 + 0.05 + 0.25 * k
        split = ARMS[k % 2]
        phase = 0 if start - T0 < 5.0 else 1
        lost = k == 9
        stopped = k == requests - 1
        own = 1.0 if lost else LATENCY[(split, phase)]
        frame = round((start - T0) * cfg.rate_hz)
        s.decision(start, frame, split, ARMS, k)
        ok = not (lost or stopped)
        error = (
            "no result within the request timeout"
            if lost
            else "node stopped before the answer was used"
            if stopped
            else ""
        )
        # latency: answer - capture; the frame is up to one period older than the request
        capture_to_answer = own + 0.02 if ok else math.nan
        s.inference(start + own, frame, split, ARMS, capture_to_answer, ok, lost, error)
    s.metadata["edgeloc.run"] = {"run_id": "sp1", "scenario": "splits-test", "status": "ok"}
    if config is not None:
        s.attachments[NODE_CONFIG_FILE] = json.dumps(config_to_dict(config)).encode()
    return s


def write(tmp_path: Path, synth: SynthRun, name: str = "run") -> Path:
    folder = tmp_path / name
    folder.mkdir()
    synth.write(folder / "run.mcap")
    return folder


def test_requests_are_timed_from_their_own_start() -> None:
    vd = VehicleData("av1")
    vd.decisions = [
        Decision(100.0, 100.0, 7, "image", 0, "ucb", ARMS, math.nan, 0, 0),
        Decision(100.5, 100.5, 9, "conv3", 1, "ucb", ARMS, math.nan, 1, 1),
    ]

    def inf(t: float, frame: int, split: str, lat: float, ok: bool, err: str = "") -> Inference:
        return Inference(t, t, frame, split, 0, 10, 0.0, 0.0, lat, ok, not ok and not err, err)

    vd.inference = [
        inf(100.06, 7, "image", 0.11, True),  # own: 0.06 s (the answer is 0.11 s after capture)
        inf(101.5, 9, "conv3", math.nan, False),  # timed out, 1.0 s after its start
        inf(102.0, 11, "conv3", 0.07, True),  # no decision recorded: the answer age stands in
        inf(103.0, 13, "image", math.nan, False, "node stopped before the answer was used"),
    ]
    reqs = measured_requests(vd, t0=99.0, timeout_s=1.0)
    assert [(r.split, r.lost) for r in reqs] == [
        ("image", False),
        ("conv3", True),
        ("conv3", False),
    ]
    assert [r.latency_s for r in reqs] == pytest.approx([0.06, 1.0, 0.07])
    assert [r.t_s for r in reqs] == pytest.approx([1.0, 1.5, 2.93])


def test_a_scenario_with_report_compare_false_gets_a_report_that_says_how_to_add_it(
    tmp_path: Path,
) -> None:
    """`report: {compare: false}`: the report after the run leaves the replays out and says
    which command computes them; that command then does."""
    folder = write(tmp_path, run_with_splits())
    rep, why_not = report_after_run(folder, ("md", "json"), plots=False, splits=False)
    assert rep is not None and why_not is None
    said = json.loads((folder / "summary.json").read_text())["splits"]
    assert said == {
        "skipped": f"the scenario's report.compare is false; `testbed report {folder} --compare`"
        " computes it"
    }
    assert f"Not computed: {said['skipped']}." in (folder / "report.md").read_text()
    again = build_report(folder, formats=("json",), plots=False)
    assert [r["policy"] for r in again.summary["splits"]["rows"]][:2] == ["learned", "fixed:image"]


def test_real_run_report_compares_learned_fixed_and_oracle(tmp_path: Path) -> None:
    folder = write(tmp_path, run_with_splits())
    rep = build_report(folder, formats=("md", "json"))
    sp = json.loads((folder / "summary.json").read_text())["splits"]
    assert sp == rep.summary["splits"]
    assert sp["latency_source"] == "measured" and sp["vehicle"] == "av1"
    assert sp["requests"] == 37  # the stopped request is not one
    assert sp["replayed_splits"] == ["image", "conv3"]
    policies = [r["policy"] for r in sp["rows"]]
    assert policies[:4] == ["learned", "fixed:image", "fixed:conv3", "oracle"]
    assert sp["skipped"] == {"vehicle": "never played in this run, so its latency was not measured"}
    rows = {r["policy"]: r for r in sp["rows"]}
    # Each replayed request took a latency the run measured for its split in its phase.
    lat = [f["mean_latency_s"] for f in rows["fixed:image"]["phases"]]
    assert lat == pytest.approx([0.04, 0.15], abs=1e-6)
    conv3 = rows["fixed:conv3"]["phases"]
    print([f["mean_latency_s"] for f in conv3])
    assert all(0.08 - 1e-6 <= f["mean_latency_s"] <= 1.0 for f in conv3)
    assert [p["latency_best"] for p in sp["phases"]] == ["image", "conv3"]
    assert sp["oracle_splits"] == [p["error_best"] for p in sp["phases"]]
    # The real run's EdgeLoc: 0.5 m off on every one of the 100 frames.
    assert sp["real_learned_total_m"] == pytest.approx(50.0)
    assert sp["real_learned_total_m"] == pytest.approx(
        rep.summary["per_vehicle"]["av1"]["methods"]["edgeloc"]["position_m"]["total"]
    )

    md = (folder / "report.md").read_text()
    section = md.split("## Split points: learned, fixed, oracle")[1].split("\n## ")[0]
    assert md.index("## Split-point learner") < md.index("## Split points: learned")
    for text in ("| learned |", "| fixed:image |", "| fixed:conv3 |", "| oracle |"):
        assert text in section, text
    assert " / 40.0 |" in section and " / 150.0 |" in section  # image's latency per phase
    assert "The real run's learned EdgeLoc (av1, as recorded): total 50.0 m" in section
    assert "Phase 0-5 s: fastest image" in section and "Phase 5-10 s: fastest conv3" in section
    assert "replays with the run's measured latencies" in section
    assert "reading ground truth" in section
    assert "No row for vehicle: never played in this run" in section
    for line in sp["disagreements"]:  # what the drive resolves is a warning, a tie a row
        said = f"Against the paper's claim: {line}." in section
        assert said == ("within the drive's noise" not in line), line
    for p in sp["phases"]:
        for v in p["inversions"]:
            row = f"| {p['start_s']:g}-{p['end_s']:g} s | {v['slower']} | {v['faster']} |"
            assert (row in section) == (not v["beyond_noise"]), (row, section)
    assert "A tie: the learned run (45.5 m) loses to fixed conv3" in section
    # conv3 beat the faster image in 0-5 s: weighed against the drive's noise, and said so
    [inv] = sp["phases"][0]["inversions"]
    assert (inv["faster"], inv["slower"]) == ("image", "conv3") and inv["by_m"] > 0
    assert sp["phases"][1]["inversions"] == [] and sp["noise_block_s"] == 10.0
    assert "conv3 is" in sp["disagreements"][1] and "the drive's noise (±" in section
    assert "over blocks of about 10 s: an inversion within it is a tie" in section
    assert "![Error against latency per split and phase](plots/split_error_latency.png)" in section
    assert (folder / "plots" / "split_error_latency.png").read_bytes()[:4] == b"\x89PNG"


def test_without_the_settings_attachment_the_report_says_why(tmp_path: Path) -> None:
    folder = write(tmp_path, run_with_splits(config=None))
    rep = build_report(folder, formats=("md",))
    assert "no nodes/config.json attachment" in rep.summary["splits"]["skipped"]
    md = (folder / "report.md").read_text()
    section = md.split("## Split points: learned, fixed, oracle")[1].split("\n## ")[0]
    assert "Not computed: the recording has no nodes/config.json attachment" in section
    assert not (folder / "plots" / "split_error_latency.png").exists()


@pytest.mark.parametrize(
    ("config", "says"),
    [
        (ReplayConfig(dataset="/data/kitti-00", duration_s=10.0), "recorded folder"),
        (ReplayConfig(weights="/nonexistent/locnet.pt", duration_s=10.0), "weights do not load"),
    ],
)
def test_what_cannot_be_replayed_is_skipped_with_the_reason(
    tmp_path: Path, config: ReplayConfig, says: str
) -> None:
    synth = run_with_splits(config=None)
    synth.attachments[NODE_CONFIG_FILE] = json.dumps(config_to_dict(config)).encode()
    data = read_run(write(tmp_path, synth))
    assert says in split_comparison(data)["skipped"]


def test_a_stale_settings_file_and_a_run_without_requests_are_skipped(tmp_path: Path) -> None:
    synth = run_with_splits(config=None)
    synth.attachments[NODE_CONFIG_FILE] = b'{"no_such_setting": 1}'
    assert (
        "not a nodes' settings file"
        in split_comparison(read_run(write(tmp_path, synth)))["skipped"]
    )
    quiet = SynthRun()
    quiet.pose("/av1/gt", T0, 0, "gt", 0.0, 0.0)
    quiet.attachments[NODE_CONFIG_FILE] = json.dumps(config_to_dict(CONFIG)).encode()
    data = read_run(write(tmp_path, quiet, "quiet"))
    assert "no inference request was recorded" in split_comparison(data)["skipped"]
    assert summarize(data, splits=False)["splits"] == {
        "skipped": "not computed (the report was built without it)"
    }
