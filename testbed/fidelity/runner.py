"""Running cases: each variant's probes through the relay (or the stages on a fake clock), judged
against the source, written as JSON and one CDF figure per case.

    results = run_cases(find(["srsran-urllc"]), real=True, progress=print)
    print(table(results)); write(results, Path("fidelity"))
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from netem.nr.radio import Radio
from testbed.fidelity.case import Case, Variant
from testbed.fidelity.data import load_samples
from testbed.fidelity.judge import (
    BLOCK_S,
    CaseResult,
    Check,
    Judged,
    figures,
    judge_data,
    judge_figures,
    judge_floor,
    judge_harq,
    judge_segmented,
)
from testbed.fidelity.model import Delays, model_delays


def harq_step_ms(radio: Radio) -> tuple[float, float]:
    """How much later a block sent again in the uplink is decoded: the least and the most
    over the grid's occasions (the first occasion `harq_slots` after a failed one)."""
    grid = radio.grid("uplink")
    period = grid.period_s
    ends = [(o.start_s, o.end_s) for o in grid.occasions]
    steps = []
    for _, end in ends:
        t = end + radio.harq_s
        k = 0
        while True:
            later = [e + k * period for s, e in ends if s + k * period >= t - 1e-12]
            if later:
                steps.append((min(later) - end) * 1000)
                break
            k += 1
    return min(steps), max(steps)


def judge_variant(case: Case, variant: Variant, delays: dict[str, Delays]) -> Judged:
    judged = Judged(case.name, variant.name)
    for measure, got in delays.items():
        ms = got.delivered
        if not ms:
            judged.checks.append(Check(f"{measure} delivered", 0.0, "probes", "> 0", False))
            continue
        ours = figures(ms)
        ours["lost"] = float(len(got.ms) - len(ms))
        ours["host_baseline"] = got.baseline_ms
        judged.ours[measure] = ours
        judged.samples[measure] = ms
        if measure in variant.published:
            judged.checks += judge_figures(measure, ours, variant.published[measure])
        if measure in variant.floors:
            judged.checks.append(judge_floor(measure, ours["min"], variant.floors[measure]))
        if measure in variant.data:
            values, weights = load_samples(variant.data[measure])
            block = max(1, round(BLOCK_S / case.probe.interval_s))
            judged.checks += judge_data(measure, ms, values, weights, block)
    components = variant.components
    uplink = delays.get("uplink")
    if uplink is not None:
        if "harq_share" in components:
            judged.checks.append(judge_harq(uplink.counters, float(components["harq_share"])))
        if "segmented_share" in components:
            judged.checks.append(
                judge_segmented(
                    uplink.counters, len(uplink.delivered), float(components["segmented_share"])
                )
            )
    if "harq_step_ms" in components:
        lo, hi = (float(x) for x in components["harq_step_ms"])
        least, most = harq_step_ms(variant.radio)
        judged.checks.append(
            Check("HARQ step (ms)", least, f"{lo:g}-{hi:g}", "within", lo <= least <= most <= hi)
        )
    return judged


def run_cases(
    cases: list[Case],
    real: bool = True,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list[CaseResult]:
    """Every variant of every case, measured (`real`: packets through the relay in namespaces;
    else the stages on a fake clock) and judged."""
    out = []
    for case in cases:
        judged = []
        for variant in case.variants:
            if progress:
                progress(f"{case.name} / {variant.name}: {variant.radio}")
            if real:
                from testbed.fidelity.measure import measure_delays

                delays = measure_delays(variant.radio, case.probe, case.wired_ms, seed, progress)
            else:
                delays = {
                    m: model_delays(variant.radio, case.probe, m, case.wired_ms, seed)
                    for m in case.probe.measures
                }
            judged.append(judge_variant(case, variant, delays))
        out.append(CaseResult(case, judged, real))
    return out


def table(results: list[CaseResult]) -> str:
    """Ours against theirs, one line per figure, each case's verdict under it."""
    lines = []
    for result in results:
        case = result.case
        lines.append(f"{case.name}: {case.title}")
        lines.append(
            f"  source: {case.source['cite']} ({case.source['url']}; {case.source['licence']})"
        )
        if case.calibrated:
            lines.append(f"  calibrated: {case.calibrated}")
        for judged in result.variants:
            lines.append(f"  variant {judged.variant}")
            for measure, ours in judged.ours.items():
                figs = "  ".join(f"{k} {ours[k]:.2f}" for k in ("min", "p50", "mean", "p90", "p99"))
                lines.append(
                    f"    ours {measure:<8} {figs}  (n {ours['n']:.0f}, lost {ours['lost']:.0f}"
                    f", host baseline {ours['host_baseline']:.2f} taken off)"
                )
            for c in judged.checks:
                ours_s = f"{c.ours:.3f}" if isinstance(c.ours, float) else str(c.ours)
                theirs = f"{c.theirs:g}" if isinstance(c.theirs, float) else str(c.theirs)
                mark = "ok" if c.ok else "OUT"
                lines.append(
                    f"    {c.what:<28} ours {ours_s:>8}  theirs {theirs:>9}  {c.tolerance}  {mark}"
                )
        if case.not_modelled:
            lines.append(f"  not modelled: {case.not_modelled}")
        lines.append(f"  verdict: {'within tolerance' if result.ok else 'OUT of tolerance'}")
        lines.append("")
    return "\n".join(lines)


def to_dict(results: list[CaseResult]) -> dict[str, Any]:
    return {
        "ok": all(r.ok for r in results),
        "cases": [
            {
                "case": r.case.name,
                "title": r.case.title,
                "source": r.case.source,
                "real_packets": r.real,
                "calibrated": r.case.calibrated,
                "not_modelled": r.case.not_modelled,
                "ok": r.ok,
                "variants": [
                    {
                        "variant": j.variant,
                        "ok": j.ok,
                        "ours": j.ours,
                        "checks": [c.to_dict() for c in j.checks],
                    }
                    for j in r.variants
                ],
            }
            for r in results
        ],
    }


def write(results: list[CaseResult], folder: Path) -> list[Path]:
    """fidelity.json and one CDF figure per case (ours beside theirs) in `folder`."""
    from testbed.fidelity.figure import cdf_figure

    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / "fidelity.json"]
    tmp = paths[0].with_suffix(".json.tmp")
    tmp.write_text(json.dumps(to_dict(results), indent=2) + "\n")
    tmp.replace(paths[0])
    for result in results:
        paths.append(cdf_figure(result, folder / f"{result.case.name}.png"))
    return paths
