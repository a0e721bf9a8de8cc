"""The loader's rules for cell sites and the `channel:` section, and where it applies them.

A cell's `site` is where it stands; `channel:` makes the vehicles' routes past those sites set
their air links' MCS and BLER (`testbed.mobility`). What must hold, each reported at its place
in the file:
- with `channel:` (and no `trace`), every cell has a site;
- no two sites stand within `MIN_SITE_SPACING_M` of each other (one mast, two cells would be
  one cell to the channel, and auto placement never does it);
- the timeline does not write an air link's `mcs` or `bler` (the channel does);
- a `trace` file exists and parses (`netem.nr.channel.RadioTrace`, errors at its own lines);
- the radios the channel drives are ones it can model (30 kHz, a standard bandwidth);
- `handover` comes with the model (not a trace), two or more cells, all behind one UPF with
  their edge servers behind it (one or one per cell: `edge: stay | follow`), A3 settings
  within TS 38.331's ranges and steps, and no `shape` of a vehicle.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Literal

from netem.nr.channel import RadioTrace, RadioTraceError
from netem.nr.handover import FILTER_COEFFICIENTS, TTT_MS
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


def wants_handover(root: Section) -> bool:
    """Whether the file asks for handovers (then every vehicle gets an air link to every
    gNB: `model.Scenario.gnbs_of`)."""
    channel: Section | None = root.get("channel")
    return channel is not None and channel.get("handover") is not None


def check_handover(ctx: Context, root: Section) -> None:
    """`channel.handover`'s rules (see the module doc), each at its key."""
    channel: Section | None = root.get("channel")
    handover: Section | None = channel.get("handover") if channel is not None else None
    if channel is None or not isinstance(handover, Section):
        return
    where = channel.path_of("handover")
    if channel.written("trace"):
        ctx.add(
            channel.at("handover"),
            where,
            "handover with the channel model (sites and a route)",
            "handover beside a recorded `trace`",
            "a trace's rows carry their own serving cell; drop one of the two",
        )
    topo: Section | None = root.get("topology")
    cells: Items | None = topo.get("cells") if topo is not None else None
    good = [cell for _, cell, _ in cells.good()] if cells else []
    if cells is not None and len(good) < 2:
        ctx.add(
            channel.at("handover"),
            where,
            "two or more cells to hand over between",
            f"{len(good)} cell",
        )
    upfs = sorted({str(c.get("upf")) for c in good if c.get("upf")})
    plain = [c.get("gnb") for c in good if not c.get("upf")]
    at_cell = [c.get("gnb") for c in good if c.get("upf") and placement(c) == "cell"]
    if plain or at_cell or len(upfs) > 1:
        found = (
            f"cells without a UPF ({', '.join(map(str, plain))})"
            if plain
            else f"edge servers at the cell ({', '.join(map(str, at_cell))})"
            if at_cell
            else f"several UPFs ({', '.join(upfs)})"
        )
        ctx.add(
            channel.at("handover"),
            where,
            "cells behind one UPF, their edge servers behind it (upf, edge, placement core)",
            found,
            "a handover switches the UE's N3 tunnel at its UPF (an Xn handover's path switch);"
            " another UPF would need N9, and an edge at a cell an inter-cell path, neither of"
            " which is modelled",
        )
    vehicles: Items | None = topo.get("vehicles") if topo is not None else None
    names = {v.get("name") for _, v, _ in vehicles.good()} if vehicles else set()
    events: Items | None = root.get("timeline")
    for _, event, _ in events.good() if events else ():
        if event.tag == "shape" and event.get("shape") in names:
            ctx.add(
                event.at("shape"),
                event.path_of("shape"),
                "a shaped gNB, UPF or edge (with handovers a vehicle has one air link per gNB)",
                f"shape of vehicle {event['shape']!r}",
                "`shape` caps one interface; cap the air links with `set` (rate) instead",
            )
    for key, value, ok, expected in (
        ("offset", handover.get("offset"), _half_db, "a multiple of 0.5 dB (TS 38.331)"),
        ("hysteresis", handover.get("hysteresis"), _half_db, "a multiple of 0.5 dB (TS 38.331)"),
        (
            "ttt",
            handover.get("ttt"),
            lambda v: round(v * 1000) in TTT_MS and abs(v * 1000 - round(v * 1000)) < 1e-6,
            f"one of TS 38.331's TimeToTrigger values ({', '.join(map(str, TTT_MS))} ms)",
        ),
        (
            "filter",
            handover.get("filter"),
            lambda v: v in FILTER_COEFFICIENTS,
            "one of TS 38.331's FilterCoefficient values "
            f"({', '.join(map(str, FILTER_COEFFICIENTS))})",
        ),
    ):
        if handover.written(key) and value is not None and not ok(value):
            shown = f"{value * 1000:g} ms" if key == "ttt" else f"{value!r}"
            ctx.add(handover.at(key), handover.path_of(key), expected, shown)


def _half_db(value: float) -> bool:
    return bool((value * 2).is_integer())


def placement(cell: Section) -> Literal["core", "cell"]:
    """Where a cell's edge server is written to stand (`edge: {placement: ...}`; core if not)."""
    edge = cell.get("edge")
    return edge.get("placement", "core") if isinstance(edge, Section) else "core"
