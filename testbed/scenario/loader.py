"""Scenario files -> `Scenario`: parse YAML keeping positions, check it, convert to SI units.

Three passes, each reporting `Issue`s with file:line:column and the field path:
1. YAML syntax (PyYAML's composer keeps every node's position; nothing is constructed that
   is not a plain scalar, so loading never runs anything);
2. the declarations of `schema_v1.py`, made of the kinds of `kinds.py` (types, units, ranges,
   allowed values, unknown and duplicate keys);
3. the rules that join fields, one module per section of the file, which `Builder` calls in
   the file's order: `rules_topology` (names defined once and referred to correctly),
   `rules_links`, `rules_timeline` (times inside the run, trace files that exist and parse),
   `rules_workload` (paths relative to the file), `channel` and `programs`.
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
        scenario = Builder(ctx, section, base_dir, display_dir, path).build()
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


class Builder:
    """Checks the rules between fields, section by section in the order of the file, and
    builds the `Scenario` when nothing is wrong. It holds what the sections' rules share."""

    def __init__(
        self, ctx: Context, root: Section, base_dir: Path, display_dir: Path, path: Path | None
    ) -> None:
        self.ctx, self.root = ctx, root
        self.base_dir, self.display_dir, self.path = base_dir, display_dir, path
        self.duration: float | None = root.get("duration")
        self.roles: dict[str, str] = {}  # node name -> vehicle | gnb | core
        self.topology_ok = False  # every node known: references to unknown names are errors
        self.link_kinds: dict[str, str] = {}  # link name -> air | backhaul
        self.link_specs: dict[str, model.LinkSpec] = {}  # the links, once they checked out
        # node -> (its host, the field path and YAML node where it is listed): `topology.hosts`
        self.placed: dict[str, tuple[str, str, Node]] = {}

    def build(self) -> model.Scenario | None:
        topology = rules_topology.build(self)
        links = rules_links.build(self)
        if topology is not None and links is not None:
            rules_topology.check_links_across_hosts(self, topology, links)
        timeline = rules_timeline.build(self)
        workload = rules_workload.build(self)
        channel.check_sites(self.ctx, self.root)
        channel.check_timeline(self.ctx, self.root, self.link_kinds)
        channel.check_handover(self.ctx, self.root)
        channel_spec = channel.spec(self.ctx, self.root, self.base_dir, self.display_dir)
        record, report = self.root.get("record"), self.root.get("report")
        if record is not None:
            rules_topology.check_links_named(self, record, "pcap")
        if report is not None:
            rules_topology.check_links_named(self, report, "link_test")
        check_node = functools.partial(rules_topology.check_node, self)
        programs = Programs(self.ctx, self.base_dir, self.duration, check_node)
        apps = programs.apps(self.root.get("apps"))
        traffic = programs.traffic(self.root.get("traffic"))
        topics = programs.topics(record.get("topics") if record is not None else None)
        if self.ctx.issues or topology is None or links is None:
            return None
        built_record = record.obj.build(record) if record else model.Record()
        scenario = model.Scenario(
            name=self.root["name"],
            seed=self.root["seed"],
            duration_s=self.root["duration"],
            topology=topology,
            links=links,
            timeline=tuple(sorted(timeline, key=lambda e: e.at_s)),
            workload=workload,
            record=dataclasses.replace(built_record, topics=topics),
            report=report.obj.build(report) if report else model.Report(),
            apps=apps,
            traffic=traffic,
            channel=channel_spec,
            source=self.path,
            version=self.root["version"],
        )
        return channel.apply(self.ctx, self.root, scenario)
