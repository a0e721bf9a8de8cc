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

`load_trace(path)` parses and validates a file and raises `ValueError` naming the line.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

TraceFormat = Literal["mahimahi", "csv"]
TRACE_FORMATS: tuple[str, ...] = ("mahimahi", "csv")

#: Bytes one delivery opportunity may carry (Mahimahi's PACKET_SIZE).
OPPORTUNITY_BYTES = 1500


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


def _fail(where: str, line: int, message: str) -> ValueError:
    return ValueError(f"{where} line {line}: {message}")


def parse_mahimahi(text: str, source: str = "trace") -> Trace:
    """Parse a Mahimahi trace: one non-negative integer ms timestamp per line, non-decreasing."""
    times: list[float] = []
    last = -1
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        try:
            ms = int(line)
        except ValueError:
            raise _fail(
                source, number, f"expected an integer millisecond timestamp, got {line!r}"
            ) from None
        if ms < 0:
            raise _fail(source, number, f"timestamp {ms} is negative")
        if ms < last:
            raise _fail(source, number, f"timestamp {ms} is earlier than the previous one ({last})")
        last = ms
        times.append(ms / 1000.0)
    if not times:
        raise ValueError(f"{source}: the trace has no timestamps")
    if times[-1] <= 0:
        raise ValueError(f"{source}: the last timestamp must be > 0 ms (it is the loop period)")
    return Trace(
        format="mahimahi", duration_s=times[-1], opportunities_s=tuple(times), source=source
    )


def parse_csv(text: str, source: str = "trace") -> Trace:
    """Parse a `time_s,mbit` trace: strictly increasing non-negative times, rates >= 0."""
    steps: list[tuple[float, float]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        cells = [c.strip() for c in line.split(",")]
        if len(cells) != 2:
            raise _fail(source, number, f"expected 2 columns `time_s,mbit`, got {line!r}")
        try:
            t, mbit = float(cells[0]), float(cells[1])
        except ValueError:
            if not steps and not any(_is_number(c) for c in cells):
                continue  # a header row such as `time_s,mbit`
            raise _fail(source, number, f"expected numbers `time_s,mbit`, got {line!r}") from None
        if not (math.isfinite(t) and math.isfinite(mbit)):
            raise _fail(source, number, f"values must be finite, got {line!r}")
        if t < 0:
            raise _fail(source, number, f"time {t} s is negative")
        if mbit < 0:
            raise _fail(source, number, f"rate {mbit} Mbit/s is negative")
        if steps and t <= steps[-1][0]:
            raise _fail(
                source, number, f"time {t} s is not after the previous row ({steps[-1][0]} s)"
            )
        steps.append((t, mbit * 1e6))
    if not steps:
        raise ValueError(f"{source}: the trace has no `time_s,mbit` rows")
    last_gap = steps[-1][0] - steps[-2][0] if len(steps) > 1 else 1.0
    duration = steps[-1][0] + last_gap
    return Trace(format="csv", duration_s=duration, steps=tuple(steps), source=source)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def load_trace(path: str | Path, format: TraceFormat | None = None) -> Trace:
    """Read and validate a trace file; `format` defaults to `csv` for `.csv` files.

    Raises `ValueError` with the file and line number on bad input (also for a missing or
    unreadable file), so a scenario validator can show it as is.
    """
    path = Path(path)
    if format is None:
        format = "csv" if path.suffix.lower() == ".csv" else "mahimahi"
    if format not in TRACE_FORMATS:
        raise ValueError(f"{path}: unknown trace format {format!r} (allowed: mahimahi, csv)")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the trace ({exc})") from None
    if format == "csv":
        return parse_csv(text, source=str(path))
    return parse_mahimahi(text, source=str(path))
