"""The report of a sweep: one row per variant and vehicle (`VariantResult`), the whole
`SweepReport`, and how it is written: `sweep.json`, `sweep.md` (one table) and `sweep.png`
(errors and latency across the variants).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from testbed.sweep.grid import Axis, label
from testbed.sweep.stats import mean_ci


@dataclass
class VariantResult:
    """One row of the report: a variant on one vehicle."""

    index: int
    values: dict[str, str]
    vehicle: str
    folder: str
    methods: dict[str, dict[str, float | None]]  # method -> {total_m, mean_m}
    reductions_pct: dict[str, float | None]  # EdgeLoc's reduction vs vo, dnn, kalman
    split_share: dict[str, float]
    mean_latency_s: float | None  # answered requests, thread 2 start -> answer
    requests: int
    lost: int
    wall_s: float
    error: str | None = None
    seed: int = 0  # the scenario's seed this row ran with (`--seeds`)
    host: str = ""  # the Ray engine's: the host whose task gave this row ("" here)
    attempts: int = 1  # 2: the Ray engine ran it again after a failure or a dead host

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class SweepReport:
    scenario: str
    mode: str  # replay | real
    axes: list[Axis]
    rows: list[VariantResult] = field(default_factory=list)
    out: Path = Path()
    wall_s: float = 0.0
    seeds: int = 1  # repetitions of each variant, with derived seeds

    def statistics(self) -> list[dict[str, Any]]:
        """Per variant and vehicle, each metric's mean and 95% interval over the seeds."""
        return across_seeds(self.rows)

    @property
    def failed(self) -> list[VariantResult]:
        return [r for r in self.rows if r.error]

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "mode": self.mode,
            "axes": [{"key": a.key, "values": list(a.texts)} for a in self.axes],
            "variants": [r.to_dict() for r in self.rows],
            "wall_s": round(self.wall_s, 3),
            "seeds": self.seeds,
            "statistics": self.statistics() if self.seeds > 1 else None,
            "notes": _notes(self.mode),
        }


def _notes(mode: str) -> list[str]:
    if mode == "replay":
        return [
            "offline replay: the EdgeLoc loop in one process with a latency model of the path",
            "each vehicle is replayed on its own path; vehicles sharing a hop do not slow each "
            "other down in the replay (a real run, --real, has them contend)",
            "reductions: (baseline total - EdgeLoc total) / baseline total, as the paper's",
        ]
    return [
        "real runs: namespaces, emulated links and ROS 2 nodes (testbed run) per variant",
        "errors over the frames the fusion node scored; latency from the inference node",
        "reductions: (baseline total - EdgeLoc total) / baseline total, as the paper's",
    ]


def row_line(r: VariantResult) -> str:
    """A row as one line of the sweep's progress."""
    if r.error:
        return f"FAILED: {r.error.splitlines()[0]}"
    e = r.methods["edgeloc"]["total_m"]
    k = r.methods["kalman"]["total_m"]
    lat = "-" if r.mean_latency_s is None else f"{1000 * r.mean_latency_s:.1f} ms"
    return (
        f"EdgeLoc total {_num(e, '.1f')} m, Kalman {_num(k, '.1f')} m, "
        f"mean latency {lat}, {r.requests} requests ({r.lost} lost)"
    )


def _num(x: float | None, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


# ---- the report -----------------------------------------------------------------------------


def markdown(report: SweepReport) -> str:
    keys = [a.key for a in report.axes]
    multi = len({r.vehicle for r in report.rows}) > 1
    seeded = report.seeds > 1
    head = [
        *keys,
        *(["vehicle"] if multi else []),
        *(["seed"] if seeded else []),
        *(f"{m} total m" for m in ("edgeloc", "kalman", "dnn", "vo")),
        "edgeloc mean m",
        *(f"vs {m}" for m in ("vo", "dnn", "kalman")),
        "split shares",
        "mean latency ms",
        "requests (lost)",
    ]
    lines = [
        f"# Sweep of `{report.scenario}` ({report.mode})",
        "",
        f"{len({r.index for r in report.rows})} variant(s); axes: "
        + ", ".join(f"`{a.key}` = {', '.join(a.texts)}" for a in report.axes)
        + f"; {report.wall_s:.1f} s.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join(" --- " for _ in head) + "|",
    ]
    for r in report.rows:
        if r.error:
            cells = [*(r.values[k] for k in keys), *([r.vehicle] if multi else [])]
            cells += [str(r.seed)] if seeded else []
            cells += [f"failed: {r.error.splitlines()[0]}"] + [""] * (len(head) - len(cells) - 1)
            lines.append("| " + " | ".join(cells) + " |")
            continue
        shares = ", ".join(
            f"{k} {100 * s:.0f}%"
            for k, s in sorted(r.split_share.items(), key=lambda x: -x[1])
            if s > 0
        )
        cells = [
            *(r.values[k] for k in keys),
            *([r.vehicle] if multi else []),
            *([str(r.seed)] if seeded else []),
            *(_num(r.methods[m]["total_m"], ".1f") for m in ("edgeloc", "kalman", "dnn", "vo")),
            _num(r.methods["edgeloc"]["mean_m"], ".2f"),
            *(_pct(r.reductions_pct[m]) for m in ("vo", "dnn", "kalman")),
            shares or "-",
            _num(None if r.mean_latency_s is None else 1000 * r.mean_latency_s, ".1f"),
            f"{r.requests} ({r.lost})",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    if seeded:
        lines += ["", *_seed_table(report, keys, multi)]
    lines += ["", "Reductions are EdgeLoc's against each baseline (positive: EdgeLoc is better)."]
    lines += [f"- {n}" for n in _notes(report.mode)]
    return "\n".join(lines) + "\n"


def _ci(stat: dict[str, Any] | None, fmt: str) -> str:
    if stat is None:
        return "-"
    half = stat["ci95"]
    width = fmt.lstrip("+")  # a half width has no sign
    return format(stat["mean"], fmt) + ("" if half is None else " ± " + format(half, width))


def _seed_table(report: SweepReport, keys: list[str], multi: bool) -> list[str]:
    """Each variant's mean ± 95% interval (Student's t) over its seeds."""
    head = [
        *keys,
        *(["vehicle"] if multi else []),
        "seeds",
        *(f"{m} total m" for m in ("edgeloc", "kalman", "dnn", "vo")),
        *(f"vs {m} %" for m in ("vo", "dnn", "kalman")),
        "mean latency ms",
    ]
    lines = [
        f"## Across {report.seeds} seeds (mean ± 95% confidence interval)",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "|".join(" --- " for _ in head) + "|",
    ]
    for g in report.statistics():
        m = g["metrics"]
        n = len(g["seeds"]) - g["failed"]
        cells = [
            *(g["values"][k] for k in keys),
            *([g["vehicle"]] if multi else []),
            f"{n}" + (f" ({g['failed']} failed)" if g["failed"] else ""),
            *(_ci(m[f"{x}_total_m"], ".1f") for x in ("edgeloc", "kalman", "dnn", "vo")),
            *(_ci(m[f"reduction_vs_{x}_pct"], "+.1f") for x in ("vo", "dnn", "kalman")),
            _ci(m["mean_latency_ms"], ".1f"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:+.1f}%"


def plot(report: SweepReport, path: Path) -> None:
    """Total position error per method (top) and mean request latency (bottom) per variant."""
    import matplotlib

    matplotlib.use("Agg")  # no display: files only
    import matplotlib.pyplot as plt

    vehicles = list(dict.fromkeys(r.vehicle for r in report.rows))
    n = len({r.index for r in report.rows})
    ticks = [
        "\n".join(f"{v}" for v in label(report.axes, i).values())
        if len(report.axes) > 1
        else label(report.axes, i)[report.axes[0].key]
        for i in range(n)
    ]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    styles = ["-", "--", ":", "-."]
    stats = {(g["index"], g["vehicle"]): g["metrics"] for g in across_seeds(report.rows)}

    def point(i: int, vehicle: str, metric: str) -> tuple[float, float]:
        """Mean over the seeds (one seed: the row's value) and its 95% half width."""
        stat = stats.get((i, vehicle), {}).get(metric)
        if stat is None:
            return math.nan, 0.0
        return stat["mean"], stat["ci95"] or 0.0

    for vi, vehicle in enumerate(vehicles):
        style = styles[vi % len(styles)]
        suffix = f" ({vehicle})" if len(vehicles) > 1 else ""
        for ci, m in enumerate(("edgeloc", "kalman", "dnn", "vo")):
            ys, es = zip(*(point(i, vehicle, f"{m}_total_m") for i in range(n)), strict=True)
            # One colour per method, one line style per vehicle; bars: 95% over the seeds.
            top.errorbar(
                range(n), ys, yerr=es, fmt=style, marker="o", color=f"C{ci}", capsize=3,
                label=f"{m}{suffix}",
            )  # fmt: skip
        lat, lat_e = zip(*(point(i, vehicle, "mean_latency_ms") for i in range(n)), strict=True)
        bottom.errorbar(
            range(n), lat, yerr=lat_e, fmt=style, marker="o", color="black", capsize=3,
            label=f"latency{suffix}",
        )  # fmt: skip
    top.set_ylabel("total position error (m)")
    top.set_yscale("log")
    top.legend(fontsize=8, ncol=2)
    seeds = f", mean ± 95% over {report.seeds} seeds" if report.seeds > 1 else ""
    top.set_title(f"sweep of {Path(report.scenario).name} ({report.mode}{seeds})")
    bottom.set_ylabel("mean request latency (ms)")
    bottom.set_xticks(range(n), ticks, fontsize=8)
    bottom.set_xlabel(" / ".join(a.key for a in report.axes))
    if len(vehicles) > 1:
        bottom.legend(fontsize=8)
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(report: SweepReport) -> None:
    out = report.out
    (out / "sweep.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    (out / "sweep.md").write_text(markdown(report))
    plot(report, out / "sweep.png")


# ---- across seeds ------------------------------------------------------------------------


def metrics(r: VariantResult) -> dict[str, float | None]:
    """The figures of a row that `across_seeds` pools."""
    out: dict[str, float | None] = {
        f"{m}_total_m": r.methods[m]["total_m"] for m in ("edgeloc", "kalman", "dnn", "vo")
    }
    out["edgeloc_mean_m"] = r.methods["edgeloc"]["mean_m"]
    out.update({f"reduction_vs_{m}_pct": r.reductions_pct[m] for m in ("vo", "dnn", "kalman")})
    out["mean_latency_ms"] = None if r.mean_latency_s is None else 1000 * r.mean_latency_s
    return out


def across_seeds(rows: Sequence[VariantResult]) -> list[dict[str, Any]]:
    """Per (variant, vehicle), each metric's mean and 95% interval over its seeds' rows (failed
    rows left out, and counted)."""
    groups: dict[tuple[int, str], list[VariantResult]] = {}
    for r in rows:
        groups.setdefault((r.index, r.vehicle), []).append(r)
    out = []
    for (index, vehicle), group in groups.items():
        good = [metrics(r) for r in group if not r.error]
        names = list(metrics(group[0])) if group else []
        out.append(
            {
                "index": index,
                "values": group[0].values,
                "vehicle": vehicle,
                "seeds": [r.seed for r in group],
                "failed": len(group) - len(good),
                "metrics": {k: mean_ci([g[k] for g in good]) for k in names},
            }
        )
    return out
