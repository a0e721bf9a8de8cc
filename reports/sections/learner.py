"""The split-point learner (its decisions, per network phase against the fastest split in
hindsight, the change detector's resets) and the split comparison: EdgeLoc replayed on the
run's drive with the learned split choice, every fixed split and the oracle
(`reports.splits`).

Its keys of summary.json:

- `learner`: {decisions, split_share {split: fraction of decisions}, switches (decisions
  that changed split), rules {explore/ucb/fixed: count}, detector_updates, resets [{vehicle,
  t_s, arm, kl, at_play}], phases [{start_s, end_s, plays, share {split: fraction}, chosen
  (most played), best_in_hindsight (lowest mean latency among splits answered >= 2 times),
  mean_latency_s {split: s}, share_best, share_best_second_half}] — one phase per span
  between applied timeline events (an event scheduled at 0 s opens the first), all vehicles
  pooled};
- `splits`: EdgeLoc with the learned split choice, every fixed split and the per-phase oracle,
  replayed on the run's drive under the run's own measured request latencies
  (`reports.splits`: the keys of `nodes.edgeloc.compare.SplitComparison.to_dict` plus
  vehicle, requests, replayed_splits, real_learned_total_m), or {skipped: why} when it cannot
  be (no nodes/config.json attachment, no torch or weights, a recorded dataset, no requests).
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from typing import Any

import numpy as np

from reports.document import Image, Para, Plot, Section, Table
from reports.mcapread import RunData
from reports.sections.fmt import cell, ms, not_recorded_note, pct, rounded
from reports.splits import split_comparison


def split_order(data: RunData) -> list[str]:
    """Split names in the model's order (from decisions' arm lists), then any others seen."""
    order: list[str] = []
    for vd in data.vehicles.values():
        for d in vd.decisions[:1]:
            order += [a for a in d.arm_names if a not in order]
        for i in sorted(vd.inference, key=lambda i: i.split_index):
            if i.split not in order:
                order.append(i.split)
        for d in vd.decisions:
            if d.chosen not in order:
                order.append(d.chosen)
    return order


def learner_summary(data: RunData) -> dict[str, Any]:
    t0 = data.t0
    decisions = [d for vd in data.vehicles.values() for d in vd.decisions]
    share = Counter(d.chosen for d in decisions)
    switches = 0
    for vd in data.vehicles.values():
        switches += sum(a.chosen != b.chosen for a, b in itertools.pairwise(vd.decisions))
    resets = [
        {"vehicle": v, "t_s": rounded(u.t - t0), "arm": u.arm, "kl": u.kl, "at_play": u.at_play}
        for v, vd in data.vehicles.items()
        for u in vd.detector
        if u.reset
    ]
    return {
        "decisions": len(decisions),
        "split_share": {
            s: share[s] / len(decisions) for s in split_order(data) if decisions and share[s]
        },
        "switches": switches,
        "rules": dict(sorted(Counter(d.rule for d in decisions).items())),
        "detector_updates": sum(len(vd.detector) for vd in data.vehicles.values()),
        "resets": resets,
        "phases": learner_phases(data),
    }


def learner_phases(data: RunData) -> list[dict[str, Any]]:
    """Per network phase (the spans between applied timeline events), all vehicles pooled:
    what the learner chose, and which split was fastest in hindsight (lowest mean measured
    latency among splits answered at least twice in the phase)."""
    t0 = data.t0
    decisions = sorted((d.t - t0, d.chosen) for vd in data.vehicles.values() for d in vd.decisions)
    answers = [
        (i.t - t0, i.split, i.latency_s)
        for vd in data.vehicles.values()
        for i in vd.inference
        if i.ok and math.isfinite(i.latency_s)
    ]
    if not decisions:
        return []
    end = max([decisions[-1][0], *(a[0] for a in answers)])
    # An event scheduled at 0 s sets the network the run starts on: it is applied while the
    # nodes come up, so the first decisions can precede it by a fraction of a second, and
    # cutting there would report a phase of one or two plays.
    cuts = sorted(
        {
            e.t - t0
            for e in data.link_events
            if e.scheduled_s > 0 and 0.0 < e.t - t0 < end and e.action != "channel"
        }
    )
    bounds = [min(0.0, decisions[0][0]), *cuts, end]
    out = []
    for k, (a, b) in enumerate(itertools.pairwise(bounds)):
        last = k == len(bounds) - 2
        inside = [c for t, c in decisions if a <= t < b or (last and t == b)]
        lat: dict[str, list[float]] = {}
        for t, split, latency in answers:
            if a <= t < b or (last and t == b):
                lat.setdefault(split, []).append(latency)
        means = {sp: float(np.mean(v)) for sp, v in lat.items() if len(v) >= 2}
        best = min(means, key=lambda sp: (means[sp], sp)) if means else None
        counts = Counter(inside)
        half = inside[len(inside) // 2 :]
        out.append(
            {
                "start_s": rounded(a),
                "end_s": rounded(b),
                "plays": len(inside),
                "share": {sp: counts[sp] / len(inside) for sp in split_order(data) if counts[sp]},
                "chosen": min(counts, key=lambda sp: (-counts[sp], sp)) if inside else None,
                "best_in_hindsight": best,
                "mean_latency_s": {sp: means[sp] for sp in split_order(data) if sp in means},
                "share_best": counts[best] / len(inside) if best and inside else None,
                "share_best_second_half": (
                    sum(c == best for c in half) / len(half) if best and half else None
                ),
            }
        )
    return out


def splits_summary(
    data: RunData, per_vehicle: dict[str, Any], splits: bool | str = True
) -> dict[str, Any]:
    """summary.json's `splits`: the split comparison (`reports.splits`) against each vehicle's
    recorded EdgeLoc total (`per_vehicle`), or {skipped: why} when `splits` is False or a
    string (the reason the report gives)."""
    why = splits if isinstance(splits, str) else "not computed (the report was built without it)"
    split_block: dict[str, Any] = {"skipped": why}
    if splits is True:
        edgeloc = {v: pv["methods"].get("edgeloc") for v, pv in per_vehicle.items()}
        real = {v: (b["position_m"] or {}).get("total") for v, b in edgeloc.items() if b}
        split_block = split_comparison(data, real)
    return split_block


def learner_section(data: RunData, s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Split-point learner")
    lr = s["learner"]
    if not lr["decisions"]:
        sec.add(not_recorded_note("split decisions", "/<vehicle>/split_decision"))
    else:
        sec.add(
            Para(
                f"{lr['decisions']} decisions, {lr['switches']} split changes; rules: "
                + ", ".join(f"{k} {v}" for k, v in lr["rules"].items())
                + "."
            ),
            Table(
                ["split", "share of decisions"],
                [[k, f"{100 * v:.1f}%"] for k, v in lr["split_share"].items()],
            ),
        )
    if lr["phases"]:
        sec.add(
            Table(
                [
                    "from s",
                    "to s",
                    "plays",
                    "most played",
                    "share",
                    "fastest in hindsight",
                    "its share",
                    "in 2nd half",
                    "mean latency per split ms",
                ],
                [
                    [
                        cell(ph["start_s"], "{:.2f}"),
                        cell(ph["end_s"], "{:.2f}"),
                        str(ph["plays"]),
                        cell(ph["chosen"]),
                        pct(ph["share"].get(ph["chosen"])) if ph["chosen"] else "-",
                        cell(ph["best_in_hindsight"]),
                        pct(ph["share_best"]),
                        pct(ph["share_best_second_half"]),
                        ", ".join(f"{k} {v * 1e3:.1f}" for k, v in ph["mean_latency_s"].items()),
                    ]
                    for ph in lr["phases"]
                ],
                caption="per network phase (between applied timeline events), vehicles pooled",
            )
        )
    for v in data.vehicles:
        p = plots.get(f"split:{v}")
        if p:
            sec.add(Image(p))
    if lr["detector_updates"] == 0 and not any(vd.detector for vd in data.vehicles.values()):
        sec.add(not_recorded_note("change-detector updates", "/<vehicle>/detector"))
    elif lr["resets"]:
        sec.add(
            Table(
                ["vehicle", "t (s)", "arm", "KL", "at play"],
                [
                    [
                        r["vehicle"],
                        cell(r["t_s"], "{:.2f}"),
                        r["arm"],
                        cell(r["kl"], "{:.3f}"),
                        str(r["at_play"]),
                    ]
                    for r in lr["resets"]
                ],
                caption=f"detector resets ({lr['detector_updates']} detector updates)",
            )
        )
    else:
        sec.add(Para(f"No detector reset in {lr['detector_updates']} detector updates."))
    return sec


def splits_section(s: dict[str, Any], plots: dict[str, Plot | None]) -> Section:
    sec = Section("Split points: learned, fixed, oracle")
    sp = s.get("splits") or {}
    if "skipped" in sp and "rows" not in sp:
        return sec.add(Para(f"Not computed: {sp['skipped']}.", "note"))
    sec.add(
        Para(
            "EdgeLoc replayed on this run's drive (the dataset regenerated from the attached "
            "nodes' settings, the same DNN) with the learned split choice, with every split "
            "the run measured held fixed, and with the oracle. Every replayed request takes "
            f"the latency of one of {sp['vehicle']}'s {sp['requests']} measured requests of "
            "the same split in the same phase. The fixed-split and oracle rows are replays with "
            "the run's measured latencies, not runs of their own; the oracle plays the most "
            "accurate split of each phase, which it knows by reading ground truth (no vehicle "
            "could). Cells: mean position error m / mean request latency ms."
        )
    )
    if sp.get("fusion"):
        sec.add(Para(f"EdgeLoc's fusion in every row: {sp['fusion']}."))
    phases = sp["phases"]
    heads = ["policy", "total m"] + [f"{p['start_s']:g}-{p['end_s']:g} s" for p in phases]
    rows = []
    for r in sp["rows"]:
        cells = [
            f"{cell(f['mean_error_m'], '{:.2f}')} / {ms(f['mean_latency_s'])}" for f in r["phases"]
        ]
        rows.append([r["policy"], cell(r["total_m"], "{:.1f}"), *cells])
    sec.add(Table(heads, rows, caption=f"replays under {sp['vehicle']}'s measured latencies"))
    real = sp.get("real_learned_total_m")
    learned = next((r for r in sp["rows"] if r["policy"] == "learned"), None)
    sec.add(
        Para(
            f"The real run's learned EdgeLoc ({sp['vehicle']}, as recorded): total "
            f"{cell(real, '{:.1f}')} m"
            + (f"; its replay above: {learned['total_m']:.1f} m." if learned else ".")
        )
    )
    for p in phases:
        if p["latency_best"] is None or p["error_best"] is None:
            verdict = "no split was timed in this phase"
        else:
            verdict = "the same split" if p["agree"] else "they DISAGREE"
        sec.add(
            Para(
                f"Phase {p['start_s']:g}-{p['end_s']:g} s: fastest {cell(p['latency_best'])}, "
                f"most accurate {cell(p['error_best'])} ({verdict})."
            )
        )
    # Latency-best against error-best, inversions and the learned run against the fixed
    # splits: what the drive resolves is a warning; a tie inside its noise is a row of one
    # table (with K splits there are up to K(K-1)/2 pairs per phase). Imported here: the
    # comparison that wrote these rows has loaded it (and torch) already; a report without
    # them does not pay for it.
    from nodes.edgeloc.compare import WITHIN_NOISE

    for line in sp["disagreements"]:
        if WITHIN_NOISE not in line:
            sec.add(Para(f"Against the paper's claim: {line}.", "warning"))
    ties = [
        [
            f"{p['start_s']:g}-{p['end_s']:g} s",
            v["slower"],
            v["faster"],
            f"{v['by_m']:.2f}",
            f"±{v['noise_m']:.2f}",
        ]
        for p in phases
        for v in p.get("inversions", [])
        if not v["beyond_noise"] and v["noise_m"] is not None and math.isfinite(v["noise_m"])
    ]
    if ties:
        sec.add(
            Table(
                ["phase", "more accurate", "than the faster", "by m", "drive's noise m"],
                ties,
                caption="ties: a slower split ahead of a faster one within the drive's noise",
            )
        )
    for line in sp["disagreements"]:
        if line.startswith("the learned run") and WITHIN_NOISE in line:
            sec.add(Para(f"A tie: {line}.", "note"))
    if any(p.get("inversions") for p in phases):
        sec.add(
            Para(
                "The drive's noise is Student's 95% interval for the mean difference in error "
                "between the two splits, from that difference's means over blocks of about "
                f"{sp['noise_block_s']:g} s: an inversion within it is a tie that this drive "
                "cannot resolve, one beyond it is evidence against the claim.",
                "note",
            )
        )
    fixed = [r for r in sp["rows"] if r["policy"].startswith("fixed:")]
    if len(fixed) < 2:
        sec.add(
            Para(
                "The run measured fewer than two splits, so latency and error cannot be "
                "compared across splits."
            )
        )
    elif not sp["disagreements"]:
        sec.add(
            Para(
                "In every phase the fastest split is also the most accurate, and error rises "
                "with latency across the splits, as the paper claims."
            )
        )
    if sp.get("learned_beats_fixed"):  # when it does not, a disagreement above says so
        sec.add(Para(f"The learned replay beats every fixed split (best: {sp['best_fixed']})."))
    for k, why in sp.get("skipped", {}).items():
        sec.add(Para(f"No row for {k}: {why}.", "note"))
    if sp.get("skipped"):
        sec.add(
            Para(
                "The learned and oracle replays chose among the measured splits only: "
                + ", ".join(sp.get("replayed_splits", []))
                + ".",
                "note",
            )
        )
    if plots.get("split_error_latency"):
        sec.add(Image(plots["split_error_latency"]))  # type: ignore[arg-type]
    return sec
