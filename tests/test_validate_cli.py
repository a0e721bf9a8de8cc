"""`testbed validate` and `testbed schema`, and the committed JSON Schema."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
import yaml
from typer.testing import CliRunner

from testbed.cli import app
from testbed.scenario import json_schema

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "scenarios"
BAD = Path(__file__).resolve().parent / "bad_scenarios"
COMMITTED = sorted(SCENARIOS.glob("*.yaml"))

runner = CliRunner()


def test_validate_accepts_the_committed_scenarios() -> None:
    result = runner.invoke(app, ["validate", *map(str, COMMITTED)])
    assert result.exit_code == 0, result.output
    for path in COMMITTED:
        assert f"{path}: valid" in result.output


@pytest.mark.parametrize(
    ("name", "line", "path"),
    [
        ("gnb_undefined", 11, "topology.vehicles[1].gnb"),
        ("rate_mbps", 11, "links.air.uplink.rate"),
        ("set_field_typo", 14, "timeline[0].dealy"),
        ("trace_missing_file", 14, "timeline[0].file"),
    ],
)
def test_validate_exits_2_and_names_line_and_path(name: str, line: int, path: str) -> None:
    bad = BAD / f"{name}.yaml"
    result = runner.invoke(app, ["validate", str(bad)])
    assert result.exit_code == 2
    assert f"{bad}:{line}:" in result.output
    assert f" {path}: expected " in result.output
    assert "Traceback" not in result.output


def test_validate_checks_every_file_and_reports_each_bad_one() -> None:
    good, bad1, bad2 = COMMITTED[0], BAD / "rate_mbps.yaml", BAD / "no_action.yaml"
    result = runner.invoke(app, ["validate", str(bad1), str(good), str(bad2)])
    assert result.exit_code == 2
    assert f"{good}: valid" in result.output
    assert f"{bad1}:11:" in result.output
    assert f"{bad2}:14:" in result.output


def test_validate_a_missing_file_is_bad_input(tmp_path: Path) -> None:
    result = runner.invoke(app, ["validate", str(tmp_path / "nope.yaml")])
    assert result.exit_code == 2
    assert "no such file" in result.output


def test_validate_locates_a_byte_that_is_not_utf8(tmp_path: Path) -> None:
    # line 3 holds two 2-byte characters before the bad byte: its column counts characters
    # (as every other issue's does), the byte offset counts bytes
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes(b"name: t\nduration: 90s\n# \xc3\xa9t\xc3\xa9!\xff\n")
    result = runner.invoke(app, ["validate", str(bad)])
    assert result.exit_code == 2
    assert f"{bad}:3:7: expected a UTF-8 text file, found byte 0xff at byte offset 30" in (
        result.output
    )
    assert "Traceback" not in result.output


def test_validate_as_a_process() -> None:
    # The real entry point: exit status and stderr as a shell sees them.
    bad = BAD / "duplicate_key.yaml"
    proc = subprocess.run(
        [sys.executable, "-m", "testbed.cli", "validate", str(bad)],
        capture_output=True,
        text=True,
        check=False,
        cwd=ROOT,
    )
    assert proc.returncode == 2
    assert proc.stderr.startswith(f"error: {bad}:14:")
    assert "links.air.uplink.delay" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_schema_command_prints_the_committed_schema() -> None:
    result = runner.invoke(app, ["schema"])
    assert result.exit_code == 0
    printed = json.loads(result.output)
    committed = json.loads((SCENARIOS / "scenario.schema.json").read_text())
    assert printed == committed == json_schema(), (
        "scenarios/scenario.schema.json is out of date: run "
        "`testbed schema > scenarios/scenario.schema.json`"
    )


def test_schema_is_a_valid_draft_2020_12_schema() -> None:
    schema = json_schema()
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)


def _objects(schema: object) -> list[dict]:
    """Every object schema inside `schema`."""
    found: list[dict] = []
    if isinstance(schema, dict):
        if schema.get("type") == "object":
            found.append(schema)
        for value in schema.values():
            found += _objects(value)
    elif isinstance(schema, list):
        for value in schema:
            found += _objects(value)
    return found


def test_every_object_is_closed_and_every_property_documented() -> None:
    objects = _objects(json_schema())
    assert len(objects) >= 15
    for obj in objects:
        if "propertyNames" in obj:  # a map of free keys (an app's env): each key checked
            assert obj["propertyNames"]["pattern"] and obj["additionalProperties"]
            continue
        assert obj["additionalProperties"] is False
        assert obj["description"]
        for key, prop in obj["properties"].items():
            assert prop.get("description"), key


def _validator() -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(json_schema())


@pytest.mark.parametrize("path", COMMITTED, ids=lambda p: p.name)
def test_committed_scenarios_validate_against_the_schema(path: Path) -> None:
    errors = list(_validator().iter_errors(yaml.safe_load(path.read_text())))
    assert errors == []


@pytest.mark.parametrize(
    "name",
    [
        "unknown_key_typo",
        "rate_mbps",
        "delay_uppercase_unit",
        "jitter_distribution_typo",
        "backend_unknown",
        "node_name_uppercase",
        "two_actions",
        "no_action",
        "shape_no_direction",
        "version_2",
        "report_format",
        "no_vehicles",
        "duration_no_unit",
    ],
)
def test_broken_scenarios_fail_the_schema_too(name: str) -> None:
    data = yaml.safe_load((BAD / f"{name}.yaml").read_text())
    assert list(_validator().iter_errors(data)), f"{name} should not validate"
