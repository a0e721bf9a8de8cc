"""Broken scenarios: every error names file:line:column, the field path, and what was expected.

Each file in tests/bad_scenarios/ starts with a comment saying what its error must be:
    # expect: line=<n> path=<field path or -> [file=<trace file>] | <text the message contains>
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from testbed.cli.common import exit_code
from testbed.errors import BadInput
from testbed.scenario import Issue, ScenarioError, load, loads

BAD = Path(__file__).parent / "bad_scenarios"
HEADER = re.compile(
    r"^# expect: line=(?P<line>\d+) path=(?P<path>\S+)(?: file=(?P<file>\S+))? \| (?P<text>.+)$"
)


def _expectation(path: Path) -> re.Match[str]:
    # bytes: a case may be a file that is not UTF-8 after its (ASCII) first line
    first = path.read_bytes().split(b"\n", 1)[0].decode("ascii")
    m = HEADER.match(first)
    assert m, f"{path.name}: first line must be '# expect: line=N path=P | text', not {first!r}"
    return m


CASES = sorted(BAD.glob("*.yaml"))


def test_corpus_is_large_enough() -> None:
    assert len(CASES) >= 30


@pytest.mark.parametrize("case", CASES, ids=[c.stem for c in CASES])
def test_bad_scenario_reports_line_and_path(case: Path) -> None:
    expect = _expectation(case)
    line, path, text = int(expect["line"]), expect["path"], expect["text"]
    file = str(case.parent / expect["file"]) if expect["file"] else str(case)
    with pytest.raises(ScenarioError) as info:
        load(case)
    err = info.value
    field_path = "" if path == "-" else path
    matching = [i for i in err.issues if i.file == file and i.line == line and i.path == field_path]
    assert matching, f"no issue at {file}:{line} {path}; got:\n{err}"
    # The same facts, as a person reads them: one line with file:line:column, path and text.
    prefix = f"{file}:{line}:"
    lines = [m for m in str(err).splitlines() if m.startswith(prefix)]
    assert any((field_path == "" or f" {field_path}: " in m) and text in m for m in lines), (
        f"expected a line starting {prefix!r} with {path!r} and {text!r}; got:\n{err}"
    )
    assert all(i.column and i.column >= 1 for i in err.issues if i.line is not None)


def test_scenario_error_is_bad_input_with_exit_code_2() -> None:
    with pytest.raises(ScenarioError) as info:
        load(BAD / "rate_mbps.yaml")
    assert isinstance(info.value, BadInput)
    assert exit_code(info.value) == 2
    issue = info.value.issues[0]
    assert isinstance(issue, Issue)
    assert (issue.path, issue.found) == ("links.air.uplink.rate", "'20mbps'")
    assert issue.expected.startswith("a rate like 20mbit, 1.5gbit or 500kbit")
    assert (
        issue.hint == "'mbps' is ambiguous: tc reads it as megabytes/s; write 20mbit for megabits/s"
    )


BASE = """\
name: t
duration: 90s
topology:
  cells: [{gnb: gnb1, core: core1}]
  vehicles: [{name: av1, gnb: gnb1}]
"""


def _issues(text: str) -> list[Issue]:
    with pytest.raises(ScenarioError) as info:
        loads(text, source="t.yaml")
    return list(info.value.issues)


def test_all_errors_of_a_file_are_reported_in_line_order() -> None:
    text = BASE + (
        "links:\n"
        "  backend: netem\n"
        "  air:\n"
        "    uplink: {rate: 20mbps, jiter: 1ms}\n"
        "workload: {codec: fp32}\n"
    )
    issues = _issues(text)
    assert [(i.line, i.path) for i in issues] == [
        (7, "links.backend"),
        (9, "links.air.uplink.rate"),
        (9, "links.air.uplink.jiter"),
        (10, "workload.codec"),
    ]
    assert str(_err(text)).count("\n") == 3  # one message per line


def _err(text: str) -> ScenarioError:
    with pytest.raises(ScenarioError) as info:
        loads(text, source="t.yaml")
    return info.value


def test_a_bad_name_does_not_cascade_into_reference_errors() -> None:
    # av1's gNB name is malformed: that is one error, not also "unknown gNB" or "unknown link".
    text = BASE.replace("vehicles: [{name: av1, gnb: gnb1}]", "vehicles: [{name: av1, gnb: G1}]")
    text += "timeline:\n  - {at: 1s, set: av1-gnb1, delay: 9ms}\n"
    issues = _issues(text)
    assert [(i.line, i.path) for i in issues] == [(5, "topology.vehicles[0].gnb")]


def test_wrong_section_type_is_one_error() -> None:
    issues = _issues(BASE + "links: [air, backhaul]\n")
    assert [(i.line, i.path) for i in issues] == [(6, "links")]
    assert issues[0].found == "a list of 2 item(s)"


def test_time_checks_are_skipped_when_duration_is_broken() -> None:
    text = BASE.replace("90s", "90") + "timeline:\n  - {at: 100s, clear: av1}\n"
    assert [i.path for i in _issues(text)] == ["duration"]


def test_duplicate_key_names_the_first_occurrence() -> None:
    issues = _issues(BASE + "seed: 1\nseed: 2\n")
    assert [(i.line, i.path) for i in issues] == [(7, "seed")]
    assert "first on line 6" in issues[0].found


def test_merge_keys_are_not_duplicates_and_explicit_keys_win() -> None:
    text = BASE + (
        "x-air: &air {rate: 50mbit, delay: 8ms}\n"
        "links:\n  air:\n    uplink: {<<: *air, delay: 9ms}\n    downlink: *air\n"
    )
    s = loads(text)
    link = s.links.get("av1-gnb1")
    assert (link.uplink.rate_bps, link.uplink.delay_s) == (50e6, 0.009)
    assert link.downlink.delay_s == 0.008


def test_an_empty_file_and_a_list_are_refused() -> None:
    assert _issues("")[0].found == "an empty document"
    (issue,) = _issues("- name: x\n")
    assert (issue.line, issue.path, issue.found) == (1, "(top level)", "a list of 1 item(s)")


def test_missing_file_is_a_scenario_error(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="no such file"):
        load(tmp_path / "nope.yaml")
    with pytest.raises(ScenarioError, match="a directory"):
        load(tmp_path)
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"name: \xff\xfe\n")
    with pytest.raises(ScenarioError, match="UTF-8"):
        load(binary)


def test_control_characters_are_located() -> None:
    (issue,) = _issues("name: a\x01b\n")
    assert (issue.line, issue.column, issue.expected) == (1, 8, "printable text")


def test_two_documents_are_refused() -> None:
    (issue,) = _issues(BASE + "---\nname: u\n")
    assert issue.line == 6
    assert issue.expected == "valid YAML"


def test_unknown_key_without_close_match_has_no_hint() -> None:
    (issue,) = _issues(BASE + "colour: blue\n")
    assert (issue.path, issue.hint) == ("colour", None)
    assert issue.found == "unknown key 'colour'"


def test_extension_keys_are_allowed_for_anchors() -> None:
    assert loads(BASE + "x-notes: anything\n").name == "t"


def test_non_string_keys_are_refused() -> None:
    (issue,) = _issues(BASE + "1: one\n")
    assert issue.line == 6
    assert issue.found == "1"


def test_trace_errors_are_capped_per_file(tmp_path: Path) -> None:
    (tmp_path / "t.mahi").write_text("".join(f"x{i}\n" for i in range(20)))
    text = BASE + "timeline:\n  - {at: 0s, trace: av1-gnb1, direction: uplink, file: t.mahi}\n"
    with pytest.raises(ScenarioError) as info:
        loads(text, source="t.yaml", base_dir=tmp_path)
    trace_issues = [i for i in info.value.issues if i.file.endswith("t.mahi")]
    assert len(trace_issues) == 6
    assert trace_issues[-1].found == "15 more wrong line(s) from here on"
    assert all(i.hint == "trace named at t.yaml:7:56" for i in trace_issues)


def test_outage_shape_and_clear_checks_together() -> None:
    text = BASE + (
        "timeline:\n"
        "  - {at: 10s, outage: av1-gnb1, for: 0s}\n"
        "  - {at: 10s, shape: av1, uplink: unlimited}\n"
        "  - {at: 10s, clear: av1, uplink: 1mbit}\n"
    )
    assert [(i.line, i.path) for i in _issues(text)] == [
        (7, "timeline[0].for"),
        (8, "timeline[1].uplink"),
        (9, "timeline[2].uplink"),
    ]


def test_set_event_rejects_field_values_like_a_profile() -> None:
    text = BASE + "timeline:\n  - {at: 1s, set: av1-gnb1, queue: 2000000, reorder: maybe}\n"
    assert [i.path for i in _issues(text)] == ["timeline[0].queue", "timeline[0].reorder"]


def test_weights_file_must_exist(tmp_path: Path) -> None:
    text = BASE + "workload: {weights: model.pt}\n"
    with pytest.raises(ScenarioError, match=r"workload.weights: .*'model.pt' \(no such file\)"):
        loads(text, base_dir=tmp_path)


def test_splits_must_be_unique() -> None:
    issues = _issues(BASE + "workload: {splits: [a, b, a]}\n")
    assert [(i.line, i.path) for i in issues] == [(6, "workload.splits[2]")]


def test_traces_the_emulator_refuses_are_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A trace that passes the validator's checks but not the link emulator's own reader must
    # fail `validate` too, at the line the emulator names.
    from netem import traces as emulator_traces

    def refuse(text: str, source: str = "trace") -> None:
        raise ValueError(f"{source} line 3: time 5.0 s is not after the previous row (5.0 s)")

    monkeypatch.setattr(emulator_traces, "parse_csv", refuse)
    (tmp_path / "t.csv").write_text("time_s,mbit\n0,10\n5,2\n")
    text = BASE + "timeline:\n  - {at: 0s, trace: av1-gnb1, direction: uplink, file: t.csv}\n"
    with pytest.raises(ScenarioError) as info:
        loads(text, source="t.yaml", base_dir=tmp_path)
    (issue,) = info.value.issues
    assert (issue.file, issue.line, issue.path) == (str(tmp_path / "t.csv"), 3, "timeline[0].file")
    assert issue.found == "time 5.0 s is not after the previous row (5.0 s)"


def test_committed_traces_are_accepted_by_the_emulator() -> None:
    from netem.traces import load_trace

    traces = Path(__file__).resolve().parent.parent / "scenarios" / "traces"
    assert load_trace(traces / "uplink-steps.csv").steps[1] == (10.0, 8e6)
    assert load_trace(traces / "step-12-6mbit.mahi").duration_s == 1.0
