"""Each vehicle's path to its edge (run.json's `paths`, written by the orchestrator):
addresses, the N3 tunnel, the edge's placement and each hop's delay, configured and as the
link self-test measured it, what the path gave, and with a UPF what GTP-U added on N3
(run.json's `core_path`). Nothing of it goes into summary.json.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from reports.document import Para, Section, Table
from reports.mcapread import RunData
from reports.sections.fmt import cell, ms


def paths_section(
    data: RunData,
    per_vehicle: dict[str, Any] | None = None,
    linktest: dict[str, Any] | None = None,
) -> Section | None:
    """Each vehicle's path to its edge (run.json `paths`): addresses, the N3 tunnel, the edge's
    placement and each hop's delay, configured and, where the link self-test ran, measured
    (its one-way median per direction, `_measured_hops`), and what the path gave (the
    summary's `per_vehicle`): its requests' median latency and EdgeLoc's mean error, so
    placements compare side by side; with a UPF, what GTP-U added on N3."""
    run = data.run_json
    paths, core = run.get("paths") or [], run.get("core_path")
    if not paths:
        return None
    sec = Section("Path to the edge")
    measured = _measured_hops(linktest)
    rows = []
    for p in paths:
        tunnel = p.get("tunnel") or {}
        hops = " + ".join(
            f"{h['link']} ({h['kind']}, {cell(h.get('uplink_delay_ms'), '{:g}')}/"
            f"{cell(h.get('downlink_delay_ms'), '{:g}')} ms"
            + (f"; measured {measured[h['link']]})" if h["link"] in measured else ")")
            for h in p.get("hops", [])
        )
        rows.append(
            [
                p["vehicle"],
                p["address"],
                p["gnb"],
                p.get("upf") or "-",
                f"UL {tunnel['ul_teid']} / DL {tunnel['dl_teid']}" if tunnel else "-",
                f"{p['edge']} {p['edge_address']} ({p['placement']})",
                hops,
                *_path_outcome((per_vehicle or {}).get(p["vehicle"]) or {}),
            ]
        )
    sec.add(
        Table(
            [
                "vehicle",
                "address",
                "gNB",
                "UPF",
                "N3 TEIDs",
                "edge (placement)",
                "hops (up/down delay" + (", measured by the link self-test)" if measured else ")"),
                "answers / requests",
                "median latency ms",
                "EdgeLoc mean error m",
            ],
            rows,
        )
    )
    if core:
        share = core.get("gtp_overhead_share")
        sec.add(
            Para(
                f"GTP-U on N3: {core.get('gtp_overhead_bytes_per_packet')} bytes per packet "
                f"(outer IPv4, UDP, GTP-U with its PDU Session Container); "
                f"{core.get('gtp_overhead_bytes', 0) / 1e6:.2f} MB of the "
                f"{core.get('n3_bytes', 0) / 1e6:.2f} MB on N3"
                + (f" ({share * 100:.1f}%)" if share is not None else "")
                + f"; UE pool {core.get('ue_pool')}."
            )
        )
        if core.get("qos_flows"):
            sec.add(Para(f"QoS flows: {core['qos_flows']}. {_qfi_counts(core)}"))
    return sec


def _measured_hops(linktest: dict[str, Any] | None) -> dict[str, str]:
    """Link -> "uplink/downlink" one-way delay medians (ms) that the link self-test measured
    before the nodes started, each net of the same path's delay with the link neutral
    (`owd_median_ms` - `baseline_ms`), so they read against the configured delays."""
    out: dict[str, str] = {}
    for link in (linktest or {}).get("links") or []:
        net = {}
        for d in link.get("directions") or []:
            owd, base = d.get("owd_median_ms"), d.get("baseline_ms")
            net[d.get("direction")] = None if owd is None else owd - (base or 0.0)
        if any(v is not None for v in net.values()):
            out[link["link"]] = (
                f"{cell(net.get('uplink'), '{:.2f}')}/{cell(net.get('downlink'), '{:.2f}')}"
            )
    return out


def _path_outcome(pv: dict[str, Any]) -> list[str]:
    """A vehicle's answers / requests, its answered requests' median latency and EdgeLoc's
    mean position error, as the path table shows them."""
    latency = (pv.get("latency_s") or {}).get("median")
    edgeloc = ((pv.get("methods") or {}).get("edgeloc") or {}).get("position_m") or {}
    count = f"{pv['answers']} / {pv['requests']}" if "requests" in pv else "-"
    return [count, ms(latency), cell(edgeloc.get("mean"), "{:.2f}")]


def _qfi_counts(core: dict[str, Any]) -> str:
    """G-PDUs per QFI and direction, from the gNB ends (uplink) and the UPF ends (downlink)."""
    counts: dict[str, Counter[str]] = {"uplink": Counter(), "downlink": Counter()}
    for key, stats in (core.get("endpoints") or {}).items():
        direction = "downlink" if "/" in key else "uplink"  # "upf1/gnb1" is a UPF's end
        counts[direction].update(stats.get("qfi_sent") or {})
    parts = [
        f"{d} " + ", ".join(f"QFI {q}: {n}" for q, n in sorted(c.items()))
        for d, c in counts.items()
        if c
    ]
    return f"G-PDUs sent: {'; '.join(parts)}." if parts else ""
