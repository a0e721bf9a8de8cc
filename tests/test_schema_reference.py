"""`testbed schema --markdown`: the field reference covers every field of the JSON Schema.

The JSON Schema is walked here on its own (every property path, list items as `[]`, free keys
as `<name>`, each `$defs` entry rooted at `<name>`), so a field the reference's walk of the kinds
skipped shows up as missing.
"""

from __future__ import annotations

import json
from typing import Any

from typer.testing import CliRunner

from testbed.cli import app
from testbed.scenario import json_schema, reference

runner = CliRunner()

#: Fewer paths than this means the walk below lost its way, not that the schema shrank.
MIN_PATHS = 200


def _paths(schema: dict[str, Any], path: str, out: list[tuple[str, dict[str, Any]]]) -> None:
    if "$ref" in schema:  # walked from its `$defs` entry
        return
    for key, sub in schema.get("properties", {}).items():
        at = f"{path}.{key}" if path else key
        # A required key says so instead of a default (the model's default never applies).
        out.append((at, {**sub, "required": key in schema.get("required", ())}))
        _paths(sub, at, out)
    for alternative in [*schema.get("anyOf", []), *schema.get("oneOf", [])]:
        _paths(alternative, path, out)
    if isinstance(schema.get("items"), dict):
        _paths(schema["items"], path + "[]", out)
    if isinstance(schema.get("additionalProperties"), dict):
        _paths(schema["additionalProperties"], f"{path}.<name>", out)


def _all_paths() -> list[tuple[str, dict[str, Any]]]:
    schema = json_schema()
    out: list[tuple[str, dict[str, Any]]] = []
    _paths(schema, "", out)
    for name, sub in schema["$defs"].items():
        _paths(sub, f"<{name}>", out)
    return out


def _missing(markdown: str) -> list[str]:
    """The paths with no entry in `markdown` that carries their description, and their default
    or that they are required."""
    lines = markdown.splitlines()
    missing = []
    for path, prop in _all_paths():
        entries = [line for line in lines if f"`{path}`: " in line]
        if not any(prop["description"] in line for line in entries):
            missing.append(path)
        elif prop["required"]:
            if not any("; required." in line for line in entries):
                missing.append(path)
        elif "default" in prop:
            default = prop["default"]
            written = default if isinstance(default, str) else json.dumps(default)
            if not any(f"default `{written}`" in line for line in entries):
                missing.append(path)
    return missing


def test_the_walk_finds_the_whole_schema() -> None:
    paths = {path for path, _ in _all_paths()}
    assert len(paths) >= MIN_PATHS
    for path in ("links.backend", "topology.cells[].site.x", "timeline[].for", "<radio>.tdd"):
        assert path in paths
    assert "topology.hosts.<name>.address" in paths


def test_the_reference_has_every_field_with_its_doc_and_default() -> None:
    assert _missing(reference.markdown()) == []


def test_a_field_left_out_of_the_reference_is_found_missing() -> None:
    kept = [
        line
        for line in reference.markdown().splitlines()
        if not line.lstrip().startswith("- `links.backend`: ")
    ]
    assert _missing("\n".join(kept)) == ["links.backend"]


def test_the_reference_has_a_section_per_top_level_key_and_shared_mapping() -> None:
    markdown = reference.markdown()
    schema = json_schema()
    for key in schema["properties"]:
        assert f"\n## `{key}`\n" in markdown
    for name in schema["$defs"]:
        assert f"\n### `<{name}>`\n" in markdown


def test_schema_markdown_prints_the_reference() -> None:
    result = runner.invoke(app, ["schema", "--markdown"])
    assert result.exit_code == 0, result.output
    assert result.output == reference.markdown()
    assert "--markdown" in runner.invoke(app, ["schema", "--help"]).output
