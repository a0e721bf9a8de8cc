"""The rules of `links:`: each link kind's default profiles, the overrides, and the radios.

`profile_changes` turns the profile keys of a section (here and in `set` events) into
`LinkProfile` fields. A link's profiles are laid from its kind's defaults, its override and
its cell's `radio` (the slot grid and carrier); the radio they add up to has fields that fit
together, and the air links of one gNB share one slot grid. `rrc` is an air link's only, and
the `tc` backend takes neither a radio nor RRC states.
"""

from __future__ import annotations

import dataclasses
import math

from netem.directions import DIRECTIONS
from netem.nr.radio import RADIO_PROFILES, Radio
from netem.nr.rrc import RrcSettings
from netem.profile import GilbertElliott, LinkProfile
from testbed.scenario import model, radios, schema_v1
from testbed.scenario.building import Builder
from testbed.scenario.kinds import Context, Items, Section
from testbed.scenario.rules_topology import check_link


def profile_changes(
    section: Section,
    ctx: Context | None = None,
    radio_base: Radio | None = None,
    with_radio: bool = True,
    check_radio: bool = True,
) -> dict[str, object]:
    """`LinkProfile` fields (SI) set by the profile keys written in `section`.

    Keys that set one of two alternatives also clear the other (a loss percentage removes a
    Gilbert-Elliott model, a packet queue limit removes a time limit), so merging and `set`
    events never leave both in place. A radio whose fields do not fit together (a pattern
    whose period TS 38.331 does not allow, say) is reported to `ctx` at its line. A radio
    mapping without a `profile` changes `radio_base` (`testbed.scenario.radios`); with
    `with_radio` off the radio is left to the caller.
    """
    v = section.values
    changes: dict[str, object] = {}
    if "radio" in v and with_radio:
        radio = radio_of(v["radio"], section, ctx, radio_base, check_radio)
        if radio is not False:
            changes["radio"] = radio
    if "rate" in v:
        changes["rate_bps"] = v["rate"]
    if "delay" in v:
        changes["delay_s"] = v["delay"]
    if "jitter" in v:
        changes["jitter_s"] = v["jitter"]
    if "jitter_distribution" in v:
        changes["jitter_distribution"] = v["jitter_distribution"]
    if "loss" in v:
        loss = v["loss"]
        if isinstance(loss, Section):
            if loss.clean:  # a broken model was reported; there is nothing to build
                ge: GilbertElliott = loss.obj.build(loss)
                changes.update(loss=0.0, gilbert_elliott=ge)
        else:
            changes.update(loss=loss, gilbert_elliott=None)
    if "queue" in v:
        queue = v["queue"]
        if isinstance(queue, int):
            changes.update(queue_packets=queue, queue_time_s=None)
        else:
            changes.update(queue_packets=None, queue_time_s=queue)
    if "reorder" in v:
        changes["reorder"] = v["reorder"]
    return changes


def radio_of(
    value: object,
    section: Section,
    ctx: Context | None,
    base: Radio | None = None,
    check: bool = True,
) -> Radio | bool | None:
    """The `Radio` a `radio` key names or describes over `base` (False: reported, none
    built). Without `check` its fields are not checked together (a later layer may still
    change them: the caller checks what they add up to)."""
    if value is None:
        return None
    if isinstance(value, str):
        return RADIO_PROFILES[value]
    assert isinstance(value, Section)
    if not value.clean:
        return False
    radio = radios.changed(value.values, base)
    why = radios.problem(radio) if check else None
    if why is None:
        return radio
    if ctx is not None:
        _misfit(ctx, section, why)
    return False


def _misfit(ctx: Context, section: Section, why: str) -> None:
    ctx.add(
        section.at("radio"),
        section.path_of("radio"),
        "a radio whose fields fit together (TS 38.211/38.213/38.331)",
        why,
    )


#: The link kinds with defaults in `links` (`model.LinkKind`).
LINK_KINDS = ("air", "backhaul", "n3", "n6")


def _rrc(value: Section | None) -> RrcSettings | None:
    """A `rrc` mapping built (null: always connected); `idle_after: null` is never IDLE."""
    if value is None:
        return None
    built: RrcSettings = schema_v1.RRC.build(value)
    if built.idle_after_s is None:
        built = dataclasses.replace(built, idle_after_s=math.inf)
    return built


def build(b: Builder) -> model.Links | None:
    """The `Links`, or None when one is wrong (reported); their specs also go to
    `b.link_specs`, over which the timeline lays its radios."""
    links: Section | None = b.root.get("links")
    defaults: dict[str, dict[str, dict[str, object]]] = {
        kind: {"uplink": {}, "downlink": {}} for kind in LINK_KINDS
    }
    merged: dict[str, dict[str, dict[str, object]]] = {}
    # Where each radio was written last (the section holding its `radio` key): the air
    # defaults by direction, the overrides by link and direction.
    where: dict[tuple[str, str], Section] = {}
    rrc: dict[str, RrcSettings | None] = {}  # "air" (the default) or a link -> settings
    if links is not None:
        air: Section | None = links.get("air")
        if air is not None and air.written("rrc"):
            rrc["air"] = _rrc(air.get("rrc"))
        for kind in LINK_KINDS:
            pair: Section | None = links.get(kind)
            if kind == "n3" and pair is None:
                pair = links.get("backhaul")  # the gNB's wired link, whatever its far end
            both = radio_of(pair.get("radio"), pair, b.ctx, check=False) if pair else None
            for direction in DIRECTIONS:
                profile = pair.get(direction) if pair else None
                base = both if isinstance(both, Radio) else None
                changes = (
                    profile_changes(profile, b.ctx, base, check_radio=False) if profile else {}
                )
                if profile is not None and "radio" in profile:
                    where[kind, direction] = profile
                elif pair is not None and "radio" in pair:
                    changes["radio"] = base
                    where[kind, direction] = pair
                defaults[kind][direction] = changes
        overrides: Items | None = links.get("overrides")
        seen: dict[str, str] = {}
        for _, override, _ in overrides.good() if overrides else ():
            if not check_link(b, override, "link"):
                continue
            name = override["link"]
            if name in seen:
                b.ctx.add(
                    override.at("link"),
                    override.path_of("link"),
                    "one override per link (put all its fields in one entry)",
                    f"{name!r} again (also at {seen[name]})",
                )
                continue
            seen[name] = override.path
            kind = b.link_kinds[name]
            if override.written("rrc"):
                if kind == "air":
                    rrc[name] = _rrc(override.get("rrc"))
                else:
                    b.ctx.add(
                        override.at("rrc"),
                        override.path_of("rrc"),
                        "rrc on an air link only (RRC states are a UE's)",
                        f"rrc on {name}, a {kind} link",
                    )
            merged[name] = {}
            for d in DIRECTIONS:
                if d not in override:
                    merged[name][d] = {}
                    continue
                base = defaults[kind][d].get("radio")
                merged[name][d] = profile_changes(
                    override[d],
                    b.ctx,
                    base if isinstance(base, Radio) else None,
                    check_radio=False,
                )
                if "radio" in override[d]:
                    where[name, d] = override[d]
    if not b.topology_ok or b.ctx.issues:
        return None
    specs = []
    for name, kind in b.link_kinds.items():
        lower, upper = name.split("-")
        states = rrc.get(name, rrc.get("air")) if kind == "air" else None
        profiles = {
            d: LinkProfile(
                **{**defaults[kind][d], **merged.get(name, {}).get(d, {}), "rrc": states}
            )
            for d in DIRECTIONS
        }
        for d in DIRECTIONS:
            if (name, d) not in where and (kind, d) in where:
                where[name, d] = where[kind, d]
        specs.append(
            model.LinkSpec(name, kind, lower, upper, profiles["uplink"], profiles["downlink"])  # type: ignore[arg-type]
        )
    specs = _cell_radios(b, specs, where)
    if specs is None or not _radios_fit(b, specs, where):
        return None
    if not _one_grid_per_cell(b, specs, where):
        return None
    backend = links.get("backend", "auto") if links is not None else "auto"
    with_radio = [s.name for s in specs if s.uplink.radio or s.downlink.radio]
    if backend == "tc" and with_radio and links is not None:
        b.ctx.add(
            links.at("backend"),
            links.path_of("backend"),
            "userspace or auto for links with a radio",
            f"tc, with a radio on {', '.join(with_radio)}",
            "the NR slot model runs in the userspace relay; tc's qdiscs have no slot clock",
        )
    with_rrc = [s.name for s in specs if s.uplink.rrc is not None]
    if backend == "tc" and with_rrc and links is not None:
        b.ctx.add(
            links.at("backend"),
            links.path_of("backend"),
            "userspace or auto for air links with rrc",
            f"tc, with RRC states on {', '.join(with_rrc)}",
            "the relay holds a quiet UE's first packet back; a qdisc cannot",
        )
        return None
    b.link_specs = {s.name: s for s in specs}
    return model.Links(backend=backend, links=tuple(specs))


def _cells(b: Builder) -> list[Section]:
    topo: Section | None = b.root.get("topology")
    cells: Items | None = topo.get("cells") if topo else None
    return [c for _, c, _ in cells.good()] if cells else []


def _cell_radios(
    b: Builder, specs: list[model.LinkSpec], where: dict[tuple[str, str], Section]
) -> list[model.LinkSpec] | None:
    """`specs` with each cell's `radio` (its slot grid and carrier) laid over its air
    links' radios; None when one does not fit (reported)."""
    out = {s.name: s for s in specs}
    for cell in _cells(b):
        if "radio" not in cell:
            continue
        value = cell["radio"]
        part, profile = radios.cell_part(value.values if isinstance(value, Section) else value)
        mine = [s for s in specs if s.kind == "air" and s.upper == cell["gnb"]]
        for spec in mine:
            changed = {}
            for d in DIRECTIONS:
                radio = radios.with_cell(getattr(spec, d).radio, part, profile)
                changed[d] = dataclasses.replace(getattr(spec, d), radio=radio)
                if radio is not None:
                    where[spec.name, d] = cell
            out[spec.name] = dataclasses.replace(spec, **changed)
        if profile is None and all(
            s.uplink.radio is None and s.downlink.radio is None for s in mine
        ):
            b.ctx.add(
                cell.at("radio"),
                cell.path_of("radio"),
                "air links with a radio (links.air.radio) for the cell's part to change, "
                "or a `profile` here",
                f"no radio on {', '.join(s.name for s in mine) or 'any air link of it'}",
            )
            return None
    return [out[s.name] for s in specs]


def _radios_fit(
    b: Builder, specs: list[model.LinkSpec], where: dict[tuple[str, str], Section]
) -> bool:
    """Whether every link direction's radio, all its layers laid, has fields that fit
    together; each misfit is reported once, where its radio was written last."""
    said: set[str] = set()
    for spec in specs:
        for d in DIRECTIONS:
            radio = getattr(spec, d).radio
            why = None if radio is None else radios.problem(radio)
            section = where.get((spec.name, d))
            if why is None or section is None or section.path in said:
                continue
            said.add(section.path)
            _misfit(b.ctx, section, f"on {spec.name} {d}: {why}")
    return not said


def _one_grid_per_cell(
    b: Builder, specs: list[model.LinkSpec], where: dict[tuple[str, str], Section]
) -> bool:
    """Whether the radios of each gNB's air links share one slot grid (reported where
    the first that does not was written)."""
    for d in DIRECTIONS:
        first: dict[str, tuple[str, Radio]] = {}
        for spec in specs:
            radio = getattr(spec, d).radio
            if spec.kind != "air" or radio is None:
                continue
            if spec.upper not in first:
                first[spec.upper] = (spec.name, radio)
                continue
            name, other = first[spec.upper]
            if radios.grid(radio) == radios.grid(other):
                continue
            section = where.get((spec.name, d))
            if section is None:  # pragma: no cover - a differing radio was written somewhere
                continue
            off_grid(
                b, section, spec, d, radio, (name, other),
                "put the cell's TDD pattern and numerology in topology.cells[].radio",
            )  # fmt: skip
            return False
    return True


def off_grid(
    b: Builder,
    section: Section,
    spec: model.LinkSpec,
    direction: str,
    radio: Radio,
    cell_radio: tuple[str, Radio],
    hint: str,
) -> None:
    """Report `radio` on `spec` as off the slot grid its cell's other UEs have
    (`cell_radio`: where that grid was seen, and a radio with it)."""
    seen_on, other = cell_radio
    b.ctx.add(
        section.at("radio"),
        section.path_of("radio"),
        f"the slot grid of cell {spec.upper} ({radios.grid_text(other)}, as on "
        f"{seen_on}): one gNB, one slot grid for all its UEs",
        f"{radios.grid_text(radio)} on {spec.name} {direction}",
        hint,
    )
