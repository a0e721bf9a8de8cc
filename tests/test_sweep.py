"""`testbed sweep`: grid expansion, overrides on the YAML tree, errors that name the field, and a
tiny offline sweep of two variants that writes the three report files. No root needed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from testbed.errors import BadInput
from testbed.scenario.issues import ScenarioError
from testbed.sweep import (
    grid,
    label,
    load_tree,
    parse_set,
    read_tree,
    rescale,
    set_path,
    shorten,
    split_values,
    variant_tree,
)

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "scenarios" / "smoke.yaml"


def _testbed(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "testbed.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env={"CI": "1", "PATH": "/usr/bin:/bin"},
        timeout=600,
    )


# ---- pure parts ------------------------------------------------------------------------------


def test_values_split_on_commas_but_not_inside_brackets() -> None:
    assert split_values("4ms, 20ms,50ms") == ["4ms", "20ms", "50ms"]
    assert split_values("[image,conv3],[vehicle]") == ["[image,conv3]", "[vehicle]"]
    axis = parse_set("workload.splits=[image,conv3],[vehicle]")
    assert axis.values == (["image", "conv3"], ["vehicle"])
    assert parse_set("workload.learner.window=20,100").values == (20, 100)
    assert parse_set("workload.learner.detector=true,false").values == (True, False)
    assert parse_set("workload.learner.fixed_split=null,image").values == (None, "image")


def test_grid_is_every_combination_first_axis_slowest() -> None:
    axes = [parse_set("a.b=1,2"), parse_set("c=x,y,z")]
    variants = grid(axes)
    assert variants == [
        {"a.b": 1, "c": "x"},
        {"a.b": 1, "c": "y"},
        {"a.b": 1, "c": "z"},
        {"a.b": 2, "c": "x"},
        {"a.b": 2, "c": "y"},
        {"a.b": 2, "c": "z"},
    ]
    assert label(axes, 4) == {"a.b": "2", "c": "y"}


@pytest.mark.parametrize(
    ("option", "says"),
    [
        ("workload.learner.window", "expected KEY=V1,V2"),
        ("=1,2", "expected KEY=V1,V2"),
        ("a..b=1", "is not a key"),
        ("workload.learner.window=20,20", "listed twice"),
        ("workload.learner.window=20,", "an empty value"),
        ("links.air.uplink.delay=[4ms", "not a YAML value"),
    ],
)
def test_malformed_options_are_bad_input(option: str, says: str) -> None:
    with pytest.raises(BadInput, match=says.replace("[", r"\[")):
        parse_set(option)


def test_grid_refuses_a_key_twice_and_no_axes() -> None:
    with pytest.raises(BadInput, match="given twice"):
        grid([parse_set("seed=1,2"), parse_set("seed=3")])
    with pytest.raises(BadInput, match="at least one --set"):
        grid([])


def test_overrides_reach_nested_fields_lists_and_single_links() -> None:
    base = read_tree(SMOKE)
    data = variant_tree(
        base,
        {
            "links.air.radio.mcs": 9,
            "workload.fusion.k_s": 40,  # smoke.yaml has no fusion: the mapping is made
            "timeline[1].uplink": "4mbit",
            "topology.vehicles.av1.cpu": 0.5,
            "links.av1-gnb1.downlink.loss": "1%",
        },
    )
    assert "mcs" not in base["links"]["air"]["radio"]  # the base tree is untouched
    scenario = load_tree(data, SMOKE, "test")
    air = scenario.links.get("av1-gnb1")
    assert air.uplink.radio is not None and air.uplink.radio.mcs == 9
    assert air.downlink.loss == pytest.approx(0.01)
    assert air.downlink.radio is not None and air.downlink.radio.sr_period_slots == 10
    assert scenario.links.get("gnb1-upf1").downlink.loss == 0  # other links keep defaults
    assert scenario.workload.fusion.k_s == 40
    assert scenario.timeline[1].uplink_bps == 4e6  # type: ignore[union-attr]
    assert scenario.topology.vehicles[0].cpu == 0.5


@pytest.mark.parametrize(
    ("key", "says"),
    [
        ("timeline[9].uplink", r"timeline has 2 item\(s\); \[9\]"),
        ("topology.vehicles.av7.cpu", "no item named 'av7' .items: av1."),
        ("name.first", "name is a value, not a mapping"),
        ("seed[0]", "seed is not a list"),
        ("links.av1-gnb1", "name a direction and a field"),
    ],
)
def test_keys_that_name_nothing_are_bad_input(key: str, says: str) -> None:
    with pytest.raises(BadInput, match=says):
        set_path(read_tree(SMOKE), key, 1)


def test_a_bad_value_is_reported_by_the_loader_with_the_field_path() -> None:
    data = variant_tree(read_tree(SMOKE), {"links.air.uplink.delay": "8mbit"})
    with pytest.raises(ScenarioError) as err:
        load_tree(data, SMOKE, "--set links.air.uplink.delay=8mbit")
    (issue,) = err.value.issues
    assert issue.path == "links.air.uplink.delay"
    assert "a duration like 8ms" in issue.expected and issue.found == "'8mbit'"
    assert "--set links.air.uplink.delay=8mbit" in str(err.value)


def test_shorten_scales_the_timeline_with_the_duration() -> None:
    base = read_tree(REPO / "scenarios" / "handover_outage.yaml")
    short = shorten(base, 8.0)
    assert short["duration"] == "8s"
    outages = [e for e in short["timeline"] if "outage" in e]
    assert [(e["at"], e["for"]) for e in outages] == [("3s", "0.6s"), ("6s", "0.1s")]
    assert load_tree(short, REPO / "scenarios" / "handover_outage.yaml", "test").duration_s == 8


def test_rescale_stretches_each_phase_and_shorten_only_the_last() -> None:
    file = REPO / "scenarios" / "default.yaml"
    base = read_tree(file)
    long = rescale(base, 360.0)
    assert long["duration"] == "360s"
    assert [e["at"] for e in long["timeline"]] == [0, "120s", "240s"]
    assert load_tree(long, file, "test").duration_s == 360
    longer = shorten(base, 360.0)  # a longer run, its last phase lengthened, no event moved
    assert longer["duration"] == "360s"
    assert [e["at"] for e in longer["timeline"]] == [0, "30s", "60s"]
    assert base["duration"] == "90s"  # and neither changes the tree it is given


# ---- the verb --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--set", "workload.lerner.window=2,3"], "workload.lerner: expected one of the keys"),
        (["--set", "workload.learner.window=1,3"], "workload.learner.window: expected a window"),
        (["--set", "links.air.uplink.rate=20mbps"], "links.air.uplink.rate: expected a rate"),
        (["--set", "duration=5s"], "timeline[1].at: expected a time within the run"),
        (["--set", "topology.vehicles[3].cpu=1"], "topology.vehicles has 1 item(s)"),
        (["--set", "seed=1", "--duration", "fast"], "--duration: expected a duration"),
    ],
)
def test_bad_set_exits_2_naming_the_field(args: list[str], says: str, tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    r = _testbed("sweep", str(SMOKE), *args, "--out", str(out))
    assert r.returncode == 2, r.stdout + r.stderr
    assert says in r.stderr, r.stderr
    assert not out.exists()  # nothing ran


def test_a_broken_scenario_file_is_reported_with_its_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(SMOKE.read_text().replace("rate_hz: 20", "rate_hz: fast"))
    r = _testbed("sweep", str(bad), "--set", "seed=1,2", "--out", str(tmp_path / "o"))
    assert r.returncode == 2
    assert f"{bad}:" in r.stderr and "workload.rate_hz" in r.stderr, r.stderr


@pytest.mark.slow
def test_a_tiny_offline_sweep_writes_the_report(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    r = _testbed(
        "sweep",
        str(SMOKE),
        "--set",
        "links.air.uplink.delay=2ms,80ms",
        "--duration",
        "4s",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "variant 1/2: links.air.uplink.delay=2ms" in r.stdout
    assert "variant 2/2: links.air.uplink.delay=80ms" in r.stdout
    report = json.loads((out / "sweep.json").read_text())
    assert report["mode"] == "replay"
    assert report["axes"] == [{"key": "links.air.uplink.delay", "values": ["2ms", "80ms"]}]
    rows = report["variants"]
    assert [r["values"] for r in rows] == [
        {"links.air.uplink.delay": "2ms"},
        {"links.air.uplink.delay": "80ms"},
    ]
    for row in rows:
        assert row["error"] is None
        assert set(row["methods"]) == {"vo", "dnn", "kalman", "edgeloc"}
        assert all(m["total_m"] > 0 for m in row["methods"].values())
        assert sum(row["split_share"].values()) == pytest.approx(1.0)
        assert row["requests"] > 0
        assert (Path(row["folder"]) / "summary.json").is_file()
    # 78 ms more on the uplink: every answer waits at least that much longer (more where the
    # protocol crosses the uplink twice, as a ROS 2 action does).
    fast, slow = rows[0]["mean_latency_s"], rows[1]["mean_latency_s"]
    assert 0.07 < slow - fast < 0.4, (fast, slow)
    md = (out / "sweep.md").read_text()
    assert "| links.air.uplink.delay | edgeloc total m |" in md
    assert md.count("\n| 2ms |") == 1 and md.count("\n| 80ms |") == 1
    png = (out / "sweep.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000
    assert sorted(p.name for p in (out / "variants").iterdir()) == ["v01.yaml", "v02.yaml"]


def test_a_real_run_of_a_sweep_runs_with_the_long_lived_objects_frozen(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A sweep's real run may happen in a process that holds torch (the local loop after its
    first report, each Ray run): its objects are frozen for the run, so the cyclic collector's
    full passes do not pause the timeline (~140 ms each with torch loaded), and thawed after."""
    import gc

    import testbed.run
    from testbed.errors import TestbedError
    from testbed.scenario import load
    from testbed.sweep.jobs import Job, run_job

    frozen: list[int] = []

    def run_scenario(*_args: object, **_kwargs: object) -> None:
        frozen.append(gc.get_freeze_count())
        raise TestbedError("stopped by the test")

    monkeypatch.setattr(testbed.run, "run_scenario", run_scenario)
    job = Job(0, 7, "v0-seed7", {"seed": "7"}, load(SMOKE), "", "variant 1/1: seed=7")
    before = gc.get_freeze_count()
    (row,) = run_job(job, True, tmp_path, lambda _line: None)
    assert row.error == "stopped by the test"
    assert frozen and frozen[0] > 10_000, frozen  # everything alive then, modules included
    assert gc.get_freeze_count() == before
