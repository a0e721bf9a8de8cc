"""Handovers from the route (`channel.handover`): event A3 on the channel's per-site RSRP
hands the vehicle over where the closed form of TR 38.901's path loss says, the timeline gets
a `handover` event there, each air link carries the radio of the steps its cell serves, the
replay follows the serving cell, and the same seed gives the same handovers."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from testbed import mobility
from testbed.replay.path import _PathPlan
from testbed.scenario import loads
from testbed.scenario.model import HandoverEvent, Scenario, SetEvent
from tests.test_mobility import _straight, _uma_los_db

SPEED = 10.0  # m/s along the x axis
SITES = ((100.0, 30.0), (500.0, 30.0))

SCENARIO = """\
name: two-cells
seed: {seed}
duration: 60s
topology:
  cells:
    - {{gnb: gnb1, upf: upf1, edge: edge1, site: {{x: {x1}, y: {y1}}}}}
    - {{gnb: gnb2, upf: upf1, edge: edge1, site: {{x: {x2}, y: {y2}}}}}
  vehicles:
    - {{name: av1, gnb: gnb1}}
links:
  air:
    radio: oai-tdd-30k
channel:
  model: uma
  los: {los}
  shadowing: {shadowing}
  handover: {handover}
"""


def _load(
    handover: str = "{offset: 3, hysteresis: 1, ttt: 320ms, filter: 0}",
    seed: int = 7,
    los: str = "los",
    shadowing: bool = False,
) -> Scenario:
    (x1, y1), (x2, y2) = SITES
    text = SCENARIO.format(
        seed=seed, x1=x1, y1=y1, x2=x2, y2=y2, los=los,
        shadowing=str(shadowing).lower(), handover=handover,
    )  # fmt: skip
    return loads(text)


def _a3_point(margin_db: float) -> float:
    """Where along the x axis the second site's RSRP first exceeds the first's by
    `margin_db` (offset + hysteresis): the same power and mast, so where the first's path
    loss exceeds the second's by it; bisection on the table's formula."""

    def excess(x: float) -> float:
        d1 = math.hypot(x - SITES[0][0], SITES[0][1])
        d2 = math.hypot(x - SITES[1][0], SITES[1][1])
        return _uma_los_db(d1) - _uma_los_db(d2) - margin_db

    lo, hi = SITES[0][0], SITES[1][0]
    assert excess(lo) < 0 < excess(hi)
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if excess(mid) < 0 else (lo, mid)
    return hi


def test_the_handover_happens_where_a3_s_closed_form_says() -> None:
    scenario = _load()
    route = _straight(SPEED, 60.0)
    plan = mobility.plans(scenario, route)["av1"]
    [decision] = plan.handovers
    assert (decision.source, decision.target) == ("gnb1", "gnb2")
    # A3 enters at the first step past the point, and triggers TTT later (no L3 filter).
    want = _a3_point(3.0 + 1.0) / SPEED + 0.32
    step = scenario.channel.step_s  # type: ignore[union-attr]
    assert abs(decision.t - want) <= step + 1e-9, (decision.t, want)
    # The target serves from the next step on; before it, the source.
    served = [(s.t, s.serving) for s in plan.steps]
    assert all(c == "gnb1" for t, c in served if t <= decision.t)
    assert all(c == "gnb2" for t, c in served if t > decision.t)


def test_the_l3_filter_and_a_longer_ttt_hand_over_later() -> None:
    route = _straight(SPEED, 60.0)
    base = mobility.plans(_load(), route)["av1"].handovers[0].t
    filtered = _load("{offset: 3, hysteresis: 1, ttt: 320ms, filter: 4}")
    longer = _load("{offset: 3, hysteresis: 1, ttt: 640ms, filter: 0}")
    assert mobility.plans(filtered, route)["av1"].handovers[0].t > base + 0.05
    assert mobility.plans(longer, route)["av1"].handovers[0].t == pytest.approx(
        base + 0.32, abs=0.011
    )


def test_the_timeline_gets_the_handover_and_each_link_its_cell_s_radio() -> None:
    scenario = mobility.with_channel(_load(), _straight(SPEED, 60.0))
    [event] = [e for e in scenario.timeline if isinstance(e, HandoverEvent)]
    assert (event.vehicle, event.source, event.target) == ("av1", "gnb1", "gnb2")
    assert (event.interruption_s, event.lossless) == (0.04, True)
    assert (event.source_link, event.target_link) == ("av1-gnb1", "av1-gnb2")
    radio = [e for e in scenario.timeline if isinstance(e, SetEvent) and e.origin == "channel"]
    on_first = [e.at_s for e in radio if e.link == "av1-gnb1"]
    on_second = [e.at_s for e in radio if e.link == "av1-gnb2"]
    assert on_first and on_second
    # The source's link changes while it serves; the target's only after the handover
    # (its first serving step's radio is the link's start).
    assert max(on_first) <= event.at_s < min(on_second)
    plan = mobility.plans(scenario, _straight(SPEED, 60.0))["av1"]
    first_served = next(s for s in plan.steps if s.serving == "gnb2")
    start = scenario.links.get("av1-gnb2").uplink.radio
    assert start is not None and start.mcs == first_served.ul_mcs


def test_same_seed_same_handovers_another_seed_others() -> None:
    def times(seed: int) -> list[float]:
        scenario = _load("{}", seed=seed, los="auto", shadowing=True)
        scenario = mobility.with_channel(scenario, _straight(SPEED, 60.0))
        return [e.at_s for e in scenario.timeline if isinstance(e, HandoverEvent)]

    assert times(3) == times(3)
    assert times(3) and times(3) != times(4)


def test_with_channel_again_replaces_the_handovers() -> None:
    scenario = _load()
    again = mobility.with_channel(scenario)
    assert again.timeline == scenario.timeline  # the channel's radio changes, not twice
    # and a route that hands over: its one handover, not two
    first = mobility.with_channel(_load(), _straight(SPEED, 60.0))
    second = mobility.with_channel(first, _straight(SPEED, 60.0))
    assert sum(isinstance(e, HandoverEvent) for e in first.timeline) == 1
    assert second.timeline == first.timeline


def test_the_replay_follows_the_serving_cell_and_stalls_for_the_interruption() -> None:
    scenario = mobility.with_channel(_load("{interruption: 100ms}"), _straight(SPEED, 60.0))
    [event] = [e for e in scenario.timeline if isinstance(e, HandoverEvent)]
    plan = _PathPlan(scenario, None)
    before, _ = plan.states_at(event.at_s - 0.001)
    during, _ = plan.states_at(event.at_s + 0.05)
    after, _ = plan.states_at(event.at_s + 0.1)
    assert before.up and not during.up and after.up
    assert event.at_s + 0.1 in plan.breakpoints(60.0)
    # After the handover the air hop is the target link's, at its radio.
    air = scenario.links.get("av1-gnb2")
    assert after.air is not None
    radio_events = [
        e for e in scenario.timeline
        if isinstance(e, SetEvent) and e.link == "av1-gnb2" and e.direction == "uplink"
        and e.at_s <= event.at_s + 0.1
    ]  # fmt: skip
    want = radio_events[-1].changes["radio"] if radio_events else air.uplink.radio
    assert after.air.radio == want


def test_the_run_s_plan_gives_every_vehicle_a_link_to_every_gnb() -> None:
    from ipaddress import IPv4Network

    from testbed.topology import plan

    net = plan(_load(), "abc123", IPv4Network("10.99.0.0/24"))
    assert set(net.links) == {"av1-gnb1", "av1-gnb2", "gnb1-upf1", "gnb2-upf1", "upf1-edge1"}
    # Its UE address and first route are the first cell's, as without handovers.
    [route] = net["av1"].routes
    assert route.dev == "gnb1"
    assert list(net["av1"].interfaces) == ["gnb1", "gnb2"]


def test_validate_counts_the_handovers(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from testbed.cli import app

    (x1, y1), (x2, y2) = SITES
    path = tmp_path / "two.yaml"
    text = SCENARIO.format(
        seed=7, x1=x1, y1=y1, x2=x2, y2=y2, los="auto", shadowing="true", handover="{}"
    )
    # Sites along the synthetic drive (the fixed ones stand by the straight test route).
    path.write_text(
        text.replace(f"{{x: {x1}, y: {y1}}}", "auto").replace(f"{{x: {x2}, y: {y2}}}", "auto")
    )
    result = CliRunner().invoke(app, ["validate", str(path)])
    assert result.exit_code == 0, result.output
    from testbed.scenario import load

    n = sum(isinstance(e, HandoverEvent) for e in load(path).timeline)
    assert n >= 1
    assert f"{n} handover(s)" in result.output and "0 timeline event(s)" in result.output


def test_a_cell_no_vehicle_starts_on_has_its_air_links_bandwidth() -> None:
    """RSRP is per resource element: a target cell measured at another bandwidth than its
    links' would be 6 dB off and hand over elsewhere."""
    scenario = loads(
        SCENARIO.format(
            seed=7, x1=100, y1=30, x2=500, y2=30, los="los", shadowing="false", handover="{}"
        ).replace("radio: oai-tdd-30k", "radio: {profile: oai-tdd-30k, prbs: 24}")
    )
    sites = mobility.sites(scenario, _straight(SPEED, 60.0))
    assert [s.bandwidth_mhz for s in sites] == [10, 10]


def test_the_replay_reports_the_learner_and_edgeloc_around_each_handover(
    tmp_path: Path,
) -> None:
    from testbed.replay import replay_scenario
    from testbed.scenario import load

    repo = Path(__file__).resolve().parents[1]
    text = (repo / "scenarios" / "drive_two_cells.yaml").read_text()
    short = tmp_path / "drive.yaml"
    short.write_text(text.replace("duration: 90s", "duration: 12s"))
    scenario = load(short)
    [event] = [e for e in scenario.timeline if isinstance(e, HandoverEvent)]
    done = replay_scenario(scenario, tmp_path / "runs", compare=False)
    [h] = done.summary["radio"]["handovers"]
    assert (h["t_s"], h["source"], h["target"]) == (event.at_s, "gnb1", "gnb2")
    before, after = h["around"]["before"], h["around"]["after"]
    plays = done.summary["learner"]["decisions"]["sent_s"]
    assert before["plays"] == sum(event.at_s - 3 <= t < event.at_s for t in plays) > 0
    assert after["plays"] == sum(event.at_s <= t < event.at_s + 3 for t in plays) > 0
    assert before["mean_error_m"] > 0 and after["mean_ul_mcs"] is not None


def test_the_learner_leaves_the_camera_frame_at_the_cell_edge_and_takes_it_again_after(
    tmp_path: Path,
) -> None:
    """#19 item 6 on the replay of scenarios/drive_two_cells.yaml (its 90 s, ~7 s here): where
    the uplink MCS falls at the first cell edge the learner sends a smaller split than the
    camera frame, and after the uplink has recovered it sends the frame again."""
    from testbed.replay import replay_scenario
    from testbed.scenario import load

    repo = Path(__file__).resolve().parents[1]
    scenario = load(repo / "scenarios" / "drive_two_cells.yaml")
    done = replay_scenario(scenario, tmp_path / "runs", compare=False)
    bands = {tuple(b["mcs"]): b for b in done.summary["radio"]["by_uplink_mcs"]}
    good, mid, edge = bands[(20, 28)], bands[(10, 19)], bands[(0, 9)]
    assert edge["plays"] >= 40 and mid["plays"] >= 40  # long enough for the learner to act
    assert max(good["share"], key=good["share"].get) == "image"
    assert max(edge["share"], key=edge["share"].get) != "image"
    for weak in (edge, mid):
        assert weak["mean_payload_bytes"] < 0.5 * good["mean_payload_bytes"], weak

    # In time: before the first cell edge, in it, and once the uplink has recovered for good.
    steps = mobility.plans(scenario)["av1"].steps
    step_s = scenario.channel.step_s  # type: ignore[union-attr]
    mcs = [s.ul_mcs for s in steps]
    first = next(k for k, m in enumerate(mcs) if m <= 9)
    window = round(10.0 / step_s)  # recovered for good: MCS >= 20 for the next 10 s
    back = next(k for k in range(first, len(mcs)) if min(mcs[k : k + window]) >= 20)
    falls, recovered = steps[first].t, steps[back].t
    decisions = done.summary["learner"]["decisions"]
    plays = list(zip(decisions["sent_s"], decisions["split"], strict=True))

    def image_share(a: float, b: float) -> float:
        inside = [split for t, split in plays if a <= t < b]
        assert len(inside) >= 20, (a, b, len(inside))
        return sum(split == "image" for split in inside) / len(inside)

    def ul_mcs(t: float) -> int:  # the uplink MCS a play was sent at
        return mcs[min(len(mcs) - 1, int(t / step_s))]

    at_edge = [split for t, split in plays if falls <= t < recovered and ul_mcs(t) <= 9]
    before, after = image_share(falls - 15.0, falls), image_share(recovered + 3.0, recovered + 18.0)
    at_edge_share = sum(split == "image" for split in at_edge) / len(at_edge)
    print(
        f"\nuplink MCS <= 9 from {falls:.2f} s, >= 20 for good from {recovered:.2f} s; image"
        f" share: {before:.0%} in the 15 s before, {at_edge_share:.0%} of the {len(at_edge)}"
        f" plays at MCS <= 9 in between, {after:.0%} from 3 to 18 s after"
    )
    for band in (edge, mid, good):
        print(
            f"MCS {band['mcs'][0]}-{band['mcs'][1]}: {band['plays']} plays,"
            f" {band['mean_payload_bytes'] / 1000:.1f} kB per request,"
            f" image {band['share'].get('image', 0.0):.0%}"
        )
    assert len(at_edge) >= 20
    assert before >= 0.5
    assert at_edge_share <= 0.3
    # The learner takes ~3 s (its window and change detector) to trust the frame again.
    assert after >= 0.6
