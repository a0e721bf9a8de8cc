"""`testbed.capacity` without root: which link rates a host's data plane cannot carry
(`check_links`), the cached figure's key and age, and where `validate --host`, `link-test` and
`run` print them. The measurement itself is in tests/test_capacity_root.py."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

import netem
from netem.profile import LinkProfile
from testbed import capacity
from testbed import links as lk
from testbed import state as st
from testbed.capacity import (
    CACHE_FILE,
    MAX_AGE_S,
    CapacityCheck,
    DataPlane,
    cached_data_plane,
    check_links,
    host_data_plane,
    host_key,
    save_data_plane,
)
from testbed.cli import app
from testbed.errors import TestbedError
from testbed.linktest import LinkTestReport
from testbed.scenario import load
from testbed.scenario.model import LinkSpec, SetEvent, TraceEvent

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "scenarios" / "default.yaml"
runner = CliRunner()

#: A host like this one: TCP 9.5 Gbit/s of goodput (a 9.84 Gbit/s link), 60,000 datagrams/s
#: (a 720 Mbit/s link), 2 CPUs.
PLANE = DataPlane(
    tcp_bps=9.5e9,
    datagram_pps=60_000,
    datagram_bps=60_000 * 1500 * 8,
    measured_at=0.0,
    seconds=3.0,
    kernel="6.1.0",
    cpus=2,
    python="3.11.7",
    netem_hash="0123456789abcdef",
)


def spec(name: str, up: float | None, down: float | None) -> LinkSpec:
    lower, upper = name.split("-")
    return LinkSpec(name, "air", lower, upper, LinkProfile(rate_bps=up), LinkProfile(rate_bps=down))


@pytest.fixture
def state(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    d = tmp_path / "state"
    monkeypatch.setenv(st.STATE_DIR_ENV, str(d))
    return d


# ---- check_links ------------------------------------------------------------------------------


def test_the_default_scenario_gets_a_note_for_each_1gbit_backhaul_direction() -> None:
    warnings = check_links(load(DEFAULT), PLANE)
    assert [(w.level, w.link, w.direction) for w in warnings] == [
        ("note", "gnb1-upf1", "uplink"),
        ("note", "gnb1-upf1", "downlink"),
    ]
    up = warnings[0]
    assert (up.rate_bps, up.host_bps) == (1e9, 720e6)
    assert up.message == (
        "gnb1-upf1 uplink: rate 1gbit is more than this host's relay carries one packet at a "
        "time (720mbit: 60,000 packets/s of 1500 bytes): UDP sent without GSO (ROS 2 DDS) above "
        "that is limited by the relay, TCP is not. Lower it to 720mbit if such traffic must "
        "reach the rate, or use a host whose kernel has sch_netem (links.backend: tc or auto)"
    )
    assert up.text() == f"note: {up.message}"
    # the air link (50 and 200 Mbit/s) is well inside both figures
    assert not [w for w in warnings if w.link == "av1-gnb1"]


def test_a_rate_above_the_tcp_figure_is_an_error_naming_link_direction_and_rates() -> None:
    (w,) = check_links([spec("av1-gnb1", 20e9, 10e6)], PLANE)
    assert (w.level, w.link, w.direction, w.rate_bps) == ("error", "av1-gnb1", "uplink", 20e9)
    assert w.host_bps == pytest.approx(9.5e9 * 1500 / 1448)
    assert w.message == (
        "av1-gnb1 uplink: rate 20gbit is more than this host's relay carries even for TCP "
        "(9.84gbit through one direction): the relay, not the link, would set the rate. Lower "
        "it to at most 9.84gbit, or use a host whose kernel has sch_netem (links.backend: tc "
        "or auto)"
    )


def test_rates_within_both_figures_and_unlimited_directions_ask_nothing() -> None:
    assert check_links([spec("av1-gnb1", 700e6, None), spec("gnb1-core1", None, None)], PLANE) == []


def test_the_figures_are_thresholds_not_approximations() -> None:
    at, above = PLANE.datagram_bps, PLANE.datagram_bps * 1.001
    assert check_links([spec("av1-gnb1", at, at)], PLANE) == []
    assert [w.level for w in check_links([spec("av1-gnb1", above, None)], PLANE)] == ["note"]
    tcp = PLANE.tcp_link_bps
    assert [w.level for w in check_links([spec("av1-gnb1", tcp, None)], PLANE)] == ["note"]
    assert [w.level for w in check_links([spec("av1-gnb1", tcp * 1.001, None)], PLANE)] == ["error"]


def test_the_tc_backend_is_not_limited_by_the_relay() -> None:
    assert check_links([spec("av1-gnb1", 100e9, 100e9)], PLANE, backend="tc") == []


def test_a_scenarios_links_alone_are_checked_too() -> None:
    scenario = load(DEFAULT)
    assert check_links(scenario.links, PLANE) == check_links(scenario, PLANE)


def test_both_directions_of_one_link_share_its_relay() -> None:
    warnings = check_links([spec("gnb1-core1", 6e9, 6e9)], PLANE)
    assert [w.level for w in warnings] == ["note", "note", "error"]  # each above per packet
    w = warnings[-1]
    assert (w.level, w.link, w.direction, w.rate_bps) == ("error", "gnb1-core1", None, 12e9)
    assert w.message.startswith(
        "gnb1-core1: its directions ask 12gbit together, more than one relay (one process) "
        "carries even for TCP (9.84gbit)"
    )
    # a direction that alone is too much already says so: no second error for its link
    warnings = check_links([spec("gnb1-core1", 20e9, 6e9)], PLANE)
    assert [(w.level, w.direction) for w in warnings] == [("error", "uplink"), ("note", "downlink")]


def test_all_links_together_share_the_hosts_cpus() -> None:
    links = [spec(f"av{i}-gnb1", 5e9, 2e9) for i in range(3)]  # 21 Gbit/s, 3 relays
    (w,) = [w for w in check_links(links, PLANE) if w.link is None]
    assert (w.level, w.direction, w.rate_bps) == ("error", None, 21e9)
    assert w.host_bps == pytest.approx(2 * PLANE.tcp_link_bps)
    assert w.message.startswith(
        "all links: 6 directions ask 21gbit together, more than the relays carry even for TCP "
        "on this host's 2 CPU(s) (19.7gbit, 9.84gbit each)"
    )
    four_cpus = dataclasses.replace(PLANE, cpus=4)
    assert [w for w in check_links(links, four_cpus) if w.link is None] == []


def test_a_set_event_that_raises_the_rate_is_checked_with_its_time() -> None:
    scenario = load(DEFAULT)
    raised = SetEvent(30.0, "av1-gnb1", "both", {"rate_bps": 12e9})
    lifted = SetEvent(40.0, "av1-gnb1", "uplink", {"rate_bps": None})  # unlimited: no ask
    scenario = dataclasses.replace(scenario, timeline=(*scenario.timeline, raised, lifted))
    air = [w for w in check_links(scenario, PLANE) if w.link == "av1-gnb1"]
    assert [(w.level, w.direction) for w in air] == [("error", "uplink"), ("error", "downlink")]
    assert air[0].message.startswith(
        "av1-gnb1 uplink: rate 12gbit (from the `set` at 30 s) is more than"
    )


def test_a_trace_moves_every_packet_on_its_own_so_its_peak_meets_the_datagram_figure() -> None:
    scenario = load(ROOT / "scenarios" / "trace_driven.yaml")
    (event,) = [e for e in scenario.timeline if isinstance(e, TraceEvent)]
    peaks: list[TraceEvent] = []

    def peak(e: TraceEvent) -> float:
        peaks.append(e)
        return 900e6

    air = [w for w in check_links(scenario, PLANE, trace_peak=peak) if w.link == "av1-gnb1"]
    assert peaks == [event]
    (w,) = air
    assert (w.level, w.direction, w.rate_bps, w.host_bps) == ("error", "uplink", 900e6, 720e6)
    assert w.message.startswith(
        "av1-gnb1 uplink: rate 900mbit (from the trace 5g-uplink-drive.csv at 0 s (its peak)) "
        "is more than this host's relay carries one packet at a time (720mbit: 60,000 "
        "packets/s), and a direction replaying a trace moves every packet on its own"
    )
    # the committed trace itself (read from its file) stays below a 720 Mbit/s relay
    assert [w for w in check_links(scenario, PLANE) if w.link == "av1-gnb1"] == []


def test_check_scenario_measures_nothing_on_the_tc_backend(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def no(*_: object, **__: object) -> DataPlane:
        raise AssertionError("measured on the tc backend")

    monkeypatch.setattr(lk, "choose_backend", lambda _s: lk.BackendChoice("tc", "auto: netem"))
    monkeypatch.setattr(capacity, "host_data_plane", no)
    check = capacity.check_scenario(load(DEFAULT))
    assert check.plane is None and check.warnings == ()
    assert check.lines() == [
        "link capacity: tc (auto: netem): kernel qdiscs, not limited by the relay"
    ]


# ---- the cached figure ------------------------------------------------------------------------


def here(**changes: Any) -> DataPlane:
    """PLANE as if measured on this host just now."""
    return dataclasses.replace(PLANE, measured_at=time.time(), **{**host_key(), **changes})


def test_a_saved_figure_is_reused_on_the_same_host_within_a_day(state: Path) -> None:
    plane = here()
    path = save_data_plane(plane)
    assert path == state / CACHE_FILE
    assert json.loads(path.read_text()) == plane.to_dict()
    assert "cached" not in plane.to_dict()
    assert list(state.iterdir()) == [path]  # written atomically: no temp file left
    got = cached_data_plane()
    assert got == plane and got is not None and got.cached
    assert got.source().startswith("cached from ")
    assert plane.source() == "measured now in 3.0 s"


@pytest.mark.parametrize(
    "change",
    [
        {"kernel": "5.10.0-other"},
        {"cpus": 64},
        {"python": "3.99.0"},
        {"netem_hash": "ffffffffffffffff"},
    ],
)
def test_a_figure_from_another_host_or_code_is_not_reused(
    state: Path, change: dict[str, Any]
) -> None:
    save_data_plane(here(**change))
    assert cached_data_plane() is None


def test_a_figure_older_than_a_day_or_from_the_future_is_not_reused(state: Path) -> None:
    now = time.time()
    save_data_plane(here())
    assert cached_data_plane(now + MAX_AGE_S - 60) is not None
    assert cached_data_plane(now + MAX_AGE_S + 60) is None
    assert cached_data_plane(now - 3600) is None  # measured "later" than now: a clock jump


def test_an_unreadable_cache_is_measured_again(state: Path) -> None:
    state.mkdir()
    (state / CACHE_FILE).write_text("{not json")
    assert cached_data_plane() is None
    (state / CACHE_FILE).write_text(json.dumps({"tcp_bps": 1.0}))
    assert cached_data_plane() is None


def test_the_netem_hash_follows_the_netem_sources(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert capacity.netem_sources_hash() == host_key()["netem_hash"]
    fake = tmp_path / "netem"
    fake.mkdir()
    (fake / "__init__.py").write_text("")
    (fake / "relay.py").write_text("RATE = 1\n")
    monkeypatch.setattr(netem, "__file__", str(fake / "__init__.py"))
    before = capacity.netem_sources_hash()
    (fake / "relay.py").write_text("RATE = 2\n")
    assert capacity.netem_sources_hash() != before
    after = capacity.netem_sources_hash()
    (fake / "notes.txt").write_text("not code")
    assert capacity.netem_sources_hash() == after


def test_host_data_plane_measures_only_without_a_fresh_figure(
    state: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    measured: list[DataPlane] = []

    def measure() -> DataPlane:
        measured.append(here(tcp_bps=8e9))
        return measured[-1]

    monkeypatch.setattr(capacity, "measure_data_plane", measure)
    lines: list[str] = []
    first = host_data_plane(progress=lines.append)
    assert len(measured) == 1 and not first.cached and first.tcp_bps == 8e9
    assert lines and lines[0].startswith("measuring this host's userspace data plane")
    again = host_data_plane(progress=lines.append)
    assert len(measured) == 1 and again.cached and again == first
    host_data_plane(refresh=True)
    assert len(measured) == 2


def test_data_plane_round_trips_through_its_dict() -> None:
    assert DataPlane.from_dict(json.loads(json.dumps(PLANE.to_dict()))) == PLANE
    assert PLANE.text() == (
        "TCP 9.5gbit goodput (offloaded; a 9.84gbit link), 60,000 datagrams/s of 1472 bytes "
        "(a 720mbit link, per packet) through one relay direction; 2 CPU(s)"
    )


# ---- where it is printed ----------------------------------------------------------------------


def _fake_host(monkeypatch: pytest.MonkeyPatch, plane: DataPlane = PLANE) -> None:
    """`validate --host` on a userspace host with `plane`, without root or a measurement."""
    import testbed.namespaces

    monkeypatch.setattr(testbed.namespaces, "require_root", lambda: None)
    monkeypatch.setattr(lk, "choose_backend", lambda _s: lk.BackendChoice("userspace", "auto"))
    monkeypatch.setattr(capacity, "host_data_plane", lambda **_: plane)


def test_validate_host_prints_the_figure_and_the_notes_and_exits_0(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _fake_host(monkeypatch)
    result = runner.invoke(app, ["validate", "--host", str(DEFAULT)])
    assert result.exit_code == 0, result.output
    assert f"host data plane: {PLANE.text()}; measured now in 3.0 s" in result.output
    assert f"note: {DEFAULT}: gnb1-upf1 uplink: rate 1gbit" in result.output
    assert f"note: {DEFAULT}: gnb1-upf1 downlink: rate 1gbit" in result.output


def test_validate_host_exits_3_when_a_rate_is_beyond_even_tcp(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    slow = dataclasses.replace(PLANE, tcp_bps=500e6, datagram_pps=10_000, datagram_bps=120e6)
    _fake_host(monkeypatch, slow)
    result = runner.invoke(app, ["validate", "--host", str(DEFAULT)])
    assert result.exit_code == 3
    assert f"error: {DEFAULT}: gnb1-upf1 uplink: rate 1gbit is more than" in result.output
    # a bad file still decides the exit code: 2
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\n")
    result = runner.invoke(app, ["validate", "--host", str(DEFAULT), str(bad)])
    assert result.exit_code == 2


def test_validate_host_without_root_exits_3_and_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    def measure() -> DataPlane:
        raise AssertionError("measured without root")

    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    monkeypatch.setattr(capacity, "measure_data_plane", measure)
    result = runner.invoke(app, ["validate", "--host", str(DEFAULT)])
    assert result.exit_code == 3
    assert f"{DEFAULT}: valid" in result.output
    assert "error: validate --host: building or removing namespaces needs root" in result.output


def test_validate_without_host_measures_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    def no(**_: object) -> DataPlane:
        raise AssertionError("measured without --host")

    monkeypatch.setattr(capacity, "host_data_plane", no)
    result = runner.invoke(app, ["validate", str(DEFAULT)])
    assert result.exit_code == 0 and "host data plane" not in result.output


class Built(Exception):
    """Stands in for building the network: the check must have been printed before it."""


def _no_build(*_: object, **__: object) -> None:
    raise Built


def test_link_test_prints_the_capacity_first_and_keeps_it_in_its_report(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import testbed.topology
    from testbed.linktest import link_test

    check = CapacityCheck("userspace (auto)", PLANE, tuple(check_links(load(DEFAULT), PLANE)))
    lines: list[str] = []
    monkeypatch.setattr(testbed.topology, "build", _no_build)
    with pytest.raises(Built):
        link_test(load(DEFAULT), quick=True, progress=lines.append, capacity=check)
    assert lines == check.lines()
    assert lines[0] == f"host data plane: {PLANE.text()}; measured now in 3.0 s"
    assert lines[1].startswith("note: gnb1-upf1 uplink: rate 1gbit")
    report = LinkTestReport("userspace", True, [], capacity=check.to_dict())
    data = json.loads(json.dumps(report.to_dict()))
    assert data["capacity"]["data_plane"] == PLANE.to_dict()
    assert [w["direction"] for w in data["capacity"]["warnings"]] == ["uplink", "downlink"]


def test_run_prints_the_capacity_before_building_and_a_failed_check_does_not_stop_it(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import testbed.run

    check = CapacityCheck("userspace (auto)", PLANE, tuple(check_links(load(DEFAULT), PLANE)))
    monkeypatch.setattr(testbed.run, "build", _no_build)
    monkeypatch.setattr(testbed.run, "check_scenario", lambda _s, progress: check)
    lines: list[str] = []
    with pytest.raises(Built):
        testbed.run.run_scenario(load(DEFAULT), tmp_path, lines.append, capacity_check=True)
    assert lines == check.lines()

    def broken(_s: object, progress: object) -> CapacityCheck:
        raise TestbedError("no traffic came through the throwaway relay link")

    monkeypatch.setattr(testbed.run, "check_scenario", broken)
    lines.clear()
    with pytest.raises(Built):  # the run goes on to build its network
        testbed.run.run_scenario(load(DEFAULT), tmp_path, lines.append, capacity_check=True)
    assert lines == [
        "warning: link capacity not checked: no traffic came through the throwaway relay link"
    ]
    lines.clear()
    with pytest.raises(Built):  # off (the library's default): nothing checked or printed
        testbed.run.run_scenario(load(DEFAULT), tmp_path, lines.append)
    assert lines == []
