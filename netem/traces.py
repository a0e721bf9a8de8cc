"""Bandwidth traces: when a link may deliver bytes, read from a file.

Two formats, both turned into one idea (Mahimahi's): a *delivery opportunity* is an instant at
which the link may send up to `OPPORTUNITY_BYTES` (1500) bytes.

- `mahimahi`: one integer millisecond timestamp per line; each line is one opportunity (the
  same timestamp on several lines = several opportunities at that instant). Looping repeats
  the trace with the last timestamp as its period, as `mm-link` does.
- `csv`: rows `time_s,mbit` (an optional header row and `#` comments are skipped); the rate of
  a row holds from its time until the next row's time. The trace lasts until the last row's
  time plus the interval before it (1 s for a single row), which is also the loop period.
  A rate is turned into evenly spaced opportunities (1500 bytes each).

`load_trace(path)` parses and validates a file; a bad file raises `TraceError` (a `ValueError`)
naming up to five wrong lines with their numbers. This is the only trace parser of the project:
`testbed validate` reports the same problems through the scenario loader.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from netem.errors import NetemError

TraceFormat = Literal["mahimahi", "csv"]
TRACE_FORMATS: tuple[str, ...] = ("mahimahi", "csv")

#: Bytes one delivery opportunity may carry (Mahimahi's PACKET_SIZE).
OPPORTUNITY_BYTES = 1500
#: The window a mahimahi trace's opportunities are counted over where only a rate can be set.
RATE_WINDOW_S = 0.1


@dataclass(frozen=True)
class Trace:
    """A parsed trace: either opportunity times (mahimahi) or rate steps (csv).

    `opportunities_s` holds the mahimahi timestamps in seconds; `steps` holds `(time_s,
    rate_bps)` rows for csv. `duration_s` is the trace's length and its loop period.
    """

    format: TraceFormat
    duration_s: float
    opportunities_s: tuple[float, ...] = ()
    steps: tuple[tuple[float, float], ...] = ()
    source: str = ""

    def mean_rate_bps(self) -> float:
        """Average rate over one period, in bit/s (what a long measurement should find)."""
        if self.duration_s <= 0:
            return 0.0
        if self.format == "mahimahi":
            return len(self.opportunities_s) * OPPORTUNITY_BYTES * 8 / self.duration_s
        bits = 0.0
        for i, (t, rate) in enumerate(self.steps):
            end = self.steps[i + 1][0] if i + 1 < len(self.steps) else self.duration_s
            bits += rate * (end - t)
        return bits / self.duration_s

    def rate_steps(self, window_s: float = RATE_WINDOW_S) -> list[tuple[float, float]]:
        """One period as `(offset_s, rate_bps)` steps: csv rows as they are; mahimahi
        opportunities counted per `window_s` window, for a backend that can only set rates
        (tc's HTB) and for the replay's latency model, which must agree with it.

        Window k holds the opportunities at times in (k·w, (k+1)·w] (time 0 in window 0): an
        opportunity at t delivers by t, so it counts in the window that ends at or after it,
        and the trace's last timestamp (its period) falls in its last window. Times are binned
        as whole milliseconds, as the trace wrote them, so 300 ms is never 0.29999 s. A last
        window cut short by the period has its rate over its own length."""
        if self.format == "csv":
            return list(self.steps)
        window_ms = round(window_s * 1000)
        period_ms = round(self.duration_s * 1000)
        windows = max(1, -(-period_ms // window_ms))
        counts = [0] * windows
        for t in self.opportunities_s:
            ms = round(t * 1000)
            counts[min(windows - 1, max(0, (ms - 1) // window_ms))] += 1
        steps = []
        for k, n in enumerate(counts):
            length_ms = min(window_ms, period_ms - k * window_ms) if period_ms > 0 else window_ms
            steps.append((k * window_ms / 1000, n * OPPORTUNITY_BYTES * 8 / (length_ms / 1000)))
        return steps

    def opportunities(self, start_s: float, loop: bool) -> Iterator[float]:
        """Absolute times of delivery opportunities, for a replay that starts at `start_s`.

        Without `loop` the iterator ends with the trace; with it, it never ends (unless the
        trace has no opportunity at all).
        """
        offset = start_s
        while True:
            produced = False
            for t in self._one_period():
                produced = True
                yield offset + t
            if not loop or not produced or self.duration_s <= 0:
                return
            offset += self.duration_s

    def _one_period(self) -> Iterator[float]:
        if self.format == "mahimahi":
            yield from self.opportunities_s
            return
        for i, (t, rate) in enumerate(self.steps):
            end = self.steps[i + 1][0] if i + 1 < len(self.steps) else self.duration_s
            if rate <= 0:
                continue
            gap = OPPORTUNITY_BYTES * 8 / rate
            # Opportunities at the end of each 1500-byte interval, so a step's first
            # packet leaves after one serialisation time, like a rate-limited link.
            count = math.floor((end - t) / gap + 1e-9)
            for k in range(1, count + 1):
                yield t + k * gap


#: Wrong lines reported per file; past this many, one more entry says how many more there were.
MAX_PROBLEMS = 5


@dataclass(frozen=True)
class TraceProblem:
    """One wrong line of a trace file (1-based `line`).

    `said` is the sentence the emulator prints (`timestamp 4 is earlier than the previous one
    (5)`); `expected`/`found` are the same fact as phrases, the way `testbed validate` reports
    every scenario problem (`expected a whole number of milliseconds, found '2.5'`).
    """

    line: int
    expected: str
    found: str
    said: str


class TraceError(NetemError, ValueError):
    """A trace that cannot be used. `problems` lists up to `MAX_PROBLEMS` wrong lines (plus one
    entry counting the rest); the message has one `<source> line <n>: <said>` line each."""

    def __init__(self, source: str, problems: list[TraceProblem]) -> None:
        self.source = source
        self.problems = tuple(problems)
        super().__init__("\n".join(f"{source} line {p.line}: {p.said}" for p in problems))


def _capped(problems: list[TraceProblem]) -> list[TraceProblem]:
    if len(problems) <= MAX_PROBLEMS:
        return problems
    extra = len(problems) - MAX_PROBLEMS
    first = problems[MAX_PROBLEMS].line
    more = f"{extra} more wrong line(s) from here on"
    return [*problems[:MAX_PROBLEMS], TraceProblem(first, "a valid line", more, more)]


def _content_lines(text: str) -> Iterator[tuple[int, str]]:
    """Numbered lines with content: blank lines and `#` comments are skipped."""
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            yield number, line


def parse_mahimahi(text: str, source: str = "trace") -> Trace:
    """Parse a Mahimahi trace: one non-negative integer ms timestamp per line, non-decreasing.

    Raises `TraceError` naming up to `MAX_PROBLEMS` wrong lines.
    """
    whole = "a whole number of milliseconds"
    problems: list[TraceProblem] = []
    stamps: list[int] = []
    last_line = 0
    for number, line in _content_lines(text):
        last_line = number
        try:
            ms = int(line)
        except ValueError:
            said = f"expected an integer millisecond timestamp, got {line[:40]!r}"
            problems.append(TraceProblem(number, whole, repr(line[:40]), said))
            continue
        if ms < 0:
            problems.append(TraceProblem(number, whole, line, f"timestamp {ms} is negative"))
            continue
        if stamps and ms < stamps[-1]:
            said = f"timestamp {ms} is earlier than the previous one ({stamps[-1]})"
            expected = f"a timestamp >= the previous one ({stamps[-1]})"
            problems.append(TraceProblem(number, expected, str(ms), said))
            continue
        stamps.append(ms)
    if not problems and not stamps:
        problems.append(
            TraceProblem(
                1, "at least one timestamp", "an empty file", "the trace has no timestamps"
            )
        )
    elif not problems and stamps[-1] == 0:
        said = "the last timestamp must be > 0 ms (it is the loop period)"
        expected = "a last timestamp > 0 (it is the trace's period)"
        problems.append(TraceProblem(last_line, expected, "0", said))
    if problems:
        raise TraceError(source, _capped(problems))
    times = tuple(ms / 1000.0 for ms in stamps)
    return Trace(format="mahimahi", duration_s=times[-1], opportunities_s=times, source=source)


def parse_csv(text: str, source: str = "trace") -> Trace:
    """Parse a `time_s,mbit` trace: strictly increasing non-negative times, rates >= 0.

    A first row with no number in it is a header and is skipped. Times must strictly increase:
    two rows at one instant would leave the first one's rate no time to hold. Raises
    `TraceError` naming up to `MAX_PROBLEMS` wrong lines.
    """
    row = "a row time_s,mbit (two numbers)"
    problems: list[TraceProblem] = []
    steps: list[tuple[float, float]] = []
    for index, (number, line) in enumerate(_content_lines(text)):
        cells = [c.strip() for c in line.split(",")]
        if index == 0 and not any(_is_number(c) for c in cells):
            continue  # a header row such as `time_s,mbit`
        shown = repr(line[:40])
        if len(cells) != 2:
            said = f"expected 2 columns `time_s,mbit`, got {shown}"
            problems.append(TraceProblem(number, row, shown, said))
            continue
        if not all(_is_number(c) for c in cells):
            said = f"expected finite numbers `time_s,mbit`, got {shown}"
            problems.append(TraceProblem(number, row, shown, said))
            continue
        t, mbit = float(cells[0]), float(cells[1])
        if t < 0:
            problems.append(
                TraceProblem(number, "a time >= 0", cells[0], f"time {t} s is negative")
            )
        elif steps and t <= steps[-1][0]:
            prev = steps[-1][0]
            said = f"time {t} s is not after the previous row ({prev} s)"
            problems.append(
                TraceProblem(number, f"a time > the previous one ({prev:g})", cells[0], said)
            )
        elif mbit < 0:
            said = f"rate {mbit} Mbit/s is negative"
            problems.append(TraceProblem(number, "a rate >= 0 Mbit/s", cells[1], said))
        else:
            steps.append((t, mbit * 1e6))
    if not problems and not steps:
        said = "the trace has no `time_s,mbit` rows"
        problems.append(TraceProblem(1, "at least one time_s,mbit row", "no rows", said))
    if problems:
        raise TraceError(source, _capped(problems))
    last_gap = steps[-1][0] - steps[-2][0] if len(steps) > 1 else 1.0
    duration = steps[-1][0] + last_gap
    return Trace(format="csv", duration_s=duration, steps=tuple(steps), source=source)


def _is_number(cell: str) -> bool:
    """A finite number (`inf` and `nan` are not rates or times)."""
    try:
        return math.isfinite(float(cell))
    except ValueError:
        return False


def default_format(path: str | Path) -> TraceFormat:
    """The format of a trace file whose format is not given: `csv` for `.csv`, else mahimahi."""
    return "csv" if str(path).lower().endswith(".csv") else "mahimahi"


def load_trace(path: str | Path, format: TraceFormat | None = None) -> Trace:
    """Read and validate a trace file; `format` defaults to `csv` for `.csv` files.

    Raises `TraceError` naming the wrong lines, or a plain `ValueError` for a missing or
    unreadable file, so a caller can show the message as is.
    """
    path = Path(path)
    if format is None:
        format = default_format(path)
    if format not in TRACE_FORMATS:
        raise ValueError(f"{path}: unknown trace format {format!r} (allowed: mahimahi, csv)")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the trace ({exc})") from None
    if format == "csv":
        return parse_csv(text, source=str(path))
    return parse_mahimahi(text, source=str(path))
