"""Scenario files -> `Scenario`: parse YAML keeping positions, check it, convert to SI units.

Three passes, each reporting `Issue`s with file:line:column and the field path:
1. YAML syntax (PyYAML's composer keeps every node's position; nothing is constructed that
   is not a plain scalar, so loading never runs anything);
2. the declarations of `schema_v1`, made of the kinds of `kinds` (types, units, ranges,
   allowed values, unknown and duplicate keys);
3. the rules that join fields, one module per section of the file, each handed the file's
   `building.Builder` (what they share) in the file's order: `rules_topology` (names defined
   once and referred to correctly), `rules_links`, `rules_timeline` (times inside the run,
   trace files that exist and parse), `rules_workload` (paths relative to the file),
   `channel` and `programs`.
All issues of a file are collected; a rule that depends on a broken part is skipped rather
than piling up errors that only repeat the first one.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import yaml
from yaml.nodes import Node

from testbed.scenario import (
    channel,
    model,
    rules_links,
    rules_timeline,
    rules_topology,
    rules_workload,
    schema_v1,
)
from testbed.scenario.building import Builder
from testbed.scenario.issues import ROOT_PATH, Issue, ScenarioError
from testbed.scenario.kinds import Context, Invalid, Section
from testbed.scenario.programs import Programs

__all__ = ["load", "loads"]


def load(path: str | Path) -> model.Scenario:
    """Read and check a scenario file; raise `ScenarioError` listing everything wrong."""
    path = Path(path)
    shown = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise _file_error(shown, "an existing scenario file", "no such file") from None
    except IsADirectoryError:
        raise _file_error(shown, "a scenario file", "a directory") from None
    except UnicodeDecodeError as err:
        raise ScenarioError([_undecodable(shown, err)]) from None
    except OSError as err:
        raise _file_error(shown, "a readable scenario file", err.strerror or str(err)) from None
    return _load(text, shown, path.parent, path.parent, path)


def loads(
    text: str, source: str = "<string>", base_dir: str | Path | None = None
) -> model.Scenario:
    """Check scenario YAML given as text. `source` names it in messages; relative paths in it
    (traces, dataset, weights) are resolved against `base_dir` (default: the current folder)."""
    base = Path(base_dir) if base_dir is not None else Path.cwd()
    display = Path(base_dir) if base_dir is not None else Path()
    return _load(text, source, base, display, None)


def _file_error(file: str, expected: str, found: str) -> ScenarioError:
    return ScenarioError([Issue(file, None, None, "", expected, found)])


def _undecodable(file: str, err: UnicodeDecodeError) -> Issue:
    """Where the first byte that is not UTF-8 is: line and column (in characters, as PyYAML
    counts them for every other issue) and its byte offset, which an editor can jump to."""
    data = bytes(err.object)
    line_start = data.rfind(b"\n", 0, err.start) + 1
    line = data.count(b"\n", 0, err.start) + 1
    # the line's bytes before the bad one are valid UTF-8: the error is at the first bad byte
    column = len(data[line_start : err.start].decode("utf-8")) + 1
    return Issue(
        file,
        line,
        column,
        "",
        "a UTF-8 text file",
        f"byte 0x{data[err.start]:02x} at byte offset {err.start}, which is not UTF-8 "
        f"({err.reason})",
    )


def _load(
    text: str, source: str, base_dir: Path, display_dir: Path, path: Path | None
) -> model.Scenario:
    ctx = Context(source)
    root = _compose(text, ctx)
    section: Section | None = None
    if root is not None:
        try:
            section = schema_v1.SCENARIO.check(root, ctx, "")
        except Invalid as err:
            ctx.add(root, ROOT_PATH, err.expected, err.found, err.hint)
    elif not ctx.issues:
        ctx.issues.append(
            Issue(source, 1, 1, ROOT_PATH, schema_v1.SCENARIO.expected, "an empty document")
        )
    scenario = None
    if section is not None:
        scenario = _build(Builder(ctx, section, base_dir, display_dir, path))
    if ctx.issues or scenario is None:
        issues = sorted(
            ctx.issues, key=lambda i: (i.file != source, i.file, i.line or 0, i.column or 0)
        )
        raise ScenarioError(issues)
    return scenario


def _compose(text: str, ctx: Context) -> Node | None:
    """The YAML node tree, or None (with an issue) when the text is not YAML."""
    try:
        return yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        problem = err.problem or "a syntax error"
        context = (
            f"{err.context} (line {err.context_mark.line + 1})"
            if err.context and err.context_mark
            else err.context
        )
        ctx.issues.append(
            Issue(
                ctx.file,
                mark.line + 1 if mark else None,
                mark.column + 1 if mark else None,
                "",
                "valid YAML",
                f"a syntax error: {problem}",
                context,
            )
        )
    except yaml.reader.ReaderError as err:
        before = text[: err.position]
        line = before.count("\n") + 1
        column = err.position - (before.rfind("\n") + 1) + 1
        ctx.issues.append(
            Issue(ctx.file, line, column, "", "printable text", f"character {err.character!r}")
        )
    except yaml.YAMLError as err:  # pragma: no cover - every PyYAML error above carries a mark
        ctx.issues.append(Issue(ctx.file, None, None, "", "valid YAML", str(err)))
    return None


# ---- rules that join fields -----------------------------------------------------------------


def _build(b: Builder) -> model.Scenario | None:
    """The section rules in the order of the file, then the `Scenario` when none complained."""
    topology = rules_topology.build(b)
    links = rules_links.build(b)
    if topology is not None and links is not None:
        rules_topology.check_links_across_hosts(b, topology, links)
    timeline = rules_timeline.build(b)
    workload = rules_workload.build(b)
    channel.check_sites(b.ctx, b.root)
    channel.check_timeline(b.ctx, b.root, b.link_kinds)
    channel.check_handover(b.ctx, b.root)
    channel_spec = channel.spec(b.ctx, b.root, b.base_dir, b.display_dir)
    record, report = b.root.get("record"), b.root.get("report")
    if record is not None:
        rules_topology.check_links_named(b, record, "pcap")
    if report is not None:
        rules_topology.check_links_named(b, report, "link_test")
    check_node = functools.partial(rules_topology.check_node, b)
    programs = Programs(b.ctx, b.base_dir, b.duration, check_node)
    apps = programs.apps(b.root.get("apps"))
    traffic = programs.traffic(b.root.get("traffic"))
    topics = programs.topics(record.get("topics") if record is not None else None)
    if b.ctx.issues or topology is None or links is None:
        return None
    built_record = record.obj.build(record) if record else model.Record()
    scenario = model.Scenario(
        name=b.root["name"],
        seed=b.root["seed"],
        duration_s=b.root["duration"],
        topology=topology,
        links=links,
        timeline=tuple(sorted(timeline, key=lambda e: e.at_s)),
        workload=workload,
        record=dataclasses.replace(built_record, topics=topics),
        report=report.obj.build(report) if report else model.Report(),
        apps=apps,
        traffic=traffic,
        channel=channel_spec,
        source=b.path,
        version=b.root["version"],
    )
    return channel.apply(b.ctx, b.root, scenario)
