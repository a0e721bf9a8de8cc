"""Schema v1, declared once: every field of a scenario file, its kind, unit, default, allowed
values and doc string.

`SCENARIO` is the whole file: `topology` (cells and vehicles), `links` (backend, air and
backhaul profiles, per-link overrides), `timeline` (set / shape / clear / outage / trace
events), `workload` (learner, fusion, Kalman), `record` and `report`. The loader checks a file
against it (`SCENARIO.check`) and builds the model dataclasses from the sections
(`CELL.build`...); `json_schema()` is what `testbed schema` writes. Defaults come from the
dataclasses of `model.py`; the kinds themselves (how a duration or a mapping is checked) are
in the `kinds` package, the rules that join fields in the `rules_*` modules. Each section is
declared in its own module here; this face holds `SCENARIO` and re-exports what importers use.
"""

from __future__ import annotations

from typing import Any

from testbed.scenario.kinds import Const, Duration, Either, Field, Int, ListOf, Obj, Str
from testbed.scenario.patterns import (
    LINK_NAME_PATTERN,
    NODE_NAME_PATTERN,
    SCENARIO_NAME_PATTERN,
)
from testbed.scenario.schema_v1.apps import APP, TRAFFIC
from testbed.scenario.schema_v1.channel import CHANNEL, HANDOVER
from testbed.scenario.schema_v1.links import LINKS, PROFILE
from testbed.scenario.schema_v1.radio import RADIO, RRC
from testbed.scenario.schema_v1.record import RECORD, REPORT
from testbed.scenario.schema_v1.shared import MAX_DURATION_S, WORKLOAD_KIND
from testbed.scenario.schema_v1.timeline import EVENT
from testbed.scenario.schema_v1.topology import CELL, SITE, TOPOLOGY, VEHICLE
from testbed.scenario.schema_v1.workload import WORKLOAD

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

SCENARIO = Obj(
    "An edgeloc-testbed scenario (schema v1): topology, links, timeline, workload.",
    [
        Field(
            "version",
            Const(1, "1 (this testbed reads schema v1)"),
            "Schema version.",
            default=1,
        ),
        Field(
            "name",
            Str(
                "a scenario name: lowercase letters, digits, '_' or '-', up to 32 characters",
                SCENARIO_NAME_PATTERN,
                "the name is used in run folders and reports",
            ),
            "Scenario name (used in run folders and reports).",
            required=True,
        ),
        Field("seed", Int(0, 2**32 - 1, noun="a seed"), "Seed of every random choice.", default=0),
        Field(
            "duration",
            Duration(MAX_DURATION_S, lo_open=True, noun="a run length"),
            "How long the run lasts.",
            required=True,
        ),
        Field("topology", TOPOLOGY, "Nodes of the emulated network.", required=True),
        Field("links", LINKS, "Link behaviour."),
        Field("timeline", ListOf(EVENT), "Link and shaping changes during the run."),
        Field("channel", CHANNEL, "Radio from the vehicles' routes and the cells' sites."),
        Field(
            "workload",
            Either(WORKLOAD_KIND, WORKLOAD),
            "The built-in workload: edgeloc (default), none (apps and traffic only), or a"
            " mapping of EdgeLoc's settings.",
        ),
        Field("apps", ListOf(APP), "Processes you bring, each in a namespace of the topology."),
        Field("traffic", ListOf(TRAFFIC), "Cross-traffic flows between nodes."),
        Field("record", RECORD, "Recording."),
        Field("report", REPORT, "Report."),
    ],
    extensions=True,
)


def json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of scenario files, derived from the declarations above."""
    defs: dict[str, Any] = {}
    body = SCENARIO.schema(defs)
    return {
        "$schema": JSON_SCHEMA_DIALECT,
        "$id": "https://edgeloc-testbed.invalid/scenario.schema.json",
        "title": "edgeloc-testbed scenario, schema v1",
        **body,
        "$defs": dict(sorted(defs.items())),
    }


__all__ = [
    "APP",
    "CELL",
    "CHANNEL",
    "EVENT",
    "HANDOVER",
    "LINKS",
    "LINK_NAME_PATTERN",
    "NODE_NAME_PATTERN",
    "PROFILE",
    "RADIO",
    "RECORD",
    "REPORT",
    "RRC",
    "SCENARIO",
    "SITE",
    "TOPOLOGY",
    "TRAFFIC",
    "VEHICLE",
    "WORKLOAD",
    "json_schema",
]
