"""The radio along the route (runs with `channel:`): coverage, serving cells, SINR, MCS,
BLER and capacity per vehicle, the learner's decisions by the uplink MCS, and what EdgeLoc,
its learner and the uplink did around each handover.

Its key of summary.json:

- `radio` (runs with `channel:`): {vehicles: {vehicle: {steps, coverage, cells {cell: share},
  handovers [{t_s, from, to, interruption_ms, lossless, lateness_ms, error (null: applied)}],
  handovers_source ("/handover": as applied; "/radio/<vehicle>": changes of the serving cell,
  whose interruption, lossless, lateness and error are null), sinr_db and ul_sinr_db {min, p5,
  median, p95, max}, mean_mcs, mean_ul_mcs, mean_bler, mean_ul_bler, capacity_mbps {ul, dl:
  {min, p5, median, p95, max}} (Mbit/s the serving cell's air link carried at each step's MCS
  and BLER, `radio_capacity`; null without links.json's radios, a run older than it),
  by_uplink_mcs [{mcs [lo, hi], time_share, plays, share {split: fraction},
  mean_payload_bytes}] (the learner's decisions by the uplink MCS at their time,
  `nodes.edgeloc.bands`; null without decisions),
  handover_window_s (W, `HANDOVER_WINDOW_S`), away_from_handovers {plays, top_split, top_share,
  mean_payload_bytes} (the plays outside every [t - W, t + W)), around_handovers [one per
  handover: its keys above, and before and after ([t - W, t) and [t, t + W)), as
  `nodes.edgeloc.bands.around` gives them for the replay: {plays (decided then), top_split
  (most played), top_share, mean_payload_bytes (each play at its split's mean payload per
  request on /<vehicle>/inference), mean_latency_s (the plays' answered requests), mean_error_m
  (EdgeLoc's fused position error of the frames captured then), mean_ul_mcs (over the /radio
  steps)}, plus timed_out (plays whose request timed out) and top_split_vs_away ("smaller",
  "larger" or "same" uplink payload per request than away_from_handovers' top split; null:
  not comparable); smaller_split_near (either window's top split smaller; null: neither
  comparable)]}}, channel (model, los, step_s, sites [{name, x, y}], handover (the
  `channel.handover` settings or null))} from `/radio/<vehicle>` and `/handover`; {} without
  /radio.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from netem.directions import Direction
from nodes.edgeloc import bands
from nodes.recording.layout import HANDOVER_TOPIC, radio_topic
from reports.document import Image, Para, Plot, Section, Table
from reports.mcapread import RadioSeries, RunData, VehicleData
from reports.sections.accuracy import FrameErrors
from reports.sections.fmt import cell, ms, not_recorded_note, pct, rounded


def _spread(x: NDArray[np.float64]) -> dict[str, float | None]:
    """min, p5, median, p95, max: a cell edge shows in the low end."""
    a = x[np.isfinite(x)]
    keys = ("min", "p5", "median", "p95", "max")
    if not len(a):
        return dict.fromkeys(keys)
    values = np.percentile(a, [0, 5, 50, 95, 100])
    return {k: rounded(float(v), 3) for k, v in zip(keys, values, strict=True)}


def _payload_by_split(vd: VehicleData) -> dict[str, float]:
    """Mean uplink bytes per request of each split the vehicle sent (/<vehicle>/inference).
    This, not the split order, says which split is smaller: the raw image weighs less than
    the first layers' activations (`nodes.edgeloc.model`)."""
    sent: dict[str, list[int]] = {}
    for i in vd.inference:
        sent.setdefault(i.split, []).append(i.payload_bytes)
    return {s: sum(b) / len(b) for s, b in sent.items() if b}


def _plays_by_uplink_mcs(data: RunData, vehicle: str) -> list[dict[str, Any]] | None:
    """The vehicle's split decisions by the uplink MCS at their time (`nodes.edgeloc.bands`);
    None when it made none (no EdgeLoc on it)."""
    vd, r = data.vehicles.get(vehicle), data.radio[vehicle]
    if vd is None or not vd.decisions:
        return None
    at = np.searchsorted(r.t, [d.t for d in vd.decisions], side="right") - 1
    mcs = [int(r.ul_mcs[max(0, i)]) for i in at]
    rows = bands.by_band(
        mcs,
        [d.chosen for d in vd.decisions],
        _payload_by_split(vd),
        bands.time_shares(r.ul_mcs.astype(int)),
    )
    return [{**row, "share": {k: rounded(v) for k, v in row["share"].items()}} for row in rows]


#: The span each side of a handover over which the report says what EdgeLoc did: [t - W, t)
#: before it and [t, t + W) after. The replay's (`nodes.edgeloc.bands.AROUND_S`, 3 s: a few
#: learner windows, and the distance over which the cell edge's SINR falls at urban speeds),
#: so a run's report and its scenario's replay describe the same windows.
HANDOVER_WINDOW_S = bands.AROUND_S


def _handovers(data: RunData, r: RadioSeries) -> tuple[str, list[tuple[float, dict[str, Any]]]]:
    """The vehicle's handovers as (wall-clock time, summary row), and where they come from:
    `/handover` when the recording holds it (what the timeline applied, with its
    interruption), else the changes of the serving cell on `/radio/<vehicle>`."""
    t0 = data.t0
    if data.handovers:
        return HANDOVER_TOPIC, [
            (
                h.t,
                {
                    "t_s": rounded(h.t - t0),
                    "from": h.source,
                    "to": h.target,
                    "interruption_ms": rounded(h.interruption_s * 1e3, 3),
                    "lossless": h.lossless,
                    "lateness_ms": rounded(h.lateness_s * 1e3, 3),
                    "error": h.error or None,
                },
            )
            for h in data.handovers
            if h.vehicle == r.vehicle
        ]
    unknown = dict.fromkeys(("interruption_ms", "lossless", "lateness_ms", "error"))
    return radio_topic(r.vehicle), [
        (
            float(r.t[i]),
            {"t_s": rounded(float(r.t[i]) - t0), "from": r.cell[i - 1], "to": r.cell[i], **unknown},
        )
        for i in range(1, len(r))
        if r.cell[i] != r.cell[i - 1]
    ]


def _away(chosen: list[str], payload: Mapping[str, float]) -> dict[str, Any]:
    """The plays away from every handover: how many, the most played split (ties: the first
    played, as `nodes.edgeloc.bands.around`) and its share, and their mean payload."""
    top = Counter(chosen).most_common(1)
    sent = [payload[c] for c in chosen if c in payload]
    return {
        "plays": len(chosen),
        "top_split": top[0][0] if top else None,
        "top_share": top[0][1] / len(chosen) if top else None,
        "mean_payload_bytes": float(np.mean(sent)) if sent else None,
    }


def _size_vs(split: str | None, ref: str | None, payload: Mapping[str, float]) -> str | None:
    """Whether `split` sends less uplink payload per request than `ref` ("smaller"), more
    ("larger") or as much ("same"); None when either is missing or has no recorded payload."""
    if split is None or ref is None:
        return None
    if split == ref:
        return "same"
    if split not in payload or ref not in payload:
        return None
    a, b = payload[split], payload[ref]
    return "smaller" if a < b else "larger" if a > b else "same"


def _around_handovers(
    data: RunData,
    r: RadioSeries,
    handovers: list[tuple[float, dict[str, Any]]],
    fe: FrameErrors | None,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The plays away from every handover, and per handover what the learner, EdgeLoc and
    the uplink did in the `HANDOVER_WINDOW_S` before and after it (`bands.around`, as the
    replay: plays at their decision, each with its request's latency; frames at their
    capture), plus the plays whose request timed out and how each window's top split compares
    with the top split away from handovers, which the learner plays where no cell edge is
    near. A vehicle without EdgeLoc gets the radio's figures and no plays."""
    w = HANDOVER_WINDOW_S
    vd = data.vehicles.get(r.vehicle) or VehicleData(r.vehicle)
    payload = _payload_by_split(vd)
    result = {i.frame_id: i for i in vd.inference}  # a play's request, by its frame
    sent = [d.t for d in vd.decisions]
    outcome = [result.get(d.frame_id) for d in vd.decisions]
    series = bands.Series(
        sent_s=sent,
        splits=[d.chosen for d in vd.decisions],
        latency_s=[i.latency_s if i is not None and i.ok else math.nan for i in outcome],
        payload_bytes=payload,
        frame_t=fe.t.tolist() if fe is not None else [],
        frame_error_m=fe.position_m.tolist() if fe is not None else [],
        mcs_t=r.t.tolist(),
        ul_mcs=r.ul_mcs.tolist(),
    )
    times = [t for t, _ in handovers]
    far = [d.chosen for d in vd.decisions if all(not t - w <= d.t < t + w for t in times)]
    away = _away(far, payload)
    rows = []
    for t, row in handovers:
        windows = bands.around(t, series, window_s=w)
        for side, (a, b) in (("before", (t - w, t)), ("after", (t, t + w))):
            x = windows[side]
            x["timed_out"] = sum(
                a <= s < b and i is not None and i.timed_out
                for s, i in zip(sent, outcome, strict=True)
            )
            x["top_split_vs_away"] = _size_vs(x["top_split"], away["top_split"], payload)
        compared = [x["top_split_vs_away"] for x in windows.values() if x["top_split_vs_away"]]
        rows.append(
            {**row, **windows, "smaller_split_near": "smaller" in compared if compared else None}
        )
    return away, rows


def radio_capacity(data: RunData, r: RadioSeries) -> dict[str, NDArray[np.float64]] | None:
    """Per channel step, the Mbit/s the serving cell's air link carried, uplink (`ul`) and
    downlink (`dl`): `Radio.goodput_bps` of the link's radio (`<vehicle>-<cell>`, as
    links.json's starting profiles give it) at the step's MCS and BLER (`ul_mcs`/`ul_bler`
    up, `mcs`/`bler` down), which is what the channel set on that link then. The MCS alone
    hides what it is worth: the same MCS carries more on a wider carrier or a TDD pattern
    with more slots of that direction. NaN at a step whose link has no radio in links.json
    or whose MCS is no MCS; None when no step has a capacity (no links.json: an older run)."""
    if not data.link_radios or not len(r):
        return None
    # `goodput_bps` is the MCS's block rate times (1 - bler): the rate is looked up once per
    # link, direction and MCS, not once per step (every step's BLER is its own).
    rates: dict[tuple[str, Direction, int], float] = {}

    def mbps(cell: str, direction: Direction, mcs: float, bler: float) -> float:
        radio = data.link_radios.get((f"{r.vehicle}-{cell}", direction))
        if radio is None or not (math.isfinite(mcs) and 0.0 <= bler < 1.0):
            return math.nan
        key = (cell, direction, int(mcs))
        if key not in rates:
            try:
                rates[key] = dataclasses.replace(radio, mcs=int(mcs)).rate_bps(direction) / 1e6
            except ValueError:  # NrError: an MCS outside TS 38.214's table
                rates[key] = math.nan
        return rates[key] * (1.0 - bler)

    out = {
        key: np.array(
            [mbps(c, direction, m, b) for c, m, b in zip(r.cell, mcs, bler, strict=True)],
            dtype=np.float64,
        )
        for key, direction, mcs, bler in (
            ("ul", "uplink", r.ul_mcs, r.ul_bler),
            ("dl", "downlink", r.mcs, r.bler),
        )
    }
    return out if any(np.isfinite(x).any() for x in out.values()) else None


def radio_summary(data: RunData, edgeloc: Mapping[str, FrameErrors]) -> dict[str, Any]:
    """Per vehicle of a `channel:` run, from `/radio/<vehicle>` and `/handover`: steps,
    coverage (share of steps at downlink CQI >= 1), the serving cells' shares, handovers,
    SINR, MCS and capacity figures of both directions, and what EdgeLoc (its fused errors
    `edgeloc`, by vehicle) and its learner did around each handover; `sites` as the
    recorder's `edgeloc.run` metadata gives them. {} without /radio."""
    if not data.radio:
        return {}
    out: dict[str, Any] = {}
    for v, r in data.radio.items():
        if not len(r):
            continue
        cells = Counter(r.cell)
        source, handovers = _handovers(data, r)
        away, around = _around_handovers(data, r, handovers, edgeloc.get(v))
        capacity = radio_capacity(data, r)
        out[v] = {
            "steps": len(r),
            "coverage": rounded(float(np.mean(r.cqi >= 1))),
            "cells": {c: rounded(n / len(r)) for c, n in sorted(cells.items())},
            "handovers": [row for _, row in handovers],
            "handovers_source": source,
            "sinr_db": _spread(r.sinr_db),
            "ul_sinr_db": _spread(r.ul_sinr_db),
            "mean_mcs": rounded(float(np.mean(r.mcs))),
            "mean_ul_mcs": rounded(float(np.mean(r.ul_mcs))),
            "mean_bler": rounded(float(np.mean(r.bler))),
            "mean_ul_bler": rounded(float(np.mean(r.ul_bler))),
            "capacity_mbps": (
                {k: _spread(x) for k, x in capacity.items()} if capacity is not None else None
            ),
            "by_uplink_mcs": _plays_by_uplink_mcs(data, v),
            "handover_window_s": HANDOVER_WINDOW_S,
            "away_from_handovers": away,
            "around_handovers": around,
        }
    channel = data.run.get("channel")
    return {"vehicles": out, "channel": channel if isinstance(channel, dict) else None}


def handovers_unrecorded(data: RunData) -> bool:
    """The scenario set `channel.handover` and a vehicle's serving cell changed, yet the
    recording holds no `/handover`: its handovers are known only from /radio's cells."""
    channel = data.run.get("channel")
    if not isinstance(channel, dict) or not channel.get("handover") or data.handovers:
        return False
    return any(r.cell[i] != r.cell[i - 1] for r in data.radio.values() for i in range(1, len(r)))


def radio_section(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section | None:
    """The vehicles' radio along their routes (runs with `channel:`)."""
    radio = s.get("radio") or {}
    vehicles = radio.get("vehicles") or {}
    if not vehicles:
        return None
    ch = radio.get("channel") or {}
    sec = Section("Radio along the route")
    source = f"trace {ch['trace']}" if ch.get("trace") else f"TR 38.901 {ch.get('model', '?')}"
    sec.add(
        Para(
            f"The channel ({source}, LOS {ch.get('los', '?')}, a step every "
            f"{ms(ch.get('step_s'))} ms) set each vehicle's air link from where it was; "
            f"{len(ch.get('sites') or [])} cell site(s)."
        )
    )

    def db(block: Any, key: str) -> str:
        return cell((block or {}).get(key), "{:.1f}")

    def capacity(block: Any) -> str:
        """The uplink's p5 / median: the uplink is what EdgeLoc's requests wait on, and its
        p5 is the cell edge. "-" for a run without links.json's radios."""
        ul = (block or {}).get("ul") or {}
        if ul.get("median") is None:
            return "-"
        return f"{cell(ul.get('p5'), '{:.1f}')} / {cell(ul.get('median'), '{:.1f}')}"

    sec.add(
        Table(
            [
                "vehicle",
                "coverage",
                "cells",
                "handovers",
                "DL SINR p5/median dB",
                "UL SINR p5/median dB",
                "mean MCS DL/UL",
                "mean BLER DL/UL",
                "capacity p5/median UL Mbit/s",
            ],
            [
                [
                    v,
                    pct(r.get("coverage")),
                    ", ".join(f"{c} {pct(x)}" for c, x in (r.get("cells") or {}).items()),
                    str(len(r.get("handovers") or [])),
                    f"{db(r.get('sinr_db'), 'p5')} / {db(r.get('sinr_db'), 'median')}",
                    f"{db(r.get('ul_sinr_db'), 'p5')} / {db(r.get('ul_sinr_db'), 'median')}",
                    f"{cell(r.get('mean_mcs'), '{:.1f}')} / {cell(r.get('mean_ul_mcs'), '{:.1f}')}",
                    f"{pct(r.get('mean_bler'))} / {pct(r.get('mean_ul_bler'))}",
                    capacity(r.get("capacity_mbps")),
                ]
                for v, r in vehicles.items()
            ],
            caption="per vehicle, from /radio/<vehicle>: coverage is the share of steps at "
            "downlink CQI 1 or better; capacity is what the serving cell's uplink carried at "
            "each step's MCS and BLER, its radio from links.json (- without it)",
        )
    )
    for v, r in vehicles.items():
        rows = r.get("by_uplink_mcs")
        if rows:
            sec.add(
                Table(
                    ["uplink MCS", "share of the run", "plays", "splits chosen", "mean payload"],
                    [
                        [
                            f"{row['mcs'][0]}-{row['mcs'][1]}",
                            pct(row.get("time_share")),
                            str(row["plays"]),
                            ", ".join(f"{s} {pct(x)}" for s, x in list(row["share"].items())[:3]),
                            "-"
                            if row["mean_payload_bytes"] is None
                            else f"{row['mean_payload_bytes'] / 1000:.1f} kB",
                        ]
                        for row in rows
                    ],
                    caption=f"{v}: the learner's decisions by the uplink MCS at their time",
                )
            )
    if HANDOVER_TOPIC in (s.get("not_recorded") or []):
        sec.add(
            not_recorded_note(
                "the handovers as applied",
                f"{HANDOVER_TOPIC}, though the scenario sets channel.handover: the handovers "
                "below are the serving cell's changes on /radio/<vehicle>, without their "
                "interruption or lateness",
            )
        )
    for v, r in vehicles.items():
        if r.get("around_handovers"):
            sec.add(_around_table(v, r))
            sentence = _smaller_split_sentence(r)
            if sentence:
                sec.add(Para(sentence))
    for key in sorted(k for k in plots if k.startswith("radio:")):
        plot = plots[key]
        if plot is not None:
            sec.add(Image(plot))
    return sec


def _around_table(vehicle: str, r: dict[str, Any]) -> Table:
    """One row per handover of `vehicle`: what it was, and the radio, EdgeLoc's error and the
    learner's plays in the window before it beside the window after it."""

    def both(row: dict[str, Any], show: Callable[[dict[str, Any]], str]) -> str:
        return f"{show(row.get('before') or {})} / {show(row.get('after') or {})}"

    def top(w: dict[str, Any]) -> str:
        return "-" if w.get("top_split") is None else f"{w['top_split']} {pct(w['top_share'])}"

    rows = []
    for h in r["around_handovers"]:
        cut = "-"
        if h.get("interruption_ms") is not None:
            cut = f"{h['interruption_ms']:.1f} " + ("lossless" if h.get("lossless") else "lossy")
        rows.append(
            [
                cell(h.get("t_s"), "{:.2f}"),
                f"{h['from']} → {h['to']}" + (f" (failed: {h['error']})" if h.get("error") else ""),
                cut,
                cell(h.get("lateness_ms"), "{:.1f}"),
                both(h, lambda w: cell(w.get("mean_ul_mcs"), "{:.1f}")),
                both(h, lambda w: cell(w.get("mean_error_m"), "{:.2f}")),
                both(h, top),
                both(h, lambda w: ms(w.get("mean_latency_s"))),
            ]
        )
    w = cell(r.get("handover_window_s"), "{:g}")
    source = r.get("handovers_source") or "/radio/<vehicle>"
    return Table(
        [
            "time s",
            "from → to",
            "interruption ms",
            "lateness ms",
            "UL MCS before / after",
            "EdgeLoc error m before / after",
            "top split before / after",
            "mean latency ms before / after",
        ],
        rows,
        caption=f"Around each handover of {vehicle} (from {source}), the {w} s before it and "
        f"the {w} s after: mean uplink MCS of the channel steps, EdgeLoc's mean position error "
        "of the frames captured, the learner's most-played split and its share of the plays, "
        "the mean latency of the plays' answered requests",
    )


def _smaller_split_sentence(r: dict[str, Any]) -> str | None:
    """Whether the learner moved to a smaller split near the handovers, said plainly from the
    numbers. Rule: near a handover the learner moved to a smaller split when its most-played
    split in the window before or the window after it sends less uplink payload per request
    (that split's mean over the vehicle's requests) than its most-played split away from every
    handover; "near most" when that holds for more than half of the handovers where at least
    one window could be compared. None for a vehicle without plays (no EdgeLoc on it)."""
    around = r["around_handovers"]
    away = r.get("away_from_handovers") or {}
    near = sum(h["before"]["plays"] + h["after"]["plays"] for h in around)
    if not near and not away.get("plays"):
        return None
    judged = [h for h in around if h.get("smaller_split_near") is not None]
    w = cell(r.get("handover_window_s"), "{:g}")
    if not judged:
        why = (
            "it made no plays away from them to compare with"
            if not away.get("plays")
            else "no window near them has plays of a split whose payload was recorded "
            "(/<vehicle>/inference)"
        )
        return f"Whether the learner moved to a smaller split near the handovers is unknown: {why}."
    n = sum(bool(h["smaller_split_near"]) for h in judged)
    before = sum(h["before"]["top_split_vs_away"] == "smaller" for h in judged)
    after = sum(h["after"]["top_split_vs_away"] == "smaller" for h in judged)
    verdict = "moved" if 2 * n > len(judged) else "did not move"
    text = (
        f"The learner {verdict} to a smaller split near most handovers: near {n} of "
        f"{len(judged)} handovers its most-played split in the {w} s before or after sent less "
        f"uplink payload per request than {away['top_split']}, its most-played split away "
        f"from handovers ({before} in the window before, {after} in the window after)."
    )
    left = len(around) - len(judged)
    if left:
        text += (
            f" {left} handover(s) could not be compared (no plays near them, or a split "
            "without recorded payload)."
        )
    return text
