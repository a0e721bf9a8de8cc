"""`testbed sweep --seeds N` (issue #20, part 2): each variant repeated with derived seeds, and
each figure's mean with its 95% confidence interval, checked against scipy's Student t."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from scipy import stats as scipy_stats

from testbed.errors import BadInput
from testbed.sweep import run_sweep
from testbed.sweep.stats import derived_seed, mean_ci, t975

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "scenarios" / "smoke.yaml"


@pytest.mark.parametrize("df", [1, 2, 3, 5, 9, 29, 30, 31, 40, 60, 120, 1000])
def test_t_quantile_matches_scipy(df: int) -> None:
    assert t975(df) == pytest.approx(scipy_stats.t.ppf(0.975, df), abs=2e-4)


def test_mean_ci_is_students_interval() -> None:
    xs = [10.0, 12.5, 9.0, 14.0, 11.0]
    got = mean_ci(xs)
    assert got is not None
    lo, hi = scipy_stats.t.interval(0.95, len(xs) - 1, loc=sum(xs) / 5, scale=scipy_stats.sem(xs))
    assert got["mean"] == pytest.approx((lo + hi) / 2)
    assert got["ci95"] == pytest.approx((hi - lo) / 2, rel=1e-4)
    assert got["n"] == 5
    assert mean_ci([3.0, None, math.nan])["ci95"] is None  # type: ignore[index,list-item]
    assert mean_ci([None]) is None


def test_seeds_derive_from_the_scenarios_own() -> None:
    assert [derived_seed(7, k) for k in range(3)] == [7, 8, 9]
    assert derived_seed(2**32 - 1, 1) == 0


def test_a_seeded_sweep_repeats_each_variant_and_reports_mean_and_interval(
    tmp_path: Path,
) -> None:
    lines: list[str] = []
    report = run_sweep(
        SMOKE,
        ["links.air.uplink.delay=2ms,80ms"],
        out=tmp_path / "sweep",
        progress=lines.append,
        duration="4s",
        seeds=3,
    )
    rows = report.rows
    base = next(
        int(x.split(":")[1]) for x in SMOKE.read_text().splitlines() if x.startswith("seed:")
    )
    assert [(r.index, r.seed) for r in rows] == [(i, base + k) for i in (0, 1) for k in range(3)]
    totals = [r.methods["edgeloc"]["total_m"] for r in rows if r.index == 0]
    assert len(set(totals)) > 1  # another seed, another drive: not three copies
    data = json.loads((tmp_path / "sweep" / "sweep.json").read_text())
    assert data["seeds"] == 3
    first = next(g for g in data["statistics"] if g["index"] == 0)
    stat = first["metrics"]["edgeloc_total_m"]
    assert stat["n"] == 3 and stat["mean"] == pytest.approx(sum(totals) / 3)
    sd = math.sqrt(sum((t - stat["mean"]) ** 2 for t in totals) / 2)
    assert stat["ci95"] == pytest.approx(scipy_stats.t.ppf(0.975, 2) * sd / math.sqrt(3), rel=1e-3)
    md = (tmp_path / "sweep" / "sweep.md").read_text()
    assert "## Across 3 seeds (mean ± 95% confidence interval)" in md
    assert f"{stat['mean']:.1f} ± {stat['ci95']:.1f}" in md
    files = sorted(p.name for p in (tmp_path / "sweep" / "variants").iterdir())
    assert files[0] == f"v01-s{base}.yaml" and len(files) == 6
    assert f"seed: {base + 1}" in (tmp_path / "sweep" / "variants" / files[1]).read_text()
    # The same seed replays the same drive: seed base+1 again gives the same total.
    again = run_sweep(
        SMOKE,
        ["links.air.uplink.delay=2ms"],
        out=tmp_path / "again",
        progress=lambda _: None,
        duration="4s",
        seeds=2,
    )
    assert again.rows[1].methods["edgeloc"]["total_m"] == pytest.approx(totals[1])


def test_seeds_out_of_range_are_bad_input(tmp_path: Path) -> None:
    with pytest.raises(BadInput, match="--seeds"):
        run_sweep(SMOKE, ["seed=1"], out=tmp_path, progress=lambda _: None, seeds=0)


def test_a_variant_whose_runs_all_fail_is_reported_not_averaged(tmp_path: Path) -> None:
    from testbed.sweep.grid import parse_set
    from testbed.sweep.jobs import _failed_row
    from testbed.sweep.output import SweepReport, markdown

    ok = run_sweep(
        SMOKE, ["seed=7"], out=tmp_path / "ok", progress=lambda _: None, duration="4s", seeds=2
    )
    failed = [_failed_row(1, {"seed": "9"}, "av1", "the edge server died") for _ in range(3)]
    for k, r in enumerate(failed):
        r.seed = 9 + k
    axes = [parse_set("seed=7,9")]
    report = SweepReport("smoke.yaml", "real", axes, rows=[*ok.rows, *failed], seeds=3)
    stats = {g["index"]: g for g in report.statistics()}
    assert stats[1]["failed"] == 3
    assert all(v is None for v in stats[1]["metrics"].values())  # nothing averaged
    assert stats[0]["metrics"]["edgeloc_total_m"]["n"] == 2
    md = markdown(report)
    assert "| 9 | 0 (3 failed) | - |" in md
    assert md.count("failed: the edge server died") == 3
