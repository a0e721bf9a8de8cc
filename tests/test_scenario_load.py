"""Valid scenarios load into the typed model with SI values, merged overrides and defaults."""

from __future__ import annotations

import dataclasses
import ipaddress
from pathlib import Path

import pytest

from netem.nr.radio import RADIO_PROFILES
from netem.profile import DEFAULT_QUEUE_PACKETS, GilbertElliott, LinkProfile
from testbed.scenario import ScenarioError, load, loads
from testbed.scenario import model as m

SCENARIOS = Path(__file__).resolve().parent.parent / "scenarios"

BASE = """\
name: t
duration: 90s
topology:
  cells: [{gnb: gnb1, core: core1}]
  vehicles: [{name: av1, gnb: gnb1}]
"""


def test_default_scenario() -> None:
    s = load(SCENARIOS / "default.yaml")
    assert (s.name, s.seed, s.duration_s, s.version) == ("default", 7, 90.0, 1)
    assert s.source == SCENARIOS / "default.yaml"
    assert s.topology.vehicles == (m.Vehicle("av1", "gnb1", cpu=0.025),)
    assert s.topology.cells == (m.Cell("gnb1", upf="upf1", edge="edge1", placement="core"),)
    assert s.links.backend == "auto"
    assert sorted(s.links.names()) == ["av1-gnb1", "gnb1-upf1", "upf1-edge1"]
    air = s.links.get("av1-gnb1")
    assert (air.kind, air.lower, air.upper) == ("air", "av1", "gnb1")
    # The NR cell a fidelity case calibrated, its core and cloud left to N3 and N6.
    cell = dataclasses.replace(RADIO_PROFILES["public-n78-cicv5g"], core_delay_s=0.0)
    assert air.uplink == LinkProfile(radio=cell) and air.downlink == LinkProfile(radio=cell)
    pipe = load(SCENARIOS / "default_pipe.yaml").links.get("av1-gnb1")
    assert pipe.uplink == LinkProfile(rate_bps=50e6, delay_s=0.008, jitter_s=0.002, loss=0.001)
    assert pipe.downlink.rate_bps == 200e6
    n3 = s.links.get("gnb1-upf1")
    assert (n3.kind, n3.uplink) == ("n3", LinkProfile(rate_bps=1e9, delay_s=0.001))
    assert s.links.get("upf1-edge1").uplink == LinkProfile()  # N6: the edge on the UPF's host
    # The paper's three uplink phases, in order.
    assert [(e.at_s, e.node, e.uplink_bps) for e in s.timeline] == [
        (0.0, "av1", 40e6),
        (30.0, "av1", 2e6),
        (60.0, "av1", 20e6),
    ]
    assert all(isinstance(e, m.ShapeEvent) and e.downlink_bps is None for e in s.timeline)
    assert s.workload.fusion == m.Fusion(k_s=2.0, dt0_s=-1.4)


def test_smoke_scenario() -> None:
    s = load(SCENARIOS / "smoke.yaml")
    assert (s.name, s.duration_s, len(s.timeline)) == ("smoke", 20.0, 2)
    assert s.workload.learner.window == 20
    assert s.report.formats == ("json", "md")
    assert s.links.names() == load(SCENARIOS / "default.yaml").links.names()


@pytest.mark.parametrize("path", sorted(SCENARIOS.glob("*.yaml")), ids=lambda p: p.name)
def test_every_committed_scenario_loads_and_has_the_schema_hint(path: Path) -> None:
    load(path)
    first = path.read_text().splitlines()[0]
    assert first == "# yaml-language-server: $schema=scenario.schema.json"


def test_minimal_file_gets_model_defaults() -> None:
    s = loads(BASE)
    assert s.seed == 0
    assert s.version == 1
    assert s.source is None
    assert s.timeline == ()
    assert s.workload == m.Workload()
    assert s.record == m.Record()
    assert s.report == m.Report()
    assert s.topology.address_pool is None
    assert s.links.backend == "auto"
    # No air/backhaul section: links exist but do nothing to packets.
    assert s.links.get("av1-gnb1").uplink == LinkProfile()
    assert s.links.get("gnb1-core1").downlink.queue_packets == DEFAULT_QUEUE_PACKETS


def test_units_map_to_si_values() -> None:
    s = loads(
        BASE
        + """\
links:
  air:
    uplink: {rate: 20mbit, delay: 8ms, jitter: 500us, loss: 0.5%, queue: 50ms,
             jitter_distribution: pareto, reorder: true}
    downlink: {rate: unlimited, queue: 200}
"""
    )
    up = s.links.get("av1-gnb1").uplink
    assert up.rate_bps == 20e6
    assert up.delay_s == 0.008
    assert up.jitter_s == 0.0005
    assert up.loss == 0.005
    assert (up.queue_packets, up.queue_time_s) == (None, 0.05)
    assert (up.jitter_distribution, up.reorder) == ("pareto", True)
    down = s.links.get("av1-gnb1").downlink
    assert down.rate_bps is None
    assert (down.queue_packets, down.queue_time_s) == (200, None)


def test_gilbert_elliott_loss() -> None:
    s = loads(
        BASE + "links:\n  air:\n    uplink:\n      loss: {model: gilbert-elliott, p: 1%, r: 30%}\n"
    )
    up = s.links.get("av1-gnb1").uplink
    assert up.gilbert_elliott == GilbertElliott(p=0.01, r=0.3, good_loss=0.0, bad_loss=1.0)
    assert up.loss == 0.0


def test_overrides_merge_over_the_defaults() -> None:
    s = loads(
        """\
name: t
duration: 60s
topology:
  address_pool: 192.168.0.0/24
  cells:
    - {gnb: gnb1, core: core1, core_cpu: 2}
    - {gnb: gnb2, core: core2}
  vehicles:
    - {name: av1, gnb: gnb1, cpu: 0.5}
    - {name: av2, gnb: gnb1}
    - {name: av3, gnb: gnb2}
links:
  backend: userspace
  air:
    uplink: {rate: 50mbit, delay: 8ms, jitter: 2ms, loss: 0.1%}
    downlink: {rate: 200mbit, delay: 8ms}
  backhaul:
    uplink: {rate: 1gbit, delay: 1ms}
    downlink: {rate: 1gbit, delay: 1ms}
  overrides:
    - link: av2-gnb1
      uplink: {rate: 10mbit, loss: {model: gilbert-elliott, p: 2%, r: 20%}}
    - link: gnb2-core2
      downlink: {delay: 5ms, queue: 10ms}
"""
    )
    assert s.links.backend == "userspace"
    assert s.topology.address_pool == ipaddress.IPv4Network("192.168.0.0/24")
    assert s.topology.cells[0].core_cpu == 2.0
    assert s.topology.vehicles[0].cpu == 0.5
    assert s.topology.role_of("core2") == "core"
    assert s.links.names() == ["av1-gnb1", "av2-gnb1", "av3-gnb2", "gnb1-core1", "gnb2-core2"]
    av1, av2 = s.links.get("av1-gnb1"), s.links.get("av2-gnb1")
    assert av1.uplink == LinkProfile(rate_bps=50e6, delay_s=0.008, jitter_s=0.002, loss=0.001)
    # av2: only rate and loss changed; delay and jitter come from links.air.
    assert av2.uplink.rate_bps == 10e6
    assert (av2.uplink.delay_s, av2.uplink.jitter_s) == (0.008, 0.002)
    assert av2.uplink.loss == 0.0  # the Gilbert-Elliott model replaces the random loss
    assert av2.uplink.gilbert_elliott == GilbertElliott(p=0.02, r=0.2)
    assert av2.downlink == av1.downlink
    core2 = s.links.get("gnb2-core2")
    assert core2.downlink.delay_s == 0.005
    assert core2.downlink.rate_bps == 1e9
    assert (core2.downlink.queue_packets, core2.downlink.queue_time_s) == (None, 0.01)
    assert core2.uplink == s.links.get("gnb1-core1").uplink


def test_timeline_events_are_typed_and_sorted(tmp_path: Path) -> None:
    (tmp_path / "traces").mkdir()
    trace = tmp_path / "traces" / "up.csv"
    trace.write_text("time_s,mbit\n0,10\n5,2.5\n")
    s = loads(
        BASE
        + """\
timeline:
  - {at: 50s, set: av1-gnb1, direction: uplink, delay: 30ms, loss: 1%}
  - {at: 20s, shape: av1, uplink: 5mbit, downlink: 50mbit}
  - {at: 40s, clear: av1}
  - {at: 60s, outage: av1-gnb1, for: 2s}
  - {at: 0s, trace: av1-gnb1, direction: downlink, file: traces/up.csv, loop: true}
  - {at: 1m, set: gnb1-core1, rate: unlimited}
""",
        source="t.yaml",
        base_dir=tmp_path,
    )
    kinds = [type(e).__name__ for e in s.timeline]
    assert kinds == [
        "TraceEvent",
        "ShapeEvent",
        "ClearEvent",
        "SetEvent",
        "OutageEvent",
        "SetEvent",
    ]
    trace_ev, shape, clear, set_ev, outage, set2 = s.timeline
    assert trace_ev == m.TraceEvent(0.0, "av1-gnb1", "downlink", trace, "csv", True, line=11)
    assert shape == m.ShapeEvent(20.0, "av1", 5e6, 50e6, line=8)
    assert clear == m.ClearEvent(40.0, "av1", line=9)
    assert set_ev.direction == "uplink"
    assert set_ev.changes == {"delay_s": 0.03, "loss": 0.01, "gilbert_elliott": None}
    assert set_ev.line == 7
    assert outage == m.OutageEvent(60.0, "av1-gnb1", 2.0, line=10)
    assert (set2.direction, set2.changes) == ("both", {"rate_bps": None})
    # The changes apply to a LinkProfile as they are.
    assert LinkProfile().replace(**set_ev.changes).delay_s == 0.03


def test_trace_format_follows_the_extension_unless_given() -> None:
    s = loads(
        BASE
        + """\
timeline:
  - {at: 0s, trace: av1-gnb1, direction: uplink, file: traces/step-12-6mbit.mahi}
  - {at: 0s, trace: av1-gnb1, direction: downlink, file: traces/uplink-steps.csv}
""",
        base_dir=SCENARIOS,
    )
    assert [(e.format, e.path.name) for e in s.timeline] == [  # type: ignore[union-attr]
        ("mahimahi", "step-12-6mbit.mahi"),
        ("csv", "uplink-steps.csv"),
    ]
    with pytest.raises(ScenarioError, match="a whole number of milliseconds"):
        loads(
            BASE + "timeline:\n  - {at: 0s, trace: av1-gnb1, direction: uplink,"
            " file: traces/uplink-steps.csv, format: mahimahi}\n",
            base_dir=SCENARIOS,
        )


def test_workload_paths_resolve_relative_to_the_file(tmp_path: Path) -> None:
    (tmp_path / "data" / "kitti").mkdir(parents=True)
    (tmp_path / "w.pt").write_bytes(b"\0")
    scenario_file = tmp_path / "s.yaml"
    scenario_file.write_text(
        BASE
        + """\
workload:
  rate_hz: 10
  dataset: data/kitti
  weights: w.pt
  codec: int8-zlib
  splits: [conv2, conv4]
  corruption: 5%
  learner: {window: 30, cost: error, fixed_split: conv4, detector: false, kl_threshold: 0.5,
            consecutive: 2, detector_window: 8}
  fusion: {k_s: 10, dt0: 100ms}
  kalman: {q_pos: 0.1, q_yaw: 0, r_pos: 1, r_yaw: 0.02}
record: {enabled: false, compression: lz4, images: true}
report: {enabled: true, formats: [md], plots: false, link_test: false}
"""
    )
    s = load(scenario_file)
    w = s.workload
    assert w.dataset == tmp_path / "data" / "kitti"
    assert w.weights == tmp_path / "w.pt"
    assert (w.rate_hz, w.codec, w.splits, w.corruption) == (
        10.0,
        "int8-zlib",
        ("conv2", "conv4"),
        0.05,
    )
    assert w.learner == m.Learner(30, "error", "conv4", False, 0.5, 2, 8)
    assert w.fusion == m.Fusion(10.0, 0.1)
    assert w.kalman == m.Kalman(0.1, 0.0, 1.0, 0.02)
    assert s.record == m.Record(False, "lz4", True)
    assert s.report == m.Report(True, ("md",), False, False)


def test_partial_workload_sections_keep_model_defaults() -> None:
    s = loads(BASE + "workload:\n  learner: {window: 10}\n  kalman: {r_pos: 2}\n")
    assert s.workload.learner == m.Learner(window=10)
    assert s.workload.kalman == m.Kalman(r_pos=2.0)
    assert s.workload.fusion == m.Fusion()
    assert s.workload.dataset == "synthetic"


def test_record_pcap_names_links_or_all() -> None:
    s = loads(BASE + "record: {pcap: [gnb1-core1]}\n")
    assert s.record.pcap == ("gnb1-core1",)
    assert s.record.pcap_links(["gnb1-core1", "av1-gnb1"]) == ["gnb1-core1"]
    every = loads(BASE + "record: {pcap: all}\n").record
    assert every.pcap_links(["gnb1-core1", "av1-gnb1"]) == ["gnb1-core1", "av1-gnb1"]
    assert loads(BASE).record.pcap_links(["av1-gnb1"]) == []


def test_the_ekf_fusion_is_chosen_by_method_and_reaches_the_replay() -> None:
    from testbed.replay import replay_config

    s = loads(BASE + "workload:\n  fusion: {method: ekf, robust: null}\n")
    assert s.workload.fusion == m.Fusion(method="ekf", robust_c=None)
    cfg = replay_config(s)
    assert (cfg.fusion_method, cfg.robust_c) == ("ekf", None)
    assert type(cfg.build_fuser()).__name__ == "DelayedEkf"


def test_the_centred_robust_weight_reaches_the_fuser_and_the_report() -> None:
    from testbed.replay import replay_config

    s = loads(BASE + "workload:\n  fusion: {robust_centre: 1500ms}\n")
    assert s.workload.fusion == m.Fusion(robust_centre_s=1.5)  # robust keeps its default 2
    cfg = replay_config(s)
    assert (cfg.robust_c, cfg.robust_centre_s) == (2.0, 1.5)
    assert cfg.build_fuser()._recent.window_s == 1.5  # type: ignore[union-attr]
    assert "from the last 1.5 s' mean innovation (BEYOND THE PAPER)" in cfg.describe_fusion()


def test_the_confidence_weight_reads_the_calibration_beside_the_weights(tmp_path: Path) -> None:
    """`fusion.confidence` reaches the fuser with the committed weights' calibration; weights
    of one's own without a calibration beside them are refused at the field, with the command
    that writes one."""
    from nodes.edgeloc.fusion import ConfidenceWeight
    from nodes.edgeloc.settings import confidence_file
    from testbed.replay import replay_config

    s = loads(BASE + "workload:\n  fusion: {confidence: true}\n")
    assert s.workload.fusion == m.Fusion(confidence=True)
    cfg = replay_config(s)
    assert cfg.confidence == ConfidenceWeight.read(confidence_file(None))
    assert cfg.build_fuser().confidence == cfg.confidence  # type: ignore[union-attr]
    assert "entropy" in cfg.describe_fusion() and "(BEYOND THE PAPER)" in cfg.describe_fusion()
    assert replay_config(loads(BASE)).confidence is None
    (tmp_path / "own.pt").write_bytes(b"weights")
    text = BASE + "workload:\n  weights: own.pt\n  fusion: {confidence: true}\n"
    (tmp_path / "s.yaml").write_text(text)
    with pytest.raises(ScenarioError) as err:
        load(tmp_path / "s.yaml")
    issue = err.value.issues[0]
    assert issue.path == "workload.fusion.confidence"
    assert "--calibrate --out" in str(err.value) and str(tmp_path) in str(err.value)


def test_loading_never_constructs_arbitrary_tags(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    text = BASE + f'x-evil: !!python/object/apply:os.system ["touch {marker}"]\n'
    loads(text)  # an extension key: ignored, and never constructed
    assert not marker.exists()
    with pytest.raises(ScenarioError, match="a value tagged"):
        loads(BASE + f'seed: !!python/object/apply:os.system ["touch {marker}"]\n')
    assert not marker.exists()


def test_report_link_test_names_the_links_a_run_measures(tmp_path: Path) -> None:
    text = (SCENARIOS / "smoke.yaml").read_text()
    assert "link_test: false" in text
    names = ["av1-gnb1", "gnb1-upf1", "upf1-edge1"]
    for value, tested in (("[upf1-edge1, av1-gnb1]", ["av1-gnb1", "upf1-edge1"]),
                          ("true", names), ("false", [])):  # fmt: skip
        file = tmp_path / f"{len(tested)}.yaml"
        file.write_text(text.replace("link_test: false", f"link_test: {value}"))
        scenario = load(file)
        assert scenario.links.names() == names
        assert scenario.report.link_test_links(scenario.links.names()) == tested
