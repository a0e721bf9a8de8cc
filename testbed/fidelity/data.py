"""A source's own samples, read from the file a case names: per-packet delays (a CSV column of
ms) or a histogram (DETERMINISTIC6G's format: each row a bin's lower bound in ms and its
relative count, tab-separated). A histogram's samples are its bin centres, weighted by count.
"""

from __future__ import annotations

import csv

from testbed.fidelity.case import Data, FidelityError


def load_samples(data: Data) -> tuple[list[float], list[float] | None]:
    """(values in ms, weights or None) of `data`'s file."""
    try:
        text = data.path.read_text()
    except OSError as err:
        raise FidelityError(f"{data.path}: cannot read it ({err.strerror})") from None
    if data.kind == "per_packet":
        return _per_packet(data, text), None
    return _histogram(data, text)


def _per_packet(data: Data, text: str) -> list[float]:
    rows = csv.DictReader(line for line in text.splitlines() if not line.startswith("#"))
    if rows.fieldnames is None or data.column not in rows.fieldnames:
        raise FidelityError(f"{data.path}: no column {data.column!r} (has {rows.fieldnames})")
    out = []
    for n, row in enumerate(rows, start=2):
        value = row[data.column]
        if value in ("", "nan"):
            continue  # a packet the source lost
        try:
            out.append(float(value))
        except ValueError:
            raise FidelityError(
                f"{data.path}:{n}: {data.column} {value!r} is not a number"
            ) from None
    if not out:
        raise FidelityError(f"{data.path}: no samples")
    return out


def _histogram(data: Data, text: str) -> tuple[list[float], list[float]]:
    lows, counts = [], []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.replace(",", "\t").split()
        try:
            low, count = float(parts[0]), float(parts[1])
        except (IndexError, ValueError):
            raise FidelityError(
                f"{data.path}:{n}: expected a bin's lower bound (ms) and its count"
            ) from None
        lows.append(low)
        counts.append(count)
    if len(lows) < 2 or sum(counts) <= 0:
        raise FidelityError(f"{data.path}: a histogram needs two bins or more and some counts")
    width = (lows[-1] - lows[0]) / (len(lows) - 1)
    return [low + width / 2 for low in lows], counts
