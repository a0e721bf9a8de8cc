"""How a scenario's `radio` keys become `netem.nr.radio.Radio`s: pure functions, no positions.

A radio is written in layers, each changing the one below it: `links.air.radio` (every air
link, both directions), a direction's `radio` under `links.air`, a link's override, the
cell's `topology.cells[].radio` (its slot grid and carrier), and timeline `set` events. A
named profile, or a mapping with a `profile` key, starts afresh from that profile; a mapping
without one changes the radio of the layer below (or, where there is none, DEFAULT_PROFILE).
The link rules (`testbed.scenario.rules_links`) say where in the file a layer that does not fit is.

The layers in full: `links.air.radio`, a direction under `links.air`, a link's override, the
cell's `topology.cells[].radio` (its `tdd`, `special_dl`/`special_ul`, `numerology`, `prbs` and
`scheduler`: one gNB, one slot grid; a profile there gives the radio to air links that have
none), and `set` events, which change the radio the link has at that time (a `both` event on
two different radios becomes one per direction). A mapping may change `tdd`, `special_dl`,
`special_ul`, `numerology`, `prbs`, `mcs`, `layers`, `k2`, `bler`, `max_retx`, `harq_slots`,
`access`, `sr_period`, `sr_offset`, `sr_grant`, `grant_slots`, `cg_period`, `cg_offset`, `rlc`,
`rlc_status`, `rlc_max_retx`, `in_order`, `buffer` (bytes), `core_delay` (the gNB-to-core
delay a radio carries in its direction), `sched_offset` and `radio_offset` (srsRAN's S and R
slots), `ue_delay_ul`/`ue_delay_dl` (the UE's own processing) and `ul_prbs`/`ul_symbols` (what
one uplink grant may use), `l2_overhead` (bytes of MAC and RLC headers per block) and `dmrs_re`
(resource elements per PRB the DMRS takes).

The fields are checked together once every layer is laid, and an error names the layer written
last: an SR or configured grant in a slot without uplink symbols (with the slot it falls in),
UEs of one cell on different slot grids, a `set` that changes one UE's grid. `delay`, `loss` and
`rate` keep working beside a radio. `backend: tc` with a radio is refused at validation; `auto`
picks the relay and says why.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from netem.nr.phy import SYMBOLS_PER_SLOT, NrError
from netem.nr.radio import RADIO_PROFILES, Radio

DEFAULT_PROFILE = "oai-tdd-30k"
#: YAML key -> `Radio` attribute (special_dl/special_ul make up `special` together).
ATTRS = {
    "tdd": "slots",
    "numerology": "numerology",
    "prbs": "n_prb",
    "mcs": "mcs",
    "layers": "layers",
    "k2": "k2_slots",
    "bler": "bler",
    "max_retx": "max_retx",
    "harq_slots": "harq_slots",
    "access": "ul_access",
    "sr_period": "sr_period_slots",
    "sr_offset": "sr_offset",
    "sr_grant": "sr_grant_bytes",
    "grant_slots": "grant_slots",
    "cg_period": "cg_period_slots",
    "cg_offset": "cg_offset",
    "rlc": "rlc",
    "rlc_status": "rlc_status_s",
    "rlc_max_retx": "rlc_max_retx",
    "in_order": "in_order",
    "buffer": "buffer_bytes",
    "core_delay": "core_delay_s",
    "sched_offset": "sched_offset_slots",
    "radio_offset": "radio_offset_slots",
    "ue_delay_ul": "ue_ul_delay_s",
    "ue_delay_dl": "ue_dl_delay_s",
    "ul_prbs": "ul_prbs",
    "ul_symbols": "ul_symbols",
    "l2_overhead": "l2_overhead_bytes",
    "dmrs_re": "dmrs_re_per_prb",
}
#: The attributes that are the cell's, not a UE's: all the UEs of a gNB share its slot grid.
GRID_ATTRS = ("slots", "special", "numerology")
CELL_ATTRS = (*GRID_ATTRS, "n_prb")


def changed(values: dict[str, Any], base: Radio | None) -> Radio:
    """The radio a mapping's `values` (YAML keys) describe over `base`: its `profile` if it
    names one, else `base`, else DEFAULT_PROFILE."""
    if "profile" in values:
        start = RADIO_PROFILES[values["profile"]]
    else:
        start = base if base is not None else RADIO_PROFILES[DEFAULT_PROFILE]
    dl, _, ul = start.special
    dl, ul = values.get("special_dl", dl), values.get("special_ul", ul)
    changes: dict[str, object] = {attr: values[k] for k, attr in ATTRS.items() if k in values}
    if "special_dl" in values or "special_ul" in values:
        changes["special"] = (dl, SYMBOLS_PER_SLOT - dl - ul, ul)
    return dataclasses.replace(start, **changes)  # type: ignore[arg-type]


def problem(radio: Radio) -> str | None:
    """Why `radio`'s fields do not fit together, or None."""
    dl, gap, ul = radio.special
    if gap < 0:
        return f"special_dl {dl} + special_ul {ul} symbols, more than a slot's 14"
    try:
        radio.check()
    except NrError as exc:
        return str(exc)
    return None


def cell_part(value: str | dict[str, Any]) -> tuple[dict[str, Any], Radio | None]:
    """What a `topology.cells[].radio` value sets on each of the cell's radios (attribute ->
    value), and the radio a named profile gives an air link that has none (None: no
    profile named)."""
    if isinstance(value, str):
        profile = RADIO_PROFILES[value]
        return {a: getattr(profile, a) for a in CELL_ATTRS}, profile
    profile = RADIO_PROFILES[value["profile"]] if "profile" in value else None
    cell = changed(value, profile)
    keys = set(value) - {"profile", "scheduler"}
    attrs = {ATTRS[k] for k in keys if k in ATTRS}
    if keys & {"special_dl", "special_ul"}:
        attrs.add("special")
    if profile is not None:
        attrs |= set(CELL_ATTRS)
    return {a: getattr(cell, a) for a in CELL_ATTRS if a in attrs}, profile


def with_cell(radio: Radio | None, part: dict[str, Any], profile: Radio | None) -> Radio | None:
    """`radio` with the cell's part; an air link without a radio gets the cell's profile."""
    if radio is None:
        return None if profile is None else dataclasses.replace(profile, **part)
    return dataclasses.replace(radio, **part)


def grid(radio: Radio) -> tuple[object, ...]:
    """What all the radios of one cell must share."""
    return tuple(getattr(radio, a) for a in GRID_ATTRS)


def grid_text(radio: Radio) -> str:
    dl, gap, ul = radio.special
    return f"{radio.slots} at numerology {radio.numerology}, special slot {dl}/{gap}/{ul}"
