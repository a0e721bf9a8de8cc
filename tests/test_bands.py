"""The learner's plays grouped by the uplink MCS they met (`nodes.edgeloc.bands`), and the
replay of a channel scenario carrying them."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest

from nodes.edgeloc import bands


def test_band_of_puts_each_mcs_in_its_band_and_refuses_others() -> None:
    assert [bands.band_of(m) for m in (0, 9, 10, 19, 20, 28)] == [0, 0, 1, 1, 2, 2]
    with pytest.raises(ValueError, match="MCS 29"):
        bands.band_of(29)
    with pytest.raises(ValueError, match="MCS -1"):
        bands.band_of(-1)


def test_by_band_counts_shares_and_the_mean_payload() -> None:
    rows = bands.by_band(
        [3, 3, 25, 25, 25, 12],
        ["fc", "vehicle", "conv1", "conv1", "fc", "conv3"],
        {"fc": 400.0, "vehicle": 0.0, "conv1": 12000.0, "conv3": 2500.0},
        time_share=[0.5, 0.25, 0.25],
    )
    assert [r["plays"] for r in rows] == [2, 1, 3]
    assert rows[0]["share"] == {"fc": 0.5, "vehicle": 0.5}
    assert rows[0]["mean_payload_bytes"] == 200.0
    assert rows[2]["share"] == {"conv1": pytest.approx(2 / 3), "fc": pytest.approx(1 / 3)}
    assert rows[2]["mean_payload_bytes"] == pytest.approx((12000 * 2 + 400) / 3)
    assert [r["time_share"] for r in rows] == [0.5, 0.25, 0.25]
    text = bands.lines(rows)
    assert (
        text[2]
        == "uplink MCS 20-28 (25% of the run): 3 plays, conv1 67%, fc 33%; mean payload 8.1 kB"
    )
    empty = bands.by_band([], [], {})
    assert [r["plays"] for r in empty] == [0, 0, 0] and bands.lines(empty)[0].endswith("no plays")
    with pytest.raises(ValueError, match="2 MCS values for 1 plays"):
        bands.by_band([1, 2], ["fc"], {})
    assert bands.time_shares([0, 0, 15, 28]) == [0.5, 0.25, 0.25]


def test_a_channel_scenario_s_replay_sorts_its_plays_by_the_uplink_mcs(tmp_path: Path) -> None:
    from testbed import mobility
    from testbed.replay import replay_scenario
    from testbed.scenario import loads

    repo = Path(__file__).resolve().parents[1]
    text = (repo / "scenarios" / "drive_one_cell.yaml").read_text()
    scenario = loads(text.replace("duration: 90s", "duration: 30s"), base_dir=repo / "scenarios")
    done = replay_scenario(scenario, tmp_path, compare=False)
    radio = done.summary["radio"]
    rows = radio["by_uplink_mcs"]
    decisions = done.summary["learner"]["decisions"]
    assert radio["vehicle"] == "av1"
    assert sum(r["plays"] for r in rows) == len(decisions["split"]) > 100
    ul = [s.ul_mcs for s in mobility.plans(scenario)["av1"].steps]
    assert [r["time_share"] for r in rows] == bands.time_shares(ul)
    # Each play in the band of the MCS at its sending time (10 ms steps), every one of them.
    want = Counter(bands.band_of(ul[int(t / 0.01 + 1e-9)]) for t in decisions["sent_s"])
    assert [r["plays"] for r in rows] == [want[b] for b in range(len(rows))]
    assert sum(1 for n in want.values() if n) >= 2  # the drive crosses bands


def test_around_a_handover_splits_the_window_at_it() -> None:
    series = bands.Series(
        sent_s=[6.9, 7.5, 8.0, 9.9, 10.0, 12.9, 13.0],
        splits=["image", "fc", "fc", "conv1", "vehicle", "vehicle", "image"],
        latency_s=[0.1, 0.05, 0.07, float("inf"), 0.2, 0.04, 0.1],
        payload_bytes={"image": 37000.0, "fc": 400.0, "conv1": 12000.0, "vehicle": 0.0},
        frame_t=[7.0, 9.0, 10.0, 12.0, 13.5],
        frame_error_m=[1.0, 2.0, 4.0, 6.0, 100.0],
        mcs_t=[6.0, 8.0, 11.0, 12.0],
        ul_mcs=[28, 10, 4, 20],
    )
    got = bands.around(10.0, series)
    before, after = got["before"], got["after"]
    # [7, 10): 7.5, 8.0, 9.9 (6.9 is outside); the lost one's latency is left out.
    assert (before["plays"], before["top_split"]) == (3, "fc")
    assert before["top_share"] == pytest.approx(2 / 3)
    assert before["mean_payload_bytes"] == pytest.approx((400 + 400 + 12000) / 3)
    assert before["mean_latency_s"] == pytest.approx(0.06)
    assert before["mean_error_m"] == pytest.approx(1.5)
    assert before["mean_ul_mcs"] == 10
    # [10, 13): 10.0, 12.9 (13.0 is outside).
    assert (after["plays"], after["top_split"], after["top_share"]) == (2, "vehicle", 1.0)
    assert after["mean_payload_bytes"] == 0.0 and after["mean_error_m"] == pytest.approx(5.0)
    assert after["mean_ul_mcs"] == 12
    line = bands.around_lines([{"t_s": 10.0, "source": "gnb1", "target": "gnb2", "around": got}])[0]
    assert line.startswith("10.00 s gnb1 -> gnb2: before UL MCS 10, fc 67%, 4.3 kB")
    assert line.endswith("after UL MCS 12, vehicle 100%, 0.0 kB, EdgeLoc 5.00 m")
