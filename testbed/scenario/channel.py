"""The loader's rules for cell sites and the `channel:` section, and where it applies them.

A cell's `site` is where it stands; `channel:` makes the vehicles' routes past those sites set
their air links' MCS and BLER (`testbed.mobility`). What must hold, each reported at its place
in the file:
- with `channel:` (and no `trace`), every cell has a site;
- no two sites stand within `MIN_SITE_SPACING_M` of each other (one mast, two cells would be
  one cell to the channel, and auto placement never does it);
- the timeline does not write an air link's `mcs` or `bler` (the channel does);
- a `trace` file exists and parses (`netem.channel.RadioTrace`, errors at its own lines);
- the radios the channel drives are ones it can model (30 kHz, a standard bandwidth).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from netem.channel import RadioTrace, RadioTraceError
from testbed.scenario import model, schema_v1
from testbed.scenario.kinds import Context, Items, Section

#: Two sites closer than this are "on top of each other".
MIN_SITE_SPACING_M = 1.0


def site(cell: Section) -> model.CellSite | str | None:
    """A cell's `site` value: a `CellSite`, "auto", or None (not written)."""
    value = cell.get("site")
    if isinstance(value, Section):
        built: model.CellSite = schema_v1.SITE.build(value)
        return built
    return value


def check_sites(ctx: Context, root: Section) -> None:
    """Every cell has a site when the channel needs one; no two sites on one spot."""
    topo: Section | None = root.get("topology")
    cells: Items | None = topo.get("cells") if topo is not None else None
    channel: Section | None = root.get("channel")
    needs = channel is not None and not channel.written("trace")
    placed: list[tuple[float, float, str]] = []
    for _, cell, _ in cells.good() if cells else ():
        value = cell.get("site")
        if value is None and needs:
            assert channel is not None
            where = channel.node.start_mark.line + 1
            ctx.add(
                cell.node,
                cell.path,
                f"a site (the channel at line {where} places the vehicles against every cell)",
                f"cell {cell.get('gnb')!r} without one",
                "add site: auto (along the route) or site: {x: 100, y: -20}",
            )
        if not isinstance(value, Section) or not value.clean:
            continue
        x, y = value["x"], value["y"]
        for ox, oy, path in placed:
            if math.hypot(x - ox, y - oy) < MIN_SITE_SPACING_M:
                ctx.add(
                    value.node,
                    value.path,
                    f"a site at least {MIN_SITE_SPACING_M:g} m from every other",
                    f"({x:g}, {y:g}), on top of {path} ({ox:g}, {oy:g})",
                    "two cells on one mast would be one cell to the channel; move one",
                )
        placed.append((x, y, value.path))


def check_timeline(ctx: Context, root: Section, link_kinds: dict[str, str]) -> None:
    """No `set` event writes an air link's mcs or bler while the channel sets them."""
    if root.get("channel") is None:
        return
    events: Items | None = root.get("timeline")
    for _, event, _ in events.good() if events else ():
        radio = event.get("radio") if event.tag == "set" else None
        if not isinstance(radio, Section) or link_kinds.get(event.get("set")) != "air":
            continue
        for key in ("mcs", "bler"):
            if radio.written(key):
                ctx.add(
                    radio.at(key),
                    radio.path_of(key),
                    f"no {key} on an air link: the channel sets it from the route",
                    f"{key} {radio[key]!r} on {event['set']}",
                    "drop it, or drop `channel:` to write the radio by hand",
                )


def spec(
    ctx: Context, root: Section, base_dir: Path, display_dir: Path
) -> model.ChannelSpec | None:
    """The `channel:` section built, its trace resolved and parsed; None when absent or wrong
    (reported)."""
    section: Section | None = root.get("channel")
    if section is None or not section.clean:
        return None
    built: model.ChannelSpec = schema_v1.CHANNEL.build(section)
    file = section.get("trace")
    if file is None:
        return built
    path = base_dir / file
    shown = str(display_dir / file)
    expected = "an existing radio trace CSV (relative to the scenario file)"
    if not path.is_file():
        why = "a directory" if path.is_dir() else "no such file"
        ctx.add(section.at("trace"), section.path_of("trace"), expected, f"{file!r} ({why})")
        return None
    try:
        RadioTrace.parse(path.read_text(encoding="utf-8", errors="replace"), shown)
    except RadioTraceError as err:
        mark = section.at("trace").start_mark
        for problem in err.problems:
            where, _, what = problem.partition(": ")
            _, _, line = where.rpartition(":")
            ctx.add(
                None,
                section.path_of("trace"),
                "a radio trace row (time_s,ue,rsrp_dbm,sinr_db,mcs[,cell])",
                what,
                f"trace named at {ctx.file}:{mark.line + 1}:{mark.column + 1}",
                file=shown,
                line=int(line) if line.isdigit() else None,
            )
        return None
    except OSError as err:
        ctx.add(section.at("trace"), section.path_of("trace"), expected, f"{file!r} ({err})")
        return None
    return dataclasses.replace(built, trace=path.resolve())


def apply(ctx: Context, root: Section, scenario: model.Scenario) -> model.Scenario | None:
    """`scenario` with the channel's radio (`testbed.mobility.with_channel`); None when the
    channel cannot be computed (reported at `channel:`)."""
    if scenario.channel is None:
        return scenario
    from testbed.mobility import MobilityError, with_channel

    try:
        return with_channel(scenario)
    except MobilityError as err:
        section: Section = root["channel"]
        ctx.add(
            section.node,
            "channel",
            "a channel this scenario's cells, radios and route can give",
            str(err),
        )
        return None
