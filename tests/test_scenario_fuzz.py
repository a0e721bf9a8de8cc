"""Property: whatever a person does to a valid scenario, the loader answers with a Scenario or
a ScenarioError (file:line, field, expectation), never with another exception."""

from __future__ import annotations

from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from testbed.scenario import ScenarioError, loads
from testbed.scenario.model import Scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
VALID = [(p.name, p.read_text()) for p in sorted(SCENARIOS.glob("*.yaml"))]

#: Values people mistype into fields: wrong types, units, signs, sizes, YAML oddities.
ODD_VALUES = [
    "0",
    "-1",
    "1e309",
    "nan",
    ".inf",
    "20mbps",
    "8 ms",
    "-5ms",
    "150%",
    "~",
    "null",
    "[]",
    "{}",
    "yes",
    "'av1'",
    "gnb9",
    "10.0.0.0/33",
    "!!python/object:os.system",
    "&a",
    "*a",
    '""',
    "''",
    "1_000",
    "0x10",
    "12:30",
    "20mbit/s",
    "unlimited",
    "3.5",
    "true",
]


def _mutate(text: str, data: st.DataObject) -> str:
    lines = text.splitlines()
    kind = data.draw(st.sampled_from(["value", "delete", "duplicate", "indent", "chars", "key"]))
    i = data.draw(st.integers(0, len(lines) - 1))
    line = lines[i]
    if kind == "value" and ":" in line:
        head = line.split(":", 1)[0]
        lines[i] = f"{head}: {data.draw(st.sampled_from(ODD_VALUES))}"
    elif kind == "delete":
        del lines[i]
    elif kind == "duplicate":
        lines.insert(i, line)
    elif kind == "indent":
        lines[i] = data.draw(st.sampled_from(["", " ", "   ", "\t"])) + line.lstrip()
    elif kind == "key" and ":" in line:
        key, rest = line.split(":", 1)
        word = data.draw(st.text(alphabet="abcdefghijklmnopqrstuvwxyz_-", min_size=1, max_size=9))
        lines[i] = f"{key[: len(key) - len(key.lstrip())]}{word}:{rest}"
    else:
        pos = data.draw(st.integers(0, len(line)))
        junk = data.draw(st.text(alphabet=":-[]{},#&*!|>'\"%@ \t0123456789abc", max_size=4))
        lines[i] = line[:pos] + junk + line[pos + 1 :]
    return "\n".join(lines) + "\n"


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_mutated_scenarios_load_or_fail_cleanly(data: st.DataObject) -> None:
    name, text = data.draw(st.sampled_from(VALID))
    for _ in range(data.draw(st.integers(1, 3))):
        text = _mutate(text, data)
    try:
        scenario = loads(text, source=f"mutated-{name}", base_dir=SCENARIOS)
    except ScenarioError as err:
        message = str(err)
        assert message.startswith(f"mutated-{name}:"), message
        assert all(issue.line >= 1 for issue in err.issues)
        return
    assert isinstance(scenario, Scenario)


def test_the_mutation_corpus_is_valid_yaml_to_start_with() -> None:
    for _, text in VALID:
        assert isinstance(yaml.safe_load(text), dict)
        assert isinstance(loads(text, base_dir=SCENARIOS), Scenario)
