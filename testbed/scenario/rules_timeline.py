"""The rules of `timeline:`: events inside the run, naming nodes and links of the topology.

`set` events with a radio are laid in time order over the radio the link has then, and keep
their cell's slot grid; an outage ends by the end of the run; a `trace` file exists and
parses as the link emulator parses it.
"""

from __future__ import annotations

import dataclasses
import re

from netem.directions import DIRECTIONS, directions
from netem.nr.radio import Radio
from netem.traces import TraceError, TraceProblem, default_format
from testbed import units
from testbed.scenario import model, radios
from testbed.scenario.building import Builder
from testbed.scenario.kinds import Items, Section
from testbed.scenario.rules_links import off_grid, profile_changes, radio_of
from testbed.scenario.rules_topology import check_link, check_node


def _trace_problems(text: str, fmt: str) -> list[TraceProblem]:
    """The wrong lines of a trace, as the link emulator's own parser (`netem.traces`, the only
    trace parser) finds them, so a trace that validates is one a run accepts."""
    from netem import traces as emulator_traces

    try:
        if fmt == "csv":
            emulator_traces.parse_csv(text, source="")
        else:
            emulator_traces.parse_mahimahi(text, source="")
    except TraceError as err:
        return list(err.problems)
    except ValueError as err:  # a message without structured problems: `line N: text`
        m = re.match(r"^ ?line (\d+): (.*)$", str(err))
        if m:
            return [TraceProblem(int(m[1]), "a line the link emulator accepts", m[2], m[2])]
        text = str(err).lstrip(": ")
        return [TraceProblem(1, "a trace the link emulator accepts", text, text)]
    return []


def build(b: Builder) -> list[model.Event]:
    """The events that checked out, the `set` events with a radio last (`_radio_sets`)."""
    events: Items | None = b.root.get("timeline")
    out: list[model.Event] = []
    radio_sets: list[tuple[model.SetEvent, Section]] = []
    for _, event, node in events.good() if events else ():
        if event.tag is None:
            continue
        built = _event(b, event, node.start_mark.line + 1)
        if isinstance(built, model.SetEvent) and "radio" in event:
            radio_sets.append((built, event))
        elif built is not None:
            out.append(built)
    return out + _radio_sets(b, radio_sets)


def _radio_sets(b: Builder, sets: list[tuple[model.SetEvent, Section]]) -> list[model.Event]:
    """`set` events with their radios: in time order, a mapping changes the radio the
    link has then (its profile's, or the last `set`'s). Where the two directions of a
    `both` event end up with different radios, it becomes one event per direction. A
    radio that leaves its cell's slot grid is refused: one gNB, one grid."""
    if not b.link_specs:
        return []  # the links did not check out: reported there
    now = {(s.name, d): s.profile(d).radio for s in b.link_specs.values() for d in DIRECTIONS}
    out: list[model.Event] = []
    for event, section in sorted(sets, key=lambda p: (p[0].at_s, p[0].line)):
        if event.link not in b.link_specs:
            continue  # an unknown link: the event's own check reported it
        built: dict[str, Radio | None] = {}
        for d in directions(event.direction):
            radio = radio_of(section["radio"], section, b.ctx, now[event.link, d])
            if radio is False:
                break
            assert radio is not True
            if not _grid_kept(b, event.link, d, radio, now, section):
                break
            built[d] = radio
        else:
            for d, radio in built.items():
                now[event.link, d] = radio
            values = list(built.values())
            if len(values) == 1 or values[0] == values[1]:
                changes = {**event.changes, "radio": values[0]}
                out.append(dataclasses.replace(event, changes=changes))
            else:
                out += [
                    dataclasses.replace(event, direction=d, changes={**event.changes, "radio": r})
                    for d, r in built.items()
                ]
    return out


def _grid_kept(
    b: Builder,
    link: str,
    direction: str,
    radio: Radio | None,
    now: dict[tuple[str, str], Radio | None],
    section: Section,
) -> bool:
    """Whether `radio` on `link` keeps the slot grid of the other UEs of its cell."""
    spec = b.link_specs[link]
    if spec.kind != "air" or radio is None:
        return True
    for other in b.link_specs.values():
        theirs = now[other.name, direction]
        if other.name == link or other.upper != spec.upper or theirs is None:
            continue
        if radios.grid(theirs) != radios.grid(radio):
            off_grid(
                b, section, spec, direction, radio, (f"{other.name} then", theirs),
                "a set event changes one UE; a cell's TDD pattern stays as it started",
            )  # fmt: skip
            return False
    return True


def _check_time(b: Builder, event: Section) -> None:
    at = event.get("at")
    if at is None or b.duration is None or at <= b.duration:
        return
    b.ctx.add(
        event.at("at"),
        event.path_of("at"),
        f"a time within the run (0s to duration {units.format_duration(b.duration)})",
        repr(event.at("at").value),
    )


def _event(b: Builder, event: Section, line: int) -> model.Event | None:
    _check_time(b, event)
    at = event.get("at")
    if event.tag == "set":
        check_link(b, event, "set")
        if not event.clean:
            return None
        changes = profile_changes(event, b.ctx, with_radio=False)  # see _radio_sets
        return model.SetEvent(at, event["set"], event["direction"], changes, line=line)
    if event.tag == "shape":
        check_node(b, event, "shape")
        if not event.clean:
            return None
        return model.ShapeEvent(
            at, event["shape"], event.get("uplink"), event.get("downlink"), line=line
        )
    if event.tag == "clear":
        check_node(b, event, "clear")
        return model.ClearEvent(at, event["clear"], line=line) if event.clean else None
    if event.tag == "outage":
        check_link(b, event, "outage")
        length = event.get("for")
        known = at is not None and length is not None and b.duration is not None
        if known and at <= b.duration < at + length:
            b.ctx.add(
                event.at("for"),
                event.path_of("for"),
                f"an outage that ends by the end of the run ({units.format_duration(b.duration)})",
                f"{event.at('for').value!r} (ending at {units.format_duration(at + length)})",
            )
        return model.OutageEvent(at, event["outage"], length, line=line) if event.clean else None
    return _trace(b, event, line)


def _trace(b: Builder, event: Section, line: int) -> model.TraceEvent | None:
    check_link(b, event, "trace")
    file = event.get("file")
    if file is None:
        return None
    path = b.base_dir / file
    shown = str(b.display_dir / file)
    fmt = event.get("format") or default_format(file)
    expected = f"an existing {fmt} trace file (relative to the scenario file)"
    if not path.is_file():
        why = "a directory" if path.is_dir() else "no such file"
        b.ctx.add(event.at("file"), event.path_of("file"), expected, f"{file!r} ({why})")
        return None
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        b.ctx.add(event.at("file"), event.path_of("file"), expected, f"{file!r} ({err.strerror})")
        return None
    problems = _trace_problems(text, fmt)
    where = event.at("file").start_mark
    for problem in problems:
        b.ctx.add(
            None,
            event.path_of("file"),
            f"{problem.expected} ({fmt} trace)",
            problem.found,
            f"trace named at {b.ctx.file}:{where.line + 1}:{where.column + 1}",
            file=shown,
            line=problem.line,
        )
    if problems or not event.clean:
        return None
    return model.TraceEvent(
        event["at"],
        event["trace"],
        event["direction"],
        path.resolve(),
        fmt,
        loop=event["loop"],
        line=line,
    )
