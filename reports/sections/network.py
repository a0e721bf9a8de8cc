"""The links: the timeline's events applied to them, what each direction delivered, the
Wondershaper-style caps and outages the events set, and the link self-test's table (with
its radio directions against their oracle).

Its key of summary.json:

- `links`: {backend, events [{t_s, scheduled_s, lateness_s, action, target, direction,
  changes}], rates [{link, direction, backend, samples, mean_mbit, max_mbit, bytes_out,
  packets_dropped}], caps {node: [{t_s, uplink_mbit, downlink_mbit}]} (Wondershaper-style
  caps set by `shape`, lifted by `clear`; null: none), outages [{link, start_s, end_s}],
  timeline (the recorder's `edgeloc.timeline`: events, applied, failed, lateness),
  linktest (the link self-test table, attachment linktest.json, or null),
  linktest_ran (the recorder's "true"/"false", null if not said)}.
"""

from __future__ import annotations

import re
from typing import Any

from nodes.recording import linktable
from reports.document import Image, Para, Plot, Section, Table
from reports.mcapread import RunData
from reports.sections.fmt import cell, ms, not_recorded_note, rounded

#: A rate in a timeline event's text, as `testbed.timeline.describe` writes it for `shape`.
_CAP_RE = re.compile(r"\b(uplink|downlink)\s+([0-9.]+(?:e[+-]?\d+)?)\s*([kMG]?)bit/s")


_OUTAGE_RE = re.compile(r"\bfor\s+([0-9.]+(?:e[+-]?\d+)?)\s*s\b")


_SCALE = {"": 1e-6, "k": 1e-3, "M": 1.0, "G": 1e3}


def link_changes(data: RunData) -> dict[str, Any]:
    """Wondershaper-style caps per node over time (from `shape`/`clear` events) and outage
    spans per link (from `outage` events), read from the events' recorded text."""
    t0 = data.t0
    caps: dict[str, list[dict[str, Any]]] = {}
    outages = []
    for e in data.link_events:
        text = " ".join(v for _, v in e.changes)
        if e.action == "shape":
            cap: dict[str, Any] = {
                "t_s": rounded(e.t - t0),
                "uplink_mbit": None,
                "downlink_mbit": None,
            }
            prev = caps.get(e.target, [])
            if prev:  # a shape event sets the directions it names and keeps the other
                cap.update({k: prev[-1][k] for k in ("uplink_mbit", "downlink_mbit")})
            for d, num, unit in _CAP_RE.findall(text):
                cap[f"{d}_mbit"] = float(num) * _SCALE[unit]
            caps.setdefault(e.target, []).append(cap)
        elif e.action == "clear":
            caps.setdefault(e.target, []).append(
                {"t_s": rounded(e.t - t0), "uplink_mbit": None, "downlink_mbit": None}
            )
        elif e.action == "outage":
            m = _OUTAGE_RE.search(text)
            if m:
                start = e.t - t0
                outages.append(
                    {
                        "link": e.target,
                        "start_s": rounded(start),
                        "end_s": rounded(start + float(m[1])),
                    }
                )
    return {"caps": caps, "outages": outages}


def links_summary(data: RunData) -> dict[str, Any]:
    t0 = data.t0
    rates = []
    for c in data.counters:
        _, r = c.rate_mbit()
        rates.append(
            {
                "link": c.link,
                "direction": c.direction,
                "backend": c.backend,
                "samples": len(c.t),
                "mean_mbit": float(r.mean()) if len(r) else None,
                "max_mbit": float(r.max()) if len(r) else None,
                "bytes_out": float(c.bytes_out[-1] - c.bytes_out[0]) if len(c.t) else None,
                "packets_dropped": (
                    float(c.packets_dropped[-1] - c.packets_dropped[0]) if len(c.t) else None
                ),
            }
        )
    return {
        "backend": data.run.get("link_backend"),
        "events": [
            {
                "t_s": rounded(e.t - t0),
                "scheduled_s": e.scheduled_s,
                "lateness_s": e.lateness_s,
                "action": e.action,
                "target": e.target,
                "direction": e.direction,
                "changes": {k: v for k, v in e.changes},
            }
            for e in data.link_events
        ],
        "rates": rates,
        **link_changes(data),
        "timeline": data.timeline,
        "linktest": data.linktest,
        "linktest_ran": data.linktest_meta.get("ran"),
    }


def links_section(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Links")
    ls = s["links"]
    sec.add(Para(f"Link backend: {ls['backend'] or 'not recorded'}."))
    tl = ls.get("timeline") or {}
    if tl:
        late = tl.get("lateness") if isinstance(tl.get("lateness"), dict) else {}
        sec.add(
            Para(
                f"Timeline: {tl.get('events', '-')} event(s) in the scenario, "
                f"{tl.get('applied', '-')} applied, {tl.get('failed', '-')} failed; lateness "
                f"median {cell(late.get('median_ms'), '{:.2f}')} ms, p99 "
                f"{cell(late.get('p99_ms'), '{:.2f}')} ms, max "
                f"{cell(late.get('max_ms'), '{:.2f}')} ms."
            )
        )
    # The channel's radio changes (several a second) are counted, not listed.
    events = [e for e in ls["events"] if e["action"] != "channel"]
    by_channel = len(ls["events"]) - len(events)
    if by_channel:
        sec.add(Para(f"The channel changed the air links' radio {by_channel} time(s)."))
    if events:
        sec.add(
            Table(
                ["t s", "scheduled s", "late ms", "action", "target", "direction", "changes"],
                [
                    [
                        cell(e["t_s"], "{:.2f}"),
                        cell(e["scheduled_s"], "{:.2f}"),
                        ms(e["lateness_s"]),
                        e["action"],
                        e["target"],
                        e["direction"],
                        ", ".join(f"{k}={v}" for k, v in e["changes"].items()),
                    ]
                    for e in events
                ],
                caption="timeline events applied to the links",
            )
        )
    elif not by_channel:
        sec.add(not_recorded_note("link events", "/links/events"))
    if ls["rates"]:
        sec.add(
            Table(
                [
                    "link",
                    "dir",
                    "backend",
                    "samples",
                    "mean Mbit/s",
                    "max Mbit/s",
                    "bytes",
                    "dropped pkts",
                ],
                [
                    [
                        r["link"],
                        r["direction"],
                        r["backend"],
                        str(r["samples"]),
                        cell(r["mean_mbit"], "{:.3f}"),
                        cell(r["max_mbit"], "{:.3f}"),
                        cell(r["bytes_out"], "{:.0f}"),
                        cell(r["packets_dropped"], "{:.0f}"),
                    ]
                    for r in ls["rates"]
                ],
                caption="delivered traffic per link direction (counter differences)",
            )
        )
        if plots.get("link_rates"):
            sec.add(Image(plots["link_rates"]))  # type: ignore[arg-type]
    else:
        sec.add(not_recorded_note("link counters", "/links/counters"))
    lt = ls["linktest"]
    if lt:
        verdict = "every link within tolerance" if lt.get("ok") else "a link is OUT of tolerance"
        sec.add(
            Table(
                list(linktable.HEADERS),  # the same columns `testbed link-test` prints
                linktable.rows(lt),
                caption=f"link self-test ({verdict}; backend {lt.get('backend', '-')})",
            )
        )
        radio = _radio_table(lt)
        if radio is not None:
            sec.add(radio)
            if plots.get("radio_cdfs"):
                sec.add(Image(plots["radio_cdfs"]))  # type: ignore[arg-type]
    elif str(ls.get("linktest_ran")).lower() == "false":
        sec.add(Para("The link self-test did not run (the scenario's report.link_test is off)."))
    else:
        sec.add(not_recorded_note("the link self-test", "no linktest.json attachment"))
    return sec


def _radio_table(lt: dict[str, Any]) -> Table | None:
    """The self-test's radio directions against their oracle (`nodes.recording.linktable`
    holds the figures' text, as `testbed link-test` prints it)."""
    directions = linktable.radio_directions(lt)
    if not directions:
        return None
    rows = []
    for link, direction, radio in directions:
        points = {round(q * 100): (m, o) for q, m, o in linktable.cdf_points(radio)}
        cells = [
            f"{points[k][0]:.2f} / {points[k][1]:.2f}" if k in points else "-"
            for k in (10, 50, 90, 99)
        ]
        harq, slots = radio.get("harq"), radio.get("slots")
        rows.append(
            [
                link,
                direction,
                str(radio.get("samples", "-")),
                cell(radio.get("w1_ms")),
                cell(radio.get("ks")),
                f"{cell(radio.get('tolerance_ms'))} ({cell(radio.get('host_tolerance_ms'))} host "
                f"+ {cell(radio.get('sampling_tolerance_ms'))} chance)",
                *cells,
                linktable.harq_text(harq) if isinstance(harq, dict) else "-",
                linktable.slots_text(slots) if isinstance(slots, dict) else "-",
            ]
        )
    floor = lt.get("timer_floor")
    timer = (
        f"; this host's timer floor: p50 {cell(floor.get('p50_ms'))} ms, p99 "
        f"{cell(floor.get('p99_ms'))} ms over {floor.get('count', '-')} timed wake-ups"
        if isinstance(floor, dict)
        else ""
    )
    return Table(
        [
            "link",
            "dir",
            "probes",
            "W1 ms",
            "KS",
            "tolerance ms",
            "p10 ms meas / oracle",
            "p50",
            "p90",
            "p99",
            "HARQ shares measured (expected %)",
            "per slot at saturation",
        ],
        rows,
        caption="radio directions against the closed-form oracle (one-way delay of sparse "
        f"probes, net of the wired delay and the path without the link){timer}",
    )
