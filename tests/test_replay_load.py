"""The replay under cross-traffic (issues #16 and #18): `traffic:` flows of other UEs in a
vehicle's NR cell take their share of its PRBs, flows on its path take rate off the wired hops.

The share is checked against the shared cell a real run plays (`netem.nr.cell.Cell` with the
other UEs' `Slots` stages saturated), and `loaded_cell.yaml`'s replay against its phases.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from netem.nr.cell import Cell
from netem.nr.radio import RADIO_PROFILES
from netem.nr.ue import Slots
from netem.profile import LinkProfile
from netem.relay.direction import build_pipeline
from testbed.replay import RadioHop, cell_share, latency_model, wire_bps
from testbed.scenario import load
from testbed.scenario.model import Traffic
from tests.test_scenario_library import SCENARIOS


def test_cell_share_fills_water_like_the_rr_scheduler() -> None:
    assert cell_share(20e6, []) == 1.0
    assert cell_share(20e6, [30e6, 30e6, 30e6]) == pytest.approx(0.25)
    assert cell_share(20e6, [2e6]) == pytest.approx(0.9)  # a light UE keeps what it wants
    # 2 Mbit/s and two saturating UEs: the rest split in three.
    assert cell_share(20e6, [2e6, math.inf, math.inf]) == pytest.approx(18 / 3 / 20)


def test_wire_rate_counts_headers_and_the_on_off_duty_cycle() -> None:
    udp = Traffic("u", "udp", "a", "b", rate_bps=10e6, size=1200)
    assert wire_bps(udp) == pytest.approx(10e6 * 1228 / 1200)
    onoff = Traffic("o", "onoff", "a", "b", rate_bps=10e6, size=1200, on_s=1.0, off_s=3.0)
    assert wire_bps(onoff) == pytest.approx(wire_bps(udp) / 4)
    assert wire_bps(Traffic("t", "tcp", "a", "b")) == math.inf


def _stage(cell: Cell, seed: int) -> Slots:
    radio = RADIO_PROFILES["oai-tdd-30k"]
    slots = build_pipeline(LinkProfile(radio=radio, queue_packets=None), seed=seed).stage("slots")
    assert isinstance(slots, Slots)
    cell.join(slots)
    return slots


def test_a_message_beside_three_saturating_ues_takes_what_the_shared_cell_takes() -> None:
    """The replay's quarter of the PRBs against the real-run cell with three backlogged UEs:
    a 37 kB camera frame's delivery time, over 20 frames."""
    radio = RADIO_PROFILES["oai-tdd-30k"]
    hop = RadioHop(radio, "uplink", share=cell_share(radio.goodput_bps("uplink"), [1e9] * 3))
    rng = np.random.default_rng(1)
    frame = 37_000
    starts = [0.3 + 0.25 * k for k in range(20)]
    replayed = [hop.deliver(t, frame, rng) - t for t in starts]

    cell = Cell("rr")
    ours, *others = [_stage(cell, seed) for seed in range(4)]
    for s in others:  # backlogged all along
        for _ in range(6000):
            s.push(bytes(1228), 0.0)
    pending = {k: (t, frame) for k, t in enumerate(starts)}
    born: dict[int, int] = {}
    done: dict[int, float] = {}
    k = 0
    while len(done) < len(starts):
        due = min(d for s in (ours, *others) if (d := s.next_due()) is not None)
        if k < len(starts) and starts[k] <= due:
            left = frame
            while left > 0:
                p = bytes(min(left, 1472))
                born[id(p)] = k
                ours.push(p, starts[k])
                left -= len(p)
            k += 1
            continue
        for s in others:
            s.pop_ready(due)
        for p in ours.pop_ready(due):
            j = born[id(p)]
            pending[j] = (pending[j][0], pending[j][1] - len(p))
            if pending[j][1] <= 0:
                done[j] = due - pending[j][0]
    shared = [done[j] for j in range(len(starts))]
    alone = [RadioHop(radio, "uplink").deliver(t, frame, rng) - t for t in starts]
    print(
        f"37 kB frame: alone {np.median(alone) * 1e3:.1f} ms, replay with a quarter "
        f"{np.median(replayed) * 1e3:.1f} ms, shared cell {np.median(shared) * 1e3:.1f} ms"
    )
    assert np.median(shared) > 2.5 * np.median(alone)
    assert np.median(replayed) == pytest.approx(np.median(shared), rel=0.25)


def test_loaded_cell_replay_loads_av1s_uplink_only_while_the_background_ues_send() -> None:
    scenario = load(SCENARIOS / "loaded_cell.yaml")
    model = latency_model(scenario, vehicle="av1")
    capacity = RADIO_PROFILES["oai-tdd-30k"].goodput_bps("uplink")
    for t, share in ((10.0, 1.0), (30.0, 0.25), (50.0, 1.0)):
        air = model.uplink.at(t).air
        assert isinstance(air, RadioHop)
        assert air.share == pytest.approx(share), t
        assert air.rate_bps == pytest.approx(capacity * share, rel=0.03)
    assert model.downlink.at(30.0).air.share == 1.0  # type: ignore[union-attr]
