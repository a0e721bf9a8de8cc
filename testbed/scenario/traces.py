"""Bandwidth trace files: read them, or say which line is wrong.

Two formats:
- `mahimahi`: one integer per line, a millisecond timestamp at which one 1500-byte packet may
  be delivered; timestamps never go down and the last one is > 0 (it is the trace's period).
- `csv`: `time_s,mbit` rows (an optional header line), times never go down, rates >= 0; each
  row's rate holds until the next row's time.
Blank lines and `#` comments are skipped in both.

This module finds *every* wrong line, for `testbed validate`; the link emulator reads traces
with `netem.traces`, and the loader also runs that reader so that a trace which validates is
one the emulator accepts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

TraceFormat = Literal["mahimahi", "csv"]
MAX_PROBLEMS = 5  # per file: after this many, one line says how many more there were


@dataclass(frozen=True)
class TraceProblem:
    """One wrong line of a trace file (1-based)."""

    line: int
    expected: str
    found: str


class TraceError(ValueError):
    """A trace file cannot be used; `problems` name its wrong lines."""

    def __init__(self, path: Path, problems: list[TraceProblem]) -> None:
        self.path, self.problems = path, problems
        super().__init__(
            "\n".join(f"{path}:{p.line}: expected {p.expected}, found {p.found}" for p in problems)
        )


@dataclass(frozen=True)
class CsvTrace:
    """Piecewise-constant rate: from `times_s[i]` on, the link carries `rates_bps[i]`."""

    times_s: tuple[float, ...]
    rates_bps: tuple[float, ...]


@dataclass(frozen=True)
class MahimahiTrace:
    """Delivery opportunities (ms); the trace repeats every `period_ms`."""

    opportunities_ms: tuple[int, ...]

    @property
    def period_ms(self) -> int:
        return self.opportunities_ms[-1]


def default_format(path: str | Path) -> TraceFormat:
    """The format a trace file has when the scenario does not say: by its extension."""
    return "csv" if str(path).lower().endswith(".csv") else "mahimahi"


def _lines(text: str) -> list[tuple[int, str]]:
    """Numbered lines with content; blank lines and `#` comments are skipped (as netem does)."""
    out = []
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if line and not line.startswith("#"):
            out.append((n, line))
    return out


def _cap(problems: list[TraceProblem]) -> list[TraceProblem]:
    if len(problems) <= MAX_PROBLEMS:
        return problems
    extra = len(problems) - MAX_PROBLEMS
    last = problems[MAX_PROBLEMS]
    return [
        *problems[:MAX_PROBLEMS],
        TraceProblem(last.line, "a valid line", f"{extra} more wrong line(s) from here on"),
    ]


def parse_mahimahi(text: str) -> tuple[MahimahiTrace | None, list[TraceProblem]]:
    problems: list[TraceProblem] = []
    stamps: list[int] = []
    last_line = 0
    for n, line in _lines(text):
        last_line = n
        if not line.isdigit():
            problems.append(TraceProblem(n, "a whole number of milliseconds", repr(line[:40])))
            continue
        value = int(line)
        if stamps and value < stamps[-1]:
            problems.append(
                TraceProblem(n, f"a timestamp >= the previous one ({stamps[-1]})", str(value))
            )
            continue
        stamps.append(value)
    if not problems and not stamps:
        problems.append(TraceProblem(1, "at least one timestamp", "an empty file"))
    elif not problems and stamps[-1] == 0:
        problems.append(
            TraceProblem(last_line, "a last timestamp > 0 (it is the trace's period)", "0")
        )
    if problems:
        return None, _cap(problems)
    return MahimahiTrace(tuple(stamps)), []


def _number(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def parse_csv(text: str) -> tuple[CsvTrace | None, list[TraceProblem]]:
    problems: list[TraceProblem] = []
    times: list[float] = []
    rates: list[float] = []
    row_expected = "a row time_s,mbit (two numbers)"
    for index, (n, line) in enumerate(_lines(text)):
        cells = [c.strip() for c in line.split(",")]
        numbers = [_number(c) for c in cells]
        if index == 0 and len(cells) == 2 and all(v is None for v in numbers):
            continue  # a header such as `time_s,mbit`
        if len(cells) != 2 or None in numbers:
            problems.append(TraceProblem(n, row_expected, repr(line[:40])))
            continue
        t, mbit = numbers
        assert t is not None and mbit is not None
        if t < 0:
            problems.append(TraceProblem(n, "a time >= 0", cells[0]))
        elif times and t < times[-1]:
            problems.append(
                TraceProblem(n, f"a time >= the previous one ({times[-1]:g})", cells[0])
            )
        elif mbit < 0:
            problems.append(TraceProblem(n, "a rate >= 0 Mbit/s", cells[1]))
        else:
            times.append(t)
            rates.append(mbit * 1e6)
    if not problems and not times:
        problems.append(TraceProblem(1, "at least one time_s,mbit row", "no rows"))
    if problems:
        return None, _cap(problems)
    return CsvTrace(tuple(times), tuple(rates)), []


def read_trace(path: Path, fmt: TraceFormat | None = None) -> CsvTrace | MahimahiTrace:
    """Read a trace file; raise `TraceError` naming its wrong lines, `OSError` if unreadable."""
    fmt = fmt or default_format(path)
    text = path.read_text(encoding="utf-8", errors="replace")
    trace, problems = parse_csv(text) if fmt == "csv" else parse_mahimahi(text)
    if trace is None:
        raise TraceError(path, problems)
    return trace
