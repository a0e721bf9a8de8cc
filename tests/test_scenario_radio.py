"""A scenario's radios, written in layers: `links.air.radio` for every air link, a direction's
or an override's mapping changing it, the cell's slot grid and carrier, and `set` events
changing the radio a link has at that time. Bad values: tests/bad_scenarios/radio_*.yaml."""

from __future__ import annotations

import random

import pytest

from netem.nr.radio import RADIO_PROFILES
from netem.profile import LinkProfile
from netem.stages import Delay
from testbed import links
from testbed.scenario import loads
from testbed.scenario.model import SetEvent

OAI, SRS, COMMERCIAL = (
    RADIO_PROFILES[n] for n in ("oai-tdd-30k", "srsran-lowlat", "commercial-midband")
)

TWO_UES = """\
name: radios
duration: 20s
topology:
  cells:
    - {{gnb: gnb1, core: core1{cell}}}
  vehicles:
    - {{name: av1, gnb: gnb1}}
    - {{name: av2, gnb: gnb1}}
links:
{links}
timeline:
{timeline}
"""


def _load(links_text: str, timeline: str = "  []", cell: str = ""):  # type: ignore[no-untyped-def]
    scenario = loads(TWO_UES.format(links=links_text, timeline=timeline, cell=cell))
    specs = {s.name: s for s in scenario.links.links}
    return scenario, specs


def test_one_key_puts_a_radio_on_both_directions_of_every_air_link() -> None:
    scenario, specs = _load("  air:\n    radio: srsran-lowlat")
    for name in ("av1-gnb1", "av2-gnb1"):
        assert specs[name].uplink.radio == SRS and specs[name].downlink.radio == SRS
    assert specs["gnb1-core1"].uplink.radio is None  # the backhaul stays a wire
    backend = links.choose_backend(scenario)
    assert backend.name == "userspace" and "NR radio" in backend.reason


def test_a_direction_and_an_override_change_the_radio_below_them() -> None:
    _, specs = _load(
        "  air:\n"
        "    radio: srsran-lowlat\n"
        "    uplink: {radio: {mcs: 9}, delay: 2ms}\n"
        "  overrides:\n"
        "    - {link: av2-gnb1, uplink: {radio: {prbs: 51}}, downlink: {radio: {bler: 2%}}}"
    )
    av1, av2 = specs["av1-gnb1"], specs["av2-gnb1"]
    assert av1.uplink.radio.slots == "DDSU" and av1.uplink.radio.mcs == 9  # type: ignore[union-attr]
    assert av1.uplink.delay_s == pytest.approx(0.002)  # a wired delay beside the radio
    assert av1.downlink.radio == SRS
    # The override changes the air default of its direction, itself a change of srsran's.
    assert (av2.uplink.radio.slots, av2.uplink.radio.mcs, av2.uplink.radio.n_prb) == ("DDSU", 9, 51)  # type: ignore[union-attr]
    assert av2.downlink.radio.bler == pytest.approx(0.02) and av2.downlink.radio.slots == "DDSU"  # type: ignore[union-attr]
    # A profile named in a mapping starts afresh.
    _, specs = _load(
        "  air:\n    radio: srsran-lowlat\n    uplink: {radio: {profile: oai-tdd-30k}}"
    )
    assert specs["av1-gnb1"].uplink.radio == OAI


def test_the_cell_carries_its_slot_grid_carrier_and_scheduler() -> None:
    scenario, specs = _load(
        # OAI's SR and configured grant fall in slots DDDSU has no uplink in: moved along.
        "  air:\n    radio: {sr_period: 5, sr_offset: 4, cg_period: 5, cg_offset: 4}\n"
        "    uplink: {radio: {mcs: 9}}",
        cell=", radio: {tdd: DDDSU, special_dl: 10, special_ul: 2, prbs: 51, scheduler: pf}",
    )
    for name in ("av1-gnb1", "av2-gnb1"):
        assert specs[name].downlink.radio.slots == "DDDSU"  # type: ignore[union-attr]
        up = specs[name].uplink.radio
        assert (up.slots, up.special, up.n_prb, up.mcs) == ("DDDSU", (10, 2, 2), 51, 9)  # type: ignore[union-attr]
    assert scenario.topology.cells[0].scheduler == "pf"
    # A cell's profile turns the radio on for air links that have none.
    _, specs = _load("  air: {}", cell=", radio: commercial-midband")
    assert specs["av1-gnb1"].uplink.radio == COMMERCIAL == specs["av2-gnb1"].downlink.radio


def test_a_set_event_changes_the_radio_the_link_has_then() -> None:
    scenario, _ = _load(
        "  air:\n    radio: srsran-lowlat\n    downlink: {radio: oai-tdd-30k}",
        "  - {at: 5s, set: av1-gnb1, direction: uplink, radio: {mcs: 5}}\n"
        "  - {at: 10s, set: av1-gnb1, direction: uplink, radio: {prbs: 20}}\n"
        "  - {at: 15s, set: av2-gnb1, direction: both, radio: {bler: 30%}}",
    )
    sets = [e for e in scenario.timeline if isinstance(e, SetEvent)]
    first, second = sets[0].changes["radio"], sets[1].changes["radio"]
    assert first.slots == "DDSU" and first.mcs == 5  # type: ignore[attr-defined]
    assert (second.mcs, second.n_prb) == (5, 20)  # type: ignore[attr-defined]
    # Its two directions had different radios: one event each, both at 15 s.
    both = {e.direction: e.changes["radio"] for e in sets[2:]}
    assert set(both) == {"uplink", "downlink"} and all(e.at_s == 15 for e in sets[2:])
    assert both["uplink"].slots == "DDSU" and both["downlink"].slots == "DDDDDDDSUU"  # type: ignore[attr-defined]
    assert both["uplink"].bler == both["downlink"].bler == pytest.approx(0.3)  # type: ignore[attr-defined]


def test_commercial_midband_has_the_round_trip_measured_on_commercial_cells() -> None:
    up, down = (
        COMMERCIAL.oracle("uplink", size_bytes=92),
        COMMERCIAL.oracle("downlink", size_bytes=92),
    )
    rng = random.Random(1)
    rtts = sorted(up.quantile(rng.random()) + down.quantile(rng.random()) for _ in range(4000))
    assert 0.020 <= rtts[2000] <= 0.030  # issue #16: median RTT 20-30 ms
    assert up.quantile(0.5) <= 0.020 and down.quantile(0.5) <= 0.007  # R&S's one-way figures
    # The core's distance rides in each direction's delay stage and in the oracle.
    stage = Delay()
    stage.configure(LinkProfile(radio=COMMERCIAL, delay_s=0.001))
    assert stage.delay_s == pytest.approx(0.004)
    assert down.minimum >= COMMERCIAL.core_delay_s


def test_rrc_of_the_air_links_reaches_both_directions_and_an_override_drops_it() -> None:
    import math

    from netem.nr.rrc import RrcSettings

    scenario, specs = _load(
        "  air:\n"
        "    uplink: {delay: 2ms}\n"
        "    rrc: {inactivity: 5s, resume: 20ms, idle_after: null}\n"
        "  overrides:\n"
        "    - {link: av2-gnb1, rrc: null}"
    )
    want = RrcSettings(inactivity_s=5.0, idle_after_s=math.inf, resume_s=0.02, setup_s=0.15)
    assert specs["av1-gnb1"].uplink.rrc == specs["av1-gnb1"].downlink.rrc == want
    assert specs["av2-gnb1"].uplink.rrc is None and specs["gnb1-core1"].uplink.rrc is None
    backend = links.choose_backend(scenario, probe=lambda: (True, "netem here"))
    assert backend.name == "userspace" and "RRC states" in backend.reason
    _, defaults = _load("  air:\n    rrc: {}")
    assert defaults["av1-gnb1"].uplink.rrc == RrcSettings()  # 10 s, 60 s, 30 ms, 150 ms
