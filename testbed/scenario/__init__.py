"""Scenarios: the YAML format (schema v1), its loader and its JSON Schema.

    from testbed.scenario import load, ScenarioError
    scenario = load("scenarios/default.yaml")   # a typed model.Scenario, SI units

`ScenarioError` (a `BadInput`, exit code 2) lists every problem of a file as
`file:line:column: field.path: expected ..., found ...`; `.issues` holds them as `Issue`s.
"""

from typing import TYPE_CHECKING

from testbed.lazyexports import lazy

if TYPE_CHECKING:
    from testbed.scenario.issues import Issue, ScenarioError
    from testbed.scenario.loader import load, loads
    from testbed.scenario.rules_links import profile_changes
    from testbed.scenario.schema_v1 import json_schema

lazy(
    __name__,
    {
        "Issue": "issues",
        "ScenarioError": "issues",
        "load": "loader",
        "loads": "loader",
        "profile_changes": "rules_links",
        "json_schema": "schema_v1",
    },
)

__all__ = ["Issue", "ScenarioError", "json_schema", "load", "loads", "profile_changes"]
