"""What every section shares: a figure rounded for summary.json, spread into its
statistics, and written into a table cell of the report."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from reports.document import Para


def rounded(x: float | None, nd: int = 6) -> float | None:
    """Round run times for readability; NaN/inf become null (JSON has neither)."""
    if x is None or not math.isfinite(x):
        return None
    return round(float(x), nd)


def series_stats(x: list[float]) -> dict[str, Any] | None:
    a = np.asarray([v for v in x if math.isfinite(v)], dtype=np.float64)
    if not len(a):
        return None
    return {
        "n": len(a),
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
        "max": float(a.max()),
    }


def cell(x: Any, spec: str = "{:.3f}") -> str:
    """`x` as the report writes it in a table cell: "-" for None, yes/no, a number by `spec`."""
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float | int):
        return spec.format(x)
    return str(x)


def pct(x: Any) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def ms(x: Any) -> str:
    return "-" if x is None else f"{x * 1e3:.1f}"


def not_recorded_note(what: str, why: str = "") -> Para:
    return Para(f"Not recorded: {what}" + (f" ({why})." if why else "."), "note")
