"""The replay on a 5G NR air link: its radio hop is the relay's slot model on a virtual clock."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from netem.nr.radio import Radio
from testbed.replay import ACTION_EXCHANGE, RadioHop, latency_model
from testbed.scenario import load

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def test_the_radio_hop_of_an_idle_ue_is_the_oracles_delay() -> None:
    radio = Radio(bler=0.1)
    hop = RadioHop(radio, "uplink")
    rng = np.random.default_rng(3)
    starts = rng.uniform(0.0, 100.0, 3000)
    delays = [hop.deliver(float(t), 92, rng) - t for t in starts]
    oracle = radio.oracle("uplink", size_bytes=92)
    assert np.mean(delays) == pytest.approx(oracle.mean(), abs=0.0003)
    assert np.median(delays) == pytest.approx(oracle.quantile(0.5), abs=0.0005)
    assert hop.rate_bps == pytest.approx(radio.goodput_bps("uplink"))


def test_out_of_coverage_a_message_is_lost_not_waited_for() -> None:
    """At BLER near 1 RLC-AM gives each packet up after its maxRetxThreshold resends: the
    hop says the message never arrives (before that bound a replay drove the slot model's
    virtual clock for days and never finished)."""
    hop = RadioHop(Radio(bler=0.999, mcs=0, n_prb=24), "uplink")
    rng = np.random.default_rng(4)
    assert hop.deliver(10.0, 38_000, rng) == math.inf
    fine = RadioHop(Radio(bler=0.1, mcs=0, n_prb=24), "uplink")
    assert 10.0 < fine.deliver(10.0, 38_000, rng) < 13.0


def test_a_message_beside_another_ues_in_the_cell_shares_its_slots() -> None:
    """`ContendedHop` (the `--against` model of a cell's other EdgeLoc vehicles): two UEs of
    one `rr` cell that each send a 37 kB frame at once finish together, about when one UE
    alone would have sent both frames (the cell's blocks are shared, not doubled); a
    neighbour's message far away in time changes nothing."""
    from testbed.replay import ContendedHop, OtherMessage

    radio = Radio(bler=0.0)
    alone = RadioHop(radio, "uplink")
    rng = np.random.default_rng(5)
    frame = 37_000
    t = 10.0
    one = alone.deliver(t, frame, rng) - t
    both = alone.deliver(t, 2 * frame, rng) - t
    shared = ContendedHop(alone, (OtherMessage("av2", t, frame, radio),))
    got = shared.deliver(t, frame, rng) - t
    period = radio.pattern().period_s
    assert got > one + period  # the other UE's frame took half of the PRBs
    assert abs(got - both) <= period, (one, both, got)
    far = ContendedHop(alone, (OtherMessage("av2", t + 5.0, frame, radio),))
    assert far.deliver(t, frame, rng) - t == pytest.approx(one)
    assert shared.rate_bps == alone.rate_bps


def test_against_a_run_the_other_vehicles_requests_share_the_cell(tmp_path: Path) -> None:
    """`testbed replay --against` on a shared cell: the other EdgeLoc vehicles' answered and
    lost requests become the messages beside this vehicle's in its uplink (their start plus
    their head compute, their radio at that time: av4's MCS 5 after 20 s), and only the
    radio hops of its path are shared."""
    from types import SimpleNamespace

    from netem.nr.radio import RADIO_PROFILES
    from reports.mcapread import Inference, VehicleData
    from testbed.replay import ContendedHop, compute_profile
    from testbed.replay.against import _cell_neighbours, _contended
    from testbed.replay.path import _PathPlan

    scenario = load(SCENARIOS / "multi_vehicle_nr.yaml")
    t0 = 1000.0
    vehicles = {}
    for k, name in enumerate(("av1", "av2", "av4")):
        vd = VehicleData(name)
        head = 0.002 * (k + 1)
        vd.inference = [
            Inference(t0 + t, t0 + t, i, "image", 0, 37_000, head, 0.01, 0.1, True, False, "")
            for i, t in enumerate((5.1, 25.1))
        ]
        vehicles[name] = vd
    data = SimpleNamespace(vehicles=vehicles, t0=t0)
    plan = _PathPlan(scenario, "av1")
    reference = compute_profile(scenario.workload.codec, None)
    others = _cell_neighbours(scenario, data, plan, reference, {"image": 37_000}, tmp_path)
    assert [o.ue for o in others] == ["av2", "av4", "av2", "av4"]  # by start, not av1
    av4 = [o for o in others if o.ue == "av4"]
    assert [o.radio.mcs for o in av4] == [RADIO_PROFILES["oai-tdd-30k"].mcs, 5]
    assert all(o.nbytes > 37_000 for o in others)  # headers on the wire
    assert all(5.0 < o.start_s < 5.2 for o in others[:2])
    model = latency_model(scenario, vehicle="av1")
    shared = _contended(model.uplink, others, plan.cell.scheduler)
    assert all(isinstance(st.air, ContendedHop) for st in shared.states)
    assert shared.times == model.uplink.times


def test_the_nr_cell_replay_pays_the_scheduling_request_and_the_cell_edge() -> None:
    model = latency_model(load(SCENARIOS / "nr_cell.yaml"))
    rng = np.random.default_rng(4)

    def mean_ms(split: str, t0: float, payload: int) -> float:
        ts = [model.timing(split, t0 + 0.1 * i, payload, rng).latency_s for i in range(40)]
        return 1000 * float(np.mean(ts))

    # Each uplink message of an idle UE waits for an SR and a grant: two TDD periods at least.
    assert mean_ms("vehicle", 1.0, 38) > 30
    # At the cell edge (MCS 5 on 51 PRBs, ~2.6 Mbit/s) a camera frame takes far longer than
    # with the good cell's blocks, while the pose-sized request barely changes.
    assert mean_ms("image", 31.0, 36_900) > mean_ms("image", 1.0, 36_900) + 80
    assert mean_ms("vehicle", 31.0, 38) == pytest.approx(mean_ms("vehicle", 1.0, 38), abs=5)
    # The phase rate a report prints is the radio's, not the backhaul's 1 Gbit/s.
    assert model.uplink.at(31.0).bottleneck_bps == pytest.approx(
        Radio(mcs=5, n_prb=51, bler=0.1).goodput_bps("uplink")
    )


def test_a_real_runs_latencies_are_set_beside_the_models_for_the_same_requests(
    tmp_path: Path,
) -> None:
    from reports.build import build_report
    from testbed.replay import latency_against_run
    from tests.test_report_splits import run_with_splits, write

    folder = write(tmp_path, run_with_splits())
    build_report(folder, formats=("json",), plots=False, splits=False)  # its summary.json
    agreement = latency_against_run(load(SCENARIOS / "nr_cell.yaml"), folder)
    rows = {a.split: a for a in agreement.rows}
    assert set(rows) == {"image", "conv3"}  # the splits the run played (lost ones left out)
    # No request without payload: the reference machine's overhead, and every split tested.
    assert agreement.calibrated is None and agreement.overhead_s == ACTION_EXCHANGE.overhead_s
    assert agreement.tested() == agreement.rows
    assert (agreement.neighbours, agreement.neighbour_requests) == (0, 0)  # one vehicle
    # The synthetic run answered image in 40 then 150 ms, and conv3 in 80 ms.
    assert 0.04 <= rows["image"].measured_s <= 0.15
    assert rows["conv3"].measured_s == pytest.approx(0.08, abs=1e-5)
    for a in rows.values():
        assert a.model_s > 0.03  # the radio's SR and grant rounds, in the model too
        assert a.ratio == pytest.approx(a.measured_s / a.model_s)

    # `testbed replay --against --json`: the same comparison, machine-readable
    from typer.testing import CliRunner

    from testbed.cli import app

    out = CliRunner().invoke(
        app, ["replay", str(SCENARIOS / "nr_cell.yaml"), "--against", str(folder), "--json"]
    )
    assert out.exit_code == 0, out.output
    printed = json.loads(out.stdout)
    assert printed == json.loads(json.dumps(agreement.to_dict()))
    assert {r["split"]: r["ratio"] for r in printed["rows"]} == pytest.approx(
        {s: a.ratio for s, a in rows.items()}
    )
    assert printed["worst"] == pytest.approx(agreement.worst())


def test_the_runs_compute_replaces_the_reference_where_the_run_answered() -> None:
    from types import SimpleNamespace

    from nodes.edgeloc.latency import ComputeProfile
    from testbed.replay import run_compute
    from testbed.replay.path import _PathPlan

    base = ComputeProfile(("image", "conv3"), (0.001, 0.002), (0.003, 0.004))
    scenario = load(SCENARIOS / "nr_cell.yaml")
    plan = _PathPlan(scenario, "av1")
    stretch = ComputeProfile.stretch(plan.vehicle.cpu), ComputeProfile.stretch(plan.cell.core_cpu)

    def answer(head: float, edge: float, ok: bool = True) -> SimpleNamespace:
        return SimpleNamespace(split="conv3", ok=ok, head_s=head, edge_compute_s=edge)

    requests = [answer(0.010, 0.020), answer(0.030, 0.040), answer(5.0, 5.0, ok=False)]
    got = run_compute(base, requests, plan, Path("runs/abc"))
    # conv3 as the run measured it (lost requests left out), back in one core's seconds
    assert got.head_core_s[1] * stretch[0] == pytest.approx(0.020)
    assert got.tail_core_s[1] * stretch[1] == pytest.approx(0.030)
    assert got.with_budgets(plan.vehicle.cpu, plan.cell.core_cpu).head_s("conv3") == pytest.approx(
        0.020
    )
    # image was never answered: the reference's
    assert (got.head_core_s[0], got.tail_core_s[0]) == (0.001, 0.003)
    assert "abc" in got.source
