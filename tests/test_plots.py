"""The report's figures draw errors and rates, which are never negative, on axes that show no
negative values: log axes from a positive floor, never a symmetric log axis whose lower half
is for values that cannot exist."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from matplotlib.figure import Figure
from report_synth import stamp
from test_report import T0, small_run, write_run

import reports.plots
from reports.build import summarize
from reports.mcapread import read_run
from reports.plots import ERROR_FLOOR_M, RATE_FLOOR_MBIT, draw_all
from reports.sections.accuracy import method_errors


@pytest.fixture(scope="module")
def figures(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Figure]:
    """Every figure of a synthetic run (a frame with zero error, an idle link sample), by
    file name, as it was when saved."""
    s = small_run()
    t = T0 + 1.5  # after the three 2 Mbit/s samples: nothing moved, a rate of exactly 0
    s.add(
        t,
        "/links/counters",
        "LinkCounters",
        {
            "stamp": stamp(t),
            "link": "av1-gnb1",
            "direction": "up",
            "backend": "userspace",
            "packets_in": 200,
            "bytes_in": 250_000,
            "packets_out": 200,
            "bytes_out": 250_000,
            "packets_dropped": 2,
            "bytes_dropped": 2000,
            "queue_packets": 0,
        },
    )
    tmp_path = tmp_path_factory.mktemp("plots")
    data = read_run(write_run(tmp_path, s) / "run.mcap")
    saved: dict[str, Figure] = {}
    real_save = reports.plots._save

    def save(fig: Figure, folder: Path, name: str) -> str:
        saved[name] = fig
        return real_save(fig, folder, name)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(reports.plots, "_save", save)
        # one process: the figures are captured here as they are saved
        draw_all(data, method_errors(data), summarize(data), tmp_path / "plots", workers=1)
    return saved


def test_figures_drawn_on_forked_workers_are_those_drawn_one_after_another(
    tmp_path: Path,
) -> None:
    data = read_run(write_run(tmp_path, small_run()) / "run.mcap")
    errs, summary = method_errors(data), summarize(data)
    one = draw_all(data, errs, summary, tmp_path / "one", workers=1)
    two = draw_all(data, errs, summary, tmp_path / "two", workers=2)
    assert list(two) == list(one) and two == one
    files = sorted(p.name for p in (tmp_path / "one").iterdir())
    assert files and files == sorted(p.name for p in (tmp_path / "two").iterdir())
    for name in files:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


def _axes(fig: Figure) -> list[Any]:
    return [a for a in fig.get_axes() if a.get_visible()]


def test_no_figure_uses_a_symmetric_log_axis(figures: dict[str, Figure]) -> None:
    assert {"errors_over_time.png", "error_boxplot.png", "link_rates.png"} <= set(figures)
    for name, fig in figures.items():
        for ax in _axes(fig):
            assert ax.get_yscale() != "symlog", f"{name}: {ax.get_ylabel()!r} is symlog"
            assert ax.get_xscale() != "symlog", f"{name}: {ax.get_xlabel()!r} is symlog"


@pytest.mark.parametrize(
    ("name", "ylabel", "floor"),
    [
        ("errors_over_time.png", "error (m, log)", ERROR_FLOOR_M),
        ("error_boxplot.png", "position error (m), log", ERROR_FLOOR_M),
        ("link_rates.png", "delivered (Mbit/s, log)", RATE_FLOOR_MBIT),
    ],
)
def test_errors_and_rates_start_at_a_positive_floor(
    figures: dict[str, Figure], name: str, ylabel: str, floor: float
) -> None:
    (ax,) = [a for a in _axes(figures[name]) if a.get_ylabel() == ylabel]
    lo, hi = ax.get_ylim()
    assert ax.get_yscale() == "log"
    assert lo == pytest.approx(floor) and lo > 0
    assert hi > 1.0  # the data (errors up to 1 m, 2 Mbit/s) fits under the top
    # values of zero (edgeloc's frame 0, the idle sample) are drawn on the bottom line
    data_lines = [ln for ln in ax.get_lines() if ln.get_transform() == ax.transData]
    ys = [y for line in data_lines for y in line.get_ydata()]
    assert min(ys) == pytest.approx(floor)
    labels = {t.get_text() for t in ax.get_yticklabels() if t.get_text()}
    assert f"≤{floor:g}" in labels


def test_heading_errors_are_linear_from_zero(figures: dict[str, Figure]) -> None:
    axes = _axes(figures["error_boxplot.png"])
    (ax,) = [a for a in axes if a.get_ylabel() == "heading error (deg)"]
    assert ax.get_yscale() == "linear"
    assert ax.get_ylim()[0] == 0
