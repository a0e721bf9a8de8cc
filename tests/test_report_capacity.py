"""The air link's capacity along the route (issue #19: "SINR/MCS/capacity over time"), from
synthetic run.mcap files written like the recorder's: /radio/av1 steps with known MCS and
BLER in each direction, links.json attached with each cell's air link radio. The expected
capacities are worked out here from `netem.nr.radio.RADIO_PROFILES` with `dataclasses.replace`, not
through the report's code; two cells with different radios show that each step counts on its
serving cell's link. A run without links.json (older runs) still reports, without capacity.
"""

from __future__ import annotations

import dataclasses
import re
import statistics
from pathlib import Path

import numpy as np
import pytest
from report_synth import SynthRun

from netem.nr.radio import RADIO_PROFILES, Radio
from nodes.recording.layout import LINKS_CONFIG_FILE
from reports.build import build_report, summarize
from reports.mcapread import read_run
from reports.sections.radio import radio_capacity

T0 = 1_700_000_000.0
STEPS = 40
#: Each cell's air link radio: different carriers and TDD patterns, so a step counted on the
#: wrong cell's link gives another figure.
RADIOS = {"gnb1": RADIO_PROFILES["oai-tdd-30k"], "gnb2": RADIO_PROFILES["srsran-lowlat"]}


def cell_of(k: int) -> str:
    return "gnb1" if k < 25 else "gnb2"


def ul_mcs_of(k: int) -> int:
    """Falls from 27 towards gnb1's edge (0 at step 24), then climbs in gnb2's cell."""
    return 27 - k if k < 25 else 2 * (k - 25)


def dl_mcs_of(k: int) -> int:
    return (7 * k + 3) % 29


def bler_of(k: int) -> float:
    return 0.1 if k % 4 else 0.35


def ul_bler_of(k: int) -> float:
    return 0.1 if k % 3 else 0.5


def capacity_run(links: bool = True) -> SynthRun:
    """av1's 4 s drive from gnb1's cell into gnb2's at step 25, a step every 0.1 s."""
    s = SynthRun()
    for k in range(STEPS):
        s.radio(
            T0 + 0.1 * k,
            cell_of(k),
            ul_mcs_of(k),
            x=float(k),
            mcs=dl_mcs_of(k),
            bler=bler_of(k),
            ul_bler=ul_bler_of(k),
        )
    s.channel_run("cap1", {"gnb1": (0.0, 50.0), "gnb2": (40.0, 50.0)})
    if links:
        s.links({"av1-gnb1": RADIOS["gnb1"], "av1-gnb2": RADIOS["gnb2"], "gnb1-upf": None})
    return s


def expected_mbps(direction: str) -> list[float]:
    """Per step, its serving cell's radio at the step's MCS and BLER: `Radio.goodput_bps`."""
    out = []
    for k in range(STEPS):
        up = direction == "uplink"
        radio = dataclasses.replace(
            RADIOS[cell_of(k)],
            mcs=ul_mcs_of(k) if up else dl_mcs_of(k),
            bler=ul_bler_of(k) if up else bler_of(k),
        )
        out.append(radio.goodput_bps(direction) / 1e6)  # type: ignore[arg-type]
    return out


def write(tmp_path: Path, synth: SynthRun) -> Path:
    folder = tmp_path / "run"
    folder.mkdir()
    synth.write(folder / "run.mcap")
    return folder


def test_links_json_is_read_and_its_radios_rebuilt(tmp_path: Path) -> None:
    data = read_run(write(tmp_path, capacity_run()))
    assert data.links_config is not None and data.links_config["backend"] == "userspace"
    assert set(data.links_config["links"]) == {"av1-gnb1", "av1-gnb2", "gnb1-upf"}
    assert data.link_radios == {
        ("av1-gnb1", "uplink"): RADIOS["gnb1"],
        ("av1-gnb1", "downlink"): RADIOS["gnb1"],
        ("av1-gnb2", "uplink"): RADIOS["gnb2"],
        ("av1-gnb2", "downlink"): RADIOS["gnb2"],
    }
    assert data.problems == []


def test_capacity_per_step_is_the_serving_links_goodput_at_the_steps_mcs(tmp_path: Path) -> None:
    data = read_run(write(tmp_path, capacity_run()))
    capacity = radio_capacity(data, data.radio["av1"])
    assert capacity is not None
    ul, dl = expected_mbps("uplink"), expected_mbps("downlink")
    assert capacity["ul"].tolist() == pytest.approx(ul, rel=1e-12)
    assert capacity["dl"].tolist() == pytest.approx(dl, rel=1e-12)
    # BLER counts (goodput, not the raw block rate), and the cells' radios differ.
    assert ul[3] == pytest.approx(
        dataclasses.replace(RADIOS["gnb1"], mcs=24, bler=0.0).rate_bps("uplink") * 0.5 / 1e6
    )
    assert RADIOS["gnb1"].goodput_bps("uplink") != RADIOS["gnb2"].goodput_bps("uplink")


def test_the_summary_spreads_the_capacity_of_each_direction(tmp_path: Path) -> None:
    av1 = summarize(read_run(write(tmp_path, capacity_run())), splits=False)["radio"]["vehicles"]
    spread = av1["av1"]["capacity_mbps"]
    assert set(spread) == {"ul", "dl"}
    for key, direction in (("ul", "uplink"), ("dl", "downlink")):
        x = expected_mbps(direction)
        p5, p95 = np.percentile(x, [5, 95])
        assert spread[key] == pytest.approx(
            {
                "min": min(x),
                "p5": p5,
                "median": statistics.median(x),
                "p95": p95,
                "max": max(x),
            },
            abs=1e-3,  # the summary rounds to 3 decimals
        )


def test_the_report_has_the_capacity_column_and_panel(tmp_path: Path) -> None:
    folder = write(tmp_path, capacity_run())
    rep = build_report(folder, splits=False)
    ul = rep.summary["radio"]["vehicles"]["av1"]["capacity_mbps"]["ul"]
    cell = f"{ul['p5']:.1f} / {ul['median']:.1f}"
    html = (folder / "report.html").read_text()
    assert "<th>capacity p5/median UL Mbit/s</th>" in html
    assert re.search(rf"<td[^>]*>{re.escape(cell)}</td>", html)
    md = (folder / "report.md").read_text()
    section = md.split("## Radio along the route")[1].split("\n## ")[0]
    assert "capacity p5/median UL Mbit/s |" in section
    assert f"| {cell} |" in section
    assert "the Mbit/s the serving cell's air link carried at that MCS and BLER" in section
    png = (folder / "plots" / "radio_av1.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # 12 x 6.5 in at 100 dpi: the capacity panel below SINR and MCS (5 in without it)
    size = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert size == (1200, 650)


def test_a_run_without_links_json_reports_without_capacity(tmp_path: Path) -> None:
    folder = write(tmp_path, capacity_run(links=False))
    data = read_run(folder)
    assert data.links_config is None and data.link_radios == {}
    assert radio_capacity(data, data.radio["av1"]) is None
    rep = build_report(folder, splits=False)
    av1 = rep.summary["radio"]["vehicles"]["av1"]
    assert av1["capacity_mbps"] is None
    assert av1["steps"] == STEPS  # the rest of the radio summary is there
    md = (folder / "report.md").read_text()
    section = md.split("## Radio along the route")[1].split("\n## ")[0]
    row = next(line for line in section.splitlines() if line.startswith("| av1 |"))
    assert row.rstrip().endswith("| - |")
    png = (folder / "plots" / "radio_av1.png").read_bytes()
    size = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert size == (1200, 500)
    assert "air link carried" not in section


def test_links_json_without_radios_or_with_a_broken_one_gives_no_capacity(tmp_path: Path) -> None:
    """Wired links only: nothing to compute from. A radio of another version's fields: left
    out with a problem, and the report still builds."""
    synth = capacity_run(links=False)
    synth.links({"av1-gnb1": None, "av1-gnb2": None})
    data = read_run(write(tmp_path, synth))
    assert data.links_config is not None and data.link_radios == {}
    assert summarize(data, splits=False)["radio"]["vehicles"]["av1"]["capacity_mbps"] is None

    broken = capacity_run(links=False)
    broken.links({"av1-gnb1": RADIOS["gnb1"], "av1-gnb2": Radio()})
    config = broken.attachments[LINKS_CONFIG_FILE].decode()
    broken.attachments[LINKS_CONFIG_FILE] = config.replace('"n_prb"', '"n_prbs"').encode()
    folder = tmp_path / "broken"
    folder.mkdir()
    broken.write(folder / "run.mcap")
    data = read_run(folder)
    assert data.link_radios == {}
    assert any(
        "links.json: the uplink radio of av1-gnb1 does not rebuild" in p for p in data.problems
    )
    rep = build_report(folder, splits=False)
    assert rep.summary["radio"]["vehicles"]["av1"]["capacity_mbps"] is None


def test_a_link_without_a_radio_leaves_its_steps_without_capacity(tmp_path: Path) -> None:
    """Only gnb1's air link has a radio: gnb2's steps have no capacity (NaN), gnb1's do."""
    synth = capacity_run(links=False)
    synth.links({"av1-gnb1": RADIOS["gnb1"], "av1-gnb2": None})
    data = read_run(write(tmp_path, synth))
    capacity = radio_capacity(data, data.radio["av1"])
    assert capacity is not None
    ul = capacity["ul"]
    assert ul[:25].tolist() == pytest.approx(expected_mbps("uplink")[:25], rel=1e-12)
    assert np.isnan(ul[25:]).all()
    spread = summarize(data, splits=False)["radio"]["vehicles"]["av1"]["capacity_mbps"]["ul"]
    assert spread["max"] == pytest.approx(max(expected_mbps("uplink")[:25]), abs=1e-3)
