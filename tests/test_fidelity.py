"""The fidelity library: every case within tolerance, a changed field of a case's radio caught,
bad case files refused by file and key, the new radio fields against the closed form, and a
shortened run of each case through the real relay."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from netem.nr.radio import RADIO_PROFILES, Radio
from testbed.fidelity import FidelityError, find, library, load_case, run_cases
from testbed.fidelity.case import shortened
from testbed.fidelity.judge import figures, sampling_w1, w1_ms
from testbed.fidelity.model import HEADERS, model_delays

CASES = [c.name for c in library()]


def test_the_library_has_the_cases_the_readme_promises() -> None:
    assert {"srsran-urllc", "sa-midband-ericsson", "oai-usrp-edaf", "public-n78-cicv5g"} <= set(
        CASES
    )
    for case in library():
        assert case.source["url"].startswith("https://")
        assert case.variants


@pytest.mark.parametrize("name", CASES)
def test_every_case_is_within_tolerance_on_the_stages(name: str) -> None:
    (result,) = run_cases(find([name]), real=False)
    bad = [(j.variant, c) for j in result.variants for c in j.checks if not c.ok]
    assert not bad, bad


#: (case, a change of one radio field, the published figure it must make us miss)
MISSES = [
    ("srsran-urllc", {"radio_offset_slots": 2}, "downlink mean"),
    ("srsran-urllc", {"sched_offset_slots": 2}, "uplink mean"),
    ("srsran-urllc", {"k2_slots": 1}, "uplink mean"),
    ("srsran-urllc", {"sr_period_slots": 8}, "uplink mean"),
    ("srsran-urllc", {"ue_ul_delay_s": 0.0}, "uplink mean"),
    ("srsran-urllc", {"ue_dl_delay_s": 0.0015}, "downlink mean"),
    ("srsran-urllc", {"slots": "DDDSU", "sr_period_slots": 5, "sr_offset": 4}, "uplink mean"),
    ("sa-midband-ericsson", {"bler": 0.0}, "downlink p99"),
    ("sa-midband-ericsson", {"ue_ul_delay_s": 0.002}, "uplink p50"),
    (
        "sa-midband-ericsson",
        {"ul_access": "sr", "sr_period_slots": 5, "sr_offset": 4},
        "uplink p50",
    ),
    ("sa-midband-ericsson", {"harq_slots": 12}, "downlink p99"),
    ("oai-usrp-edaf", {"ul_prbs": 8}, "uplink p50"),
    ("oai-usrp-edaf", {"ul_symbols": 4}, "uplink p50"),
    ("oai-usrp-edaf", {"l2_overhead_bytes": 0}, "uplink p50"),
    ("oai-usrp-edaf", {"harq_slots": 4}, "HARQ step (ms)"),
    ("oai-usrp-edaf", {"bler": 0.12}, "HARQ share of blocks"),
    ("oai-usrp-edaf", {"grant_slots": 5}, "uplink p50"),
    ("oai-usrp-edaf", {"mcs_mix": ()}, "uplink p90"),
    ("oai-usrp-edaf", {"ul_prbs": 20}, "segmented share of packets"),
    ("public-n78-cicv5g", {"bler": 0.1}, "rtt p99"),
    ("public-n78-cicv5g", {"sr_period_slots": 20}, "rtt p50"),
    ("public-n78-cicv5g", {"core_delay_s": 0.005}, "rtt p50"),
    ("public-n78-cicv5g", {"slots": "DDDDDDDSUU", "sr_offset": 8}, "rtt p50"),
]


@pytest.mark.parametrize(("name", "change", "missed"), MISSES)
def test_a_changed_field_misses_a_published_figure(
    name: str, change: dict[str, object], missed: str
) -> None:
    (case,) = find([name])
    variants = tuple(
        dataclasses.replace(v, radio=dataclasses.replace(v.radio, **change))  # type: ignore[arg-type]
        for v in case.variants
    )
    (result,) = run_cases([dataclasses.replace(case, variants=variants)], real=False)
    failed = {c.what for j in result.variants for c in j.checks if not c.ok}
    assert missed in failed, (change, failed)


def test_srsran_variants_change_only_what_the_paper_changed() -> None:
    (case,) = find(["srsran-urllc"])
    assert case.variants[0].changes == {}
    allowed = {"radio_offset", "sched_offset", "access"}
    for variant in case.variants[1:]:
        assert set(variant.changes) <= allowed, variant.changes
    base = RADIO_PROFILES["srsran-urllc"]
    assert (base.sched_offset_slots, base.radio_offset_slots, base.ul_access) == (1, 3, "sr")


@pytest.mark.parametrize(
    "radio",
    [
        RADIO_PROFILES["srsran-urllc"],
        dataclasses.replace(RADIO_PROFILES["srsran-urllc"], radio_offset_slots=1),
        dataclasses.replace(RADIO_PROFILES["srsran-urllc"], ul_access="sr_free"),
        dataclasses.replace(RADIO_PROFILES["oai-tdd-30k"], ue_ul_delay_s=0.001, bler=0.0),
    ],
    ids=["stock", "r1", "sr_free", "oai+ue"],
)
def test_the_stages_agree_with_the_closed_form_for_the_new_fields(radio: Radio) -> None:
    """Offsets, SR-free access and the UE's delay: the Slots stage on a fake clock against
    `Radio.oracle` (each probe finds its UE idle, phases uniform), mean and median within
    0.05 and 0.08 ms."""
    (case,) = find(["srsran-urllc"])
    probe = dataclasses.replace(case.probe, count=1500, interval_s=0.05)
    for direction in ("uplink", "downlink"):
        oracle = radio.oracle(direction, size_bytes=probe.size + HEADERS)
        got = figures(model_delays(radio, probe, direction).delivered)
        assert got["mean"] == pytest.approx(oracle.mean() * 1000, abs=0.05), direction
        assert got["p50"] == pytest.approx(oracle.quantile(0.5) * 1000, abs=0.08), direction
        assert got["min"] >= oracle.minimum * 1000 - 1e-6, direction


def test_small_uplink_grants_segment_a_packet() -> None:
    """ul_prbs x ul_symbols caps each uplink block, so a packet bigger than one leaves in
    several (counted as segmented), one block per uplink slot."""
    radio = dataclasses.replace(RADIO_PROFILES["oai-tdd-30k"], ul_prbs=5, ul_symbols=3, bler=0.0)
    capacity = radio.grid("uplink").occasions[0].capacity_bytes
    assert 20 <= capacity <= 60
    (case,) = find(["srsran-urllc"])
    probe = dataclasses.replace(case.probe, size=128, count=200, interval_s=0.05)
    got = model_delays(radio, probe, "uplink")
    assert got.counters["segmented_packets"] == 200
    wide = dataclasses.replace(radio, ul_prbs=None, ul_symbols=None, sr_grant_bytes=1000)
    wide = model_delays(wide, probe, "uplink")
    assert wide.counters["segmented_packets"] == 0
    assert figures(got.delivered)["mean"] > figures(wide.delivered)["mean"] + 4.0


def test_w1_tolerance_comes_from_the_data_itself() -> None:
    values = [float(x % 17) for x in range(1000)]
    assert w1_ms(values, values, None) == pytest.approx(0.0, abs=1e-9)
    assert w1_ms([v + 1.0 for v in values], values, None) == pytest.approx(1.0, abs=0.01)
    few, many = sampling_w1(values, None, 50), sampling_w1(values, None, 2000)
    assert few > many > 0
    # A series whose values come in runs (a busy queue) resampled in runs spreads more.
    runs = [float(k // 100 % 7) for k in range(2000)]
    assert sampling_w1(runs, None, 500, block=100) > 2 * sampling_w1(runs, None, 500)


def _case(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


GOOD = """\
case: x
source: {cite: c, url: https://example.org, licence: l}
radio: srsran-urllc
probe: {size: 100, interval: 10ms, measures: [uplink]}
variants:
  - name: v
    published: {uplink: {mean: 7.4}}
"""


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("radio: srsran-urllc", "radio: nope"), "radio.profile must name a radio"),
        (("{mean: 7.4}", "{median: 7.4}"), "variants[0].published.uplink: unknown key(s) median"),
        (("measures: [uplink]", "measures: [sideways]"), "probe.measures must list"),
        (("interval: 10ms", "interval: soon"), "probe.interval"),
        (("    published", "    radio: {sr_period: 3}\n    published"), "sr_period must be one"),
        (
            ("    published", "    radio: {profile: oai-tdd-30k, sched_offset: 0}\n    published"),
            "give both or neither",
        ),
        (("  - name: v\n", "  - nam: v\n"), "variants[0]: unknown key(s) nam"),
        (("case: x\n", ""), "`case` is missing"),
    ],
)
def test_a_bad_case_file_is_refused_by_file_and_key(
    tmp_path: Path, edit: tuple[str, str], message: str
) -> None:
    load_case(_case(tmp_path, GOOD))
    path = _case(tmp_path, GOOD.replace(*edit))
    with pytest.raises(FidelityError, match=r"bad\.yaml") as err:
        load_case(path)
    assert message in str(err.value)


def test_an_unknown_case_name_lists_the_library() -> None:
    with pytest.raises(FidelityError, match="srsran-urllc"):
        find(["no-such-case"])


def test_the_verb_without_root_judges_the_stages_and_writes_json(tmp_path: Path) -> None:
    out = tmp_path / "fid"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "testbed.cli",
            "fidelity",
            "srsran-urllc",
            "--model",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "variant SR-free access" in done.stdout
    data = json.loads((out / "fidelity.json").read_text())
    assert data["ok"] and data["cases"][0]["case"] == "srsran-urllc"
    assert (out / "srsran-urllc.png").stat().st_size > 10_000
    bad = subprocess.run(
        [sys.executable, "-m", "testbed.cli", "fidelity", "nope", "--model", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "no fidelity case nope" in bad.stdout + bad.stderr


@pytest.mark.root
@pytest.mark.measure
@pytest.mark.parametrize("name", CASES)
def test_a_shortened_case_through_the_relay(name: str) -> None:
    """Real packets through the relay in namespaces: the case's means, floors and components
    (HARQ share and step, segmented share) within their tolerances. A 3-second run's tails
    are too noisy to judge, and so is EDAF's median, which sits on a 2.5 ms step of its
    distribution: `make bench BENCH=fidelity` judges every figure at the case's own count.
    Nothing is left behind."""
    from pyroute2 import netns

    (case,) = find([name])
    (result,) = run_cases([shortened(case, 300)], real=True)
    judged_here = (" mean", "floor", "HARQ", "segmented")
    for judged in result.variants:
        for check in judged.checks:
            if any(word in check.what for word in judged_here):
                assert check.ok, (judged.variant, check)
    assert not [n for n in netns.listnetns() if n.startswith("elf-")]


def test_a_round_trip_is_the_uplink_then_the_downlink() -> None:
    """`rtt` sends each probe up, echoes it at the far end and brings it down, with the wired
    path both ways. The echo leaves at an uplink slot's end, so its downlink wait is that
    phase's, not a uniform one's: the mean lies between the uplink's mean plus the downlink's
    least and most."""
    radio = RADIO_PROFILES["srsran-urllc"]
    (case,) = find(["srsran-urllc"])
    probe = dataclasses.replace(case.probe, count=1000, interval_s=0.05)
    up = figures(model_delays(radio, probe, "uplink", wired_ms=2.0).delivered)
    down = figures(model_delays(radio, probe, "downlink", wired_ms=2.0).delivered)
    rtt = model_delays(radio, probe, "rtt", wired_ms=2.0)
    assert len(rtt.delivered) == 1000
    mean = figures(rtt.delivered)["mean"]
    assert up["mean"] + down["min"] - 0.01 <= mean <= up["mean"] + down["max"] + 0.01
    assert set(rtt.counters) == {"uplink", "downlink"}
