"""A vehicle's route sets its radio (`testbed.mobility`): sites, the channel's samples against
TR 38.901's closed forms, link adaptation, the `set` events the timeline gets, traces, seeds,
the replay following them, and `validate`'s coverage notes. Bad input:
tests/bad_scenarios/channel_*.yaml."""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from netem.nr.channel import CQI_SINR_DB, bler, cqi_from_sinr, mcs_from_cqi
from netem.nr.radio import RADIO_PROFILES
from testbed import mobility
from testbed.cli import app
from testbed.scenario import load, loads
from testbed.scenario.model import SetEvent

OAI = RADIO_PROFILES["oai-tdd-30k"]  # 106 PRBs at 30 kHz: a 40 MHz carrier

SCENARIO = """\
name: drive
seed: {seed}
duration: {duration}
topology:
  cells:
    - {{gnb: gnb1, upf: upf1, edge: edge1, site: {site1}}}
{more_cells}  vehicles:
    - {{name: av1, gnb: gnb1}}
links:
  air:
    radio: oai-tdd-30k
channel: {channel}
timeline:
{timeline}
"""


def _load(
    *,
    seed: int = 7,
    duration: str = "30s",
    site1: str = "auto",
    more_cells: str = "",
    channel: str = "{model: uma}",
    timeline: str = "  []",
    base_dir: Path | None = None,
):  # type: ignore[no-untyped-def]
    text = SCENARIO.format(
        seed=seed,
        duration=duration,
        site1=site1,
        more_cells=more_cells,
        channel=channel,
        timeline=timeline,
    )
    return loads(text, base_dir=base_dir)


def _straight(speed: float = 10.0, seconds: float = 40.0, y: float = 0.0) -> mobility.Route:
    """A vehicle driving along the x axis from x = 0 at `speed`."""
    t = np.arange(0.0, seconds + 0.05, 0.05)
    return mobility.Route(t, speed * t, np.full_like(t, y), np.zeros_like(t))


def _uma_los_db(d2d: float, h_bs: float = 25.0, h_ut: float = 1.5, fc: float = 3.5) -> float:
    """TR 38.901 Table 7.4.1-1, UMa LOS, written out here from the table."""
    d3d = math.sqrt(d2d**2 + (h_bs - h_ut) ** 2)
    d_bp = 4 * (h_bs - 1) * (h_ut - 1) * fc * 1e9 / 3e8
    if d2d <= d_bp:
        return 28 + 22 * math.log10(d3d) + 20 * math.log10(fc)
    return (
        28 + 40 * math.log10(d3d) + 20 * math.log10(fc)
        - 9 * math.log10(d_bp**2 + (h_bs - h_ut) ** 2)
    )  # fmt: skip


def test_the_samples_follow_tr_38901_s_closed_form_both_ways() -> None:
    # One site 30 m off a straight road; LOS everywhere and no shadowing: every sample is
    # the closed form's: RSRP = P - 10 log10(12 N_PRB) - PL; downlink SNR against kT B + 9 dB,
    # uplink 23 dBm against kT B + 5 dB.
    scenario = _load(site1="{x: 200, y: 30}", channel="{model: uma, los: los, shadowing: false}")
    plan = mobility.plans(scenario, _straight())["av1"]
    assert len(plan.steps) == 3000 and plan.steps[1].t == pytest.approx(0.01)
    bandwidth_hz = 40e6  # 106 PRBs at 30 kHz (TS 38.101-1 Table 5.3.2-1)
    noise_ue = -174 + 10 * math.log10(bandwidth_hz) + 9
    noise_gnb = -174 + 10 * math.log10(bandwidth_hz) + 5
    for s in plan.steps[::97]:
        pl = _uma_los_db(math.hypot(s.x - 200, s.y - 30))
        rsrp = 46 - 10 * math.log10(12 * 106) - pl
        assert s.rsrp_dbm == pytest.approx(rsrp, abs=1e-9)
        assert s.sinr_db == pytest.approx(46 - pl - noise_ue, abs=1e-9)
        assert s.ul_sinr_db == pytest.approx(23 - pl - noise_gnb, abs=1e-9)
    # Closest at x = 200 (t = 20 s): the best SINR there, worse on both sides.
    best = max(plan.steps, key=lambda s: s.sinr_db)
    assert best.t == pytest.approx(20.0, abs=0.01)


def test_link_adaptation_filters_the_sinr_with_its_time_constant() -> None:
    la = mobility.LinkAdaptation(time_constant_s=0.2)
    la.step(0.0, 0.0)
    for k in range(1, 21):  # a 10 dB step at t = 0+, sampled every 10 ms for 0.2 s
        cqi, mcs, b = la.step(k * 0.01, 10.0)
    assert la.sinr_db == pytest.approx(10.0 * (1 - math.exp(-1.0)), rel=1e-9)
    assert cqi == cqi_from_sinr(la.sinr_db) and mcs == mcs_from_cqi(cqi)
    assert 0.0 < b <= 0.1  # the CQI's own threshold gives 10% at most
    far = mobility.LinkAdaptation()
    assert far.step(0.0, -30.0)[1:] == (0, mobility.MAX_BLER)  # out of coverage: MCS 0, capped


def test_the_mcs_falls_as_the_vehicle_drives_away_from_the_site() -> None:
    scenario = _load(site1="{x: 0, y: 20}", channel="{model: uma, los: nlos, shadowing: false}")
    plan = mobility.plans(scenario, _straight(speed=50.0))["av1"]  # 1.5 km in 30 s
    mcs = [s.mcs for s in plan.steps]
    assert mcs[0] > 15 and mcs[-1] == 0
    assert all(b <= a for a, b in itertools.pairwise(mcs))  # never up, driving away
    ul = [s.ul_mcs for s in plan.steps]
    assert all(b <= a for a, b in itertools.pairwise(ul)) and ul[0] > ul[-1]


def test_the_timeline_gets_one_set_event_per_change_with_the_plan_s_values() -> None:
    scenario = _load(site1="{x: 0, y: 20}", channel="{model: uma, los: nlos, shadowing: false}")
    scenario = mobility.with_channel(scenario, _straight())
    plan = mobility.plans(scenario, _straight())["av1"]
    link = scenario.links.get("av1-gnb1")
    for direction in ("uplink", "downlink"):
        changes = plan.changes(direction)
        events = [
            e for e in scenario.timeline if isinstance(e, SetEvent) and e.direction == direction
        ]
        assert all(e.origin == "channel" and e.link == "av1-gnb1" for e in events)
        assert [(e.at_s, e.changes["radio"].mcs, e.changes["radio"].bler) for e in events] == [
            (t, m, b) for t, m, b in changes[1:]
        ]
        start = link.profile(direction).radio
        assert (start.mcs, start.bler) == changes[0][1:]
        # Only the MCS and BLER move: the rest is the file's radio.
        assert all(
            dataclasses.replace(e.changes["radio"], mcs=OAI.mcs, bler=OAI.bler) == OAI
            for e in events
        )
        # An event wherever the MCS or the BLER level moves, and nowhere else.
        steps = {round(s.t, 6): s for s in plan.steps}
        for e in events:
            s = steps[round(e.at_s, 6)]
            assert e.changes["radio"].mcs == (s.mcs if direction == "downlink" else s.ul_mcs)
    assert 10 < len(scenario.timeline) < 600


def test_a_timeline_radio_change_keeps_its_fields_and_takes_the_channel_s_mcs() -> None:
    scenario = _load(
        site1="{x: 0, y: 20}",
        channel="{model: uma, los: nlos, shadowing: false}",
        timeline="  - {at: 10s, set: av1-gnb1, direction: both, radio: {prbs: 51}, delay: 3ms}",
    )
    scenario = mobility.with_channel(scenario, _straight())
    mine = [e for e in scenario.timeline if isinstance(e, SetEvent) and e.origin == "timeline"]
    assert sorted(e.direction for e in mine) == ["downlink", "uplink"]  # `both`, split
    plan = mobility.plans(scenario, _straight())["av1"]
    at10 = next(s for s in plan.steps if s.t >= 10.0 - 1e-9)
    for e in mine:
        radio = e.changes["radio"]
        assert radio.n_prb == 51 and e.changes["delay_s"] == pytest.approx(0.003)
        before = [c for c in plan.changes(e.direction) if c[0] <= 10.0 + 1e-9][-1]
        assert (radio.mcs, radio.bler) == before[1:]
    later = [e for e in scenario.timeline if isinstance(e, SetEvent) and e.origin == "channel"]
    assert all(e.changes["radio"].n_prb == (51 if e.at_s >= 10.0 else 106) for e in later)
    assert at10.t == pytest.approx(10.0)


def test_same_seed_same_radio_another_seed_another() -> None:
    a, b, c = _load(seed=3), _load(seed=3), _load(seed=4)
    assert a.timeline == b.timeline and a.links == b.links
    assert a.timeline != c.timeline
    # Giving a loaded scenario another seed (as `sweep --seeds` does) redoes its radio.
    again = mobility.with_channel(dataclasses.replace(a, seed=4))
    assert again.timeline == c.timeline and again.links == c.links


def test_auto_sites_stand_abeam_the_route_at_their_share_of_the_run() -> None:
    route = _straight()
    scenario = _load(
        duration="40s",
        more_cells="    - {gnb: gnb2, upf: upf1, edge: edge1, site: auto}\n",
    )
    sites = mobility.sites(scenario, route)
    # Driving +x, the right-hand side is -y: 10 s and 30 s into a 40 s run, 25 m off.
    assert [(s.name, s.x, s.y) for s in sites] == [
        ("gnb1", pytest.approx(100.0), pytest.approx(-25.0)),
        ("gnb2", pytest.approx(300.0), pytest.approx(-25.0)),
    ]
    assert all(s.bandwidth_mhz == 40 for s in sites)


def test_the_synthetic_drive_is_the_route(tmp_path: Path) -> None:
    from nodes.edgeloc.dataset import SyntheticDataset

    scenario = _load(seed=5)
    route = mobility.Route.of_workload(scenario.workload, 5, scenario.duration_s)
    from nodes.ros.common import DATASET_MARGIN_S

    ds = SyntheticDataset(5, 20.0, scenario.duration_s + DATASET_MARGIN_S)
    x, y, _ = route.at(ds.timestamps[100])
    assert (x, y) == (pytest.approx(ds.gt_poses[100, 0]), pytest.approx(ds.gt_poses[100, 1]))


def test_a_recorded_radio_trace_plays_its_own_mcs(tmp_path: Path) -> None:
    (tmp_path / "drive.csv").write_text(
        "time_s,ue,rsrp_dbm,sinr_db,mcs\n"
        "0.0,av1,-80,20.0,22\n"
        "5.0,av1,-95,5.0,9\n"
        "12.5,av1,-110,-8.0,0\n"
    )
    scenario = _load(
        site1="{x: 0, y: 0}", channel="{trace: drive.csv}", duration="20s", base_dir=tmp_path
    )
    assert scenario.channel is not None and scenario.channel.trace == tmp_path / "drive.csv"
    for direction in ("uplink", "downlink"):
        events = [e for e in scenario.timeline if e.direction == direction]
        assert [(e.at_s, e.changes["radio"].mcs) for e in events] == [(5.0, 9), (12.5, 0)]
        assert scenario.links.get("av1-gnb1").profile(direction).radio.mcs == 22
        # The BLER is the trace's MCS's at the trace's SINR.
        assert events[-1].changes["radio"].bler == pytest.approx(bler(0, -8.0), rel=1e-3)
        assert events[0].changes["radio"].bler == pytest.approx(bler(9, 5.0), rel=1e-3)


def test_the_replay_s_air_hop_runs_at_the_channel_s_mcs() -> None:
    from testbed.replay import replay_config
    from testbed.replay.path import _PathPlan

    scenario = _load(site1="{x: 0, y: 20}", channel="{model: uma, los: nlos, shadowing: false}")
    plan = mobility.plans(scenario)["av1"]
    path = _PathPlan(scenario, None)
    for t in (0.0, 7.3, 21.05, 29.9):
        up, down = path.states_at(t)
        step = [s for s in plan.steps if s.t <= t + 1e-9][-1]
        expect = [c for c in plan.changes("uplink") if c[0] <= t + 1e-9][-1]
        assert up.air is not None and up.air.radio.mcs == expect[1] == step.ul_mcs
        assert down.air is not None
    # The channel's changes are not the learner's phases: the run is one phase.
    assert replay_config(scenario).phases == (0.0,)


def test_validate_counts_the_radio_changes_and_notes_a_route_out_of_coverage(
    tmp_path: Path,
) -> None:
    far = tmp_path / "far.yaml"
    far.write_text(
        SCENARIO.format(
            seed=1,
            duration="20s",
            site1="{x: 20000, y: 20000}",
            more_cells="",
            channel="{model: uma}",
            timeline="  []",
        )
    )
    near = tmp_path / "near.yaml"
    near.write_text(far.read_text().replace("{x: 20000, y: 20000}", "auto"))
    result = CliRunner().invoke(app, ["validate", str(far), str(near)])
    assert result.exit_code == 0, result.output
    out = " ".join(result.output.split())
    assert "av1's route never reaches its cell's coverage" in out
    assert f"below CQI 1's {CQI_SINR_DB[0]:g} dB" in out
    n = sum(e.origin == "channel" for e in load(near).timeline)
    assert f"0 timeline event(s), {n} radio change(s) from the channel" in out


def test_two_vehicles_on_two_sited_cells_each_get_their_own_radio() -> None:
    scenario = loads(
        "name: two\nseed: 2\nduration: 20s\n"
        "topology:\n  cells:\n"
        "    - {gnb: gnb1, core: core1, site: {x: 0, y: 20}}\n"
        "    - {gnb: gnb2, core: core2, site: {x: 400, y: 20}}\n"
        "  vehicles:\n    - {name: av1, gnb: gnb1}\n    - {name: av2, gnb: gnb2}\n"
        "links:\n  air: {radio: oai-tdd-30k}\n"
        "channel: {model: uma, los: los, shadowing: false}\n"
    )
    route = _straight(seconds=25.0)  # 0 -> 250 m: away from gnb1, towards gnb2
    found = mobility.plans(scenario, route)
    one, two = found["av1"], found["av2"]
    assert (one.link, two.link) == ("av1-gnb1", "av2-gnb2")
    assert {s.serving for s in one.steps} == {"gnb1"} and {s.serving for s in two.steps} == {"gnb2"}
    # The other site interferes: av1's SINR falls and av2's rises along the road.
    assert one.steps[0].sinr_db > one.steps[-1].sinr_db
    assert two.steps[0].sinr_db < two.steps[-1].sinr_db
    timed = mobility.with_channel(scenario, route)
    links = {e.link for e in timed.timeline}
    assert links == {"av1-gnb1", "av2-gnb2"}


def _fake_ros(monkeypatch: pytest.MonkeyPatch) -> None:
    """Message classes and a serializer that stand in for ROS 2's: what the /radio/* part is
    made of, without rclpy."""
    import sys
    import types

    class Message:
        def __init__(self, **fields: object) -> None:
            self.__dict__.update(fields)

    fakes = {
        "edgeloc_interfaces.msg": {"RadioState": Message},
        "builtin_interfaces.msg": {"Time": Message},
        "rclpy.serialization": {"serialize_message": lambda msg: b"\0"},
    }
    for name, attrs in fakes.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, module)


def test_a_run_computes_its_channel_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The channel (`mobility.plans`, the whole simulation) runs once per run, at load: the
    timeline's start (coverage notes) and the /radio/* part use the plans the loaded scenario
    carries."""
    from mcap.reader import make_reader

    from testbed import recording
    from testbed.recording import Recording
    from testbed.run import play_timeline
    from testbed.topology import build

    calls: list[str] = []
    simulate = mobility.plans

    def counted(scenario, route=None):  # type: ignore[no-untyped-def]
        calls.append(scenario.name)
        return simulate(scenario, route)

    monkeypatch.setattr(mobility, "plans", counted)
    monkeypatch.setattr(recording, "host_capabilities", lambda reason: {})
    _fake_ros(monkeypatch)
    scenario = _load(duration="1s")
    assert calls == ["drive"]

    class Links:  # the timeline's link changes land nowhere; nothing dies
        def __getattr__(self, name: str) -> object:
            return lambda *args, **kwargs: None

    net = build(scenario, dry_run=True)
    lines: list[str] = []
    run = Recording(net, tmp_path, "userspace (test)", lines.append)
    net.control = Links()  # type: ignore[assignment]
    player = play_timeline(net, tmp_path, lines.append)
    run.record_radio(player.started_epoch_s, ros_ok=True)
    with open(tmp_path / "parts" / "radio.mcap", "rb") as f:
        topics = {channel.topic for _, channel, _ in make_reader(f).iter_messages()}
    assert topics == {"/radio/av1"}
    assert calls == ["drive"]


def test_a_loaded_scenario_carries_its_plans_and_one_made_from_it_does_not() -> None:
    scenario = _load(duration="5s")
    carried = scenario.radio_plans
    assert carried is not None and mobility.plans_of(scenario) is carried
    assert carried == mobility.plans(scenario)  # the radio the channel gave changes none
    other = dataclasses.replace(scenario, seed=8)  # another seed, another channel
    assert other.radio_plans is None
    assert mobility.plans_of(other) == mobility.plans(other) != carried
