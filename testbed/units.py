"""Units people write in scenarios (`20mbit`, `8ms`, `0.5%`) and the SI values behind them.

Parsers take what an author wrote and return bit/s, seconds or a fraction; formatters go the
other way for reports and dry-run output. Rates use tc's spelling (bit, kbit, mbit, gbit, tbit,
any case, optional `/s`); byte units such as `mbps` are refused on purpose, because tc reads them
as bytes per second and people usually mean megabits.

The regular expressions below are also the patterns of the JSON Schema (they are written
without flags so that an editor's ECMA-262 engine reads them the same way Python does).
"""

from __future__ import annotations

import math
import re
from decimal import Decimal

__all__ = [
    "DURATION_PATTERN",
    "PERCENT_PATTERN",
    "RATE_OR_UNLIMITED_PATTERN",
    "RATE_PATTERN",
    "DurationError",
    "PercentError",
    "RateError",
    "UnitError",
    "format_duration",
    "format_percent",
    "format_rate",
    "parse_duration",
    "parse_percent",
    "parse_rate",
]

#: Bits per second of each rate unit (decimal prefixes, as tc uses them), as exact decimals.
RATE_UNITS: dict[str, str] = {
    "bit": "1",
    "kbit": "1e3",
    "mbit": "1e6",
    "gbit": "1e9",
    "tbit": "1e12",
}
#: Seconds of each duration unit, as exact decimals.
DURATION_UNITS: dict[str, str] = {"us": "1e-6", "ms": "1e-3", "s": "1", "m": "60", "h": "3600"}
#: Byte-per-second spellings that tc accepts but that people misread (value: the bit unit meant).
_BYTE_UNITS: dict[str, str] = {
    "bps": "bit",
    "kbps": "kbit",
    "mbps": "mbit",
    "gbps": "gbit",
    "tbps": "tbit",
    "b/s": "bit",
    "kb/s": "kbit",
    "mb/s": "mbit",
    "gb/s": "gbit",
    "kb": "kbit",
    "mb": "mbit",
    "gb": "gbit",
}

_NUMBER = r"(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)"


def _anycase(word: str) -> str:
    """A regex matching `word` in any letter case, without relying on regex flags."""
    return "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else re.escape(c) for c in word)


# Longest units first, so that `mbit` is not read as `m` + junk by an alternation.
_RATE_ALTS = "|".join(_anycase(u) for u in sorted(RATE_UNITS, key=len, reverse=True))
_DURATION_ALTS = "|".join(sorted(DURATION_UNITS, key=len, reverse=True))

RATE_PATTERN = rf"^{_NUMBER} *(?:{_RATE_ALTS})(?:/[sS])?$"
RATE_OR_UNLIMITED_PATTERN = rf"^(?:unlimited|{_NUMBER} *(?:{_RATE_ALTS})(?:/[sS])?)$"
DURATION_PATTERN = rf"^{_NUMBER} *(?:{_DURATION_ALTS})$"
PERCENT_PATTERN = rf"^{_NUMBER} *%$"

_RATE_RE = re.compile(rf"^(?P<num>{_NUMBER}) *(?P<unit>{_RATE_ALTS})(?:/[sS])?$")
_DURATION_RE = re.compile(rf"^(?P<num>{_NUMBER}) *(?P<unit>{_DURATION_ALTS})$")
_PERCENT_RE = re.compile(rf"^(?P<num>{_NUMBER}) *%$")
_NUMBER_AND_UNIT_RE = re.compile(rf"^(?P<num>{_NUMBER}) *(?P<unit>.*?)$")

RATE_EXPECTED = "a rate like 20mbit, 1.5gbit or 500kbit"
DURATION_EXPECTED = "a duration like 8ms, 1.5s or 500us"
PERCENT_EXPECTED = "a percentage like 0.5% (or 0)"


class UnitError(ValueError):
    """A value with a unit could not be read: what was expected, what was found, and a hint."""

    def __init__(self, expected: str, found: str, hint: str | None = None) -> None:
        self.expected = expected
        self.found = found
        self.hint = hint
        message = f"expected {expected}, found {found}"
        super().__init__(f"{message}; {hint}" if hint else message)


class RateError(UnitError):
    """Not a rate (or a byte-based rate that tc would misread)."""


class DurationError(UnitError):
    """Not a duration."""


class PercentError(UnitError):
    """Not a percentage."""


def _show(value: object) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def _finite(
    num: str, error: type[UnitError], expected: str, found: object, scale: str = "1"
) -> float:
    """`num` times `scale`, rounded once (so `9ms` is exactly the float 0.009)."""
    value = float(Decimal(num) * Decimal(scale))
    if not math.isfinite(value):
        raise error(expected, _show(found), "the number is too large")
    return value


def parse_rate(text: str) -> float:
    """`20mbit` -> 20e6 (bit/s). Units: bit, kbit, mbit, gbit, tbit, any case, optional `/s`."""
    if not isinstance(text, str) or isinstance(text, bool):
        hint = None
        if isinstance(text, int | float) and not isinstance(text, bool):
            hint = f"a bare number has no unit; write {text:g}mbit or {text:g}bit"
        raise RateError(RATE_EXPECTED, _show(text), hint)
    s = text.strip()
    if s.startswith("-"):
        raise RateError(RATE_EXPECTED, _show(text), "a rate cannot be negative")
    m = _RATE_RE.match(s)
    if m:
        return _finite(m["num"], RateError, RATE_EXPECTED, text, RATE_UNITS[m["unit"].lower()])
    loose = _NUMBER_AND_UNIT_RE.match(s)
    if loose:
        unit = loose["unit"].lower()
        if unit in _BYTE_UNITS:
            bit_unit = _BYTE_UNITS[unit]
            prefix = {"k": "kilo", "m": "mega", "g": "giga", "t": "tera"}.get(bit_unit[0], "")
            raise RateError(
                RATE_EXPECTED,
                _show(text),
                (
                    f"{loose['unit']!r} is ambiguous: tc reads it as {prefix}bytes/s"
                    if unit.endswith("ps")
                    else f"{loose['unit']!r} is ambiguous ({prefix}bytes or {prefix}bits?)"
                )
                + f"; write {loose['num']}{bit_unit} for {prefix}bits/s",
            )
        if unit == "":
            raise RateError(
                RATE_EXPECTED, _show(text), f"add a unit: {loose['num']}mbit or {loose['num']}bit"
            )
    raise RateError(RATE_EXPECTED, _show(text))


def parse_duration(text: str | int | float, signed: bool = False) -> float:
    """`8ms` -> 0.008 (s). Units: us, ms, s, m, h. A bare 0 is accepted (no unit needed).

    `signed` allows a leading minus, for offsets such as a sigmoid's midpoint (`-150ms`);
    a time span is never negative.
    """
    if signed and isinstance(text, str) and text.strip().startswith("-"):
        return -parse_duration(text.strip()[1:].lstrip())
    if isinstance(text, bool):
        raise DurationError(DURATION_EXPECTED, str(text).lower())
    if isinstance(text, int | float):
        if text == 0:
            return 0.0
        raise DurationError(DURATION_EXPECTED, _show(text), f"add a unit: {text:g}s or {text:g}ms")
    if not isinstance(text, str):
        raise DurationError(DURATION_EXPECTED, _show(text))
    s = text.strip()
    if s.startswith("-"):
        raise DurationError(DURATION_EXPECTED, _show(text), "a duration cannot be negative")
    m = _DURATION_RE.match(s)
    if m:
        return _finite(m["num"], DurationError, DURATION_EXPECTED, text, DURATION_UNITS[m["unit"]])
    loose = _NUMBER_AND_UNIT_RE.match(s)
    hint = None
    if loose and loose["unit"] == "":
        hint = f"add a unit: {loose['num']}s or {loose['num']}ms"
    elif loose and loose["unit"].lower() in DURATION_UNITS:
        hint = f"units are lowercase: {loose['num']}{loose['unit'].lower()}"
    elif loose and loose["unit"].lower() in ("sec", "secs", "second", "seconds"):
        hint = f"write {loose['num']}s"
    elif loose and loose["unit"].lower() in ("min", "mins", "minute", "minutes"):
        hint = f"write {loose['num']}m"
    elif loose and loose["unit"].lower() in ("µs", "usec", "usecs"):
        hint = f"write {loose['num']}us"
    elif loose and loose["unit"].lower() in ("msec", "msecs"):
        hint = f"write {loose['num']}ms"
    raise DurationError(DURATION_EXPECTED, _show(text), hint)


def parse_percent(text: str | int | float) -> float:
    """`0.5%` -> 0.005 (a fraction). A bare 0 is accepted; other bare numbers are ambiguous."""
    if isinstance(text, bool):
        raise PercentError(PERCENT_EXPECTED, str(text).lower())
    if isinstance(text, int | float):
        if text == 0:
            return 0.0
        raise PercentError(
            PERCENT_EXPECTED,
            _show(text),
            f"a bare number could be a fraction or a percentage; write {text:g}% "
            f"or {text * 100:g}%",
        )
    if not isinstance(text, str):
        raise PercentError(PERCENT_EXPECTED, _show(text))
    s = text.strip()
    if s.startswith("-"):
        raise PercentError(PERCENT_EXPECTED, _show(text), "a percentage cannot be negative")
    m = _PERCENT_RE.match(s)
    if not m:
        hint = None
        if re.fullmatch(_NUMBER, s):
            hint = f"add the percent sign: {s}%"
        raise PercentError(PERCENT_EXPECTED, _show(text), hint)
    return _finite(m["num"], PercentError, PERCENT_EXPECTED, text, "0.01")


def _num(value: float) -> str:
    """A short decimal: no exponent, no trailing zeros, up to 6 significant digits."""
    text = f"{value:.6g}"
    if "e" in text:
        text = f"{value:.6f}".rstrip("0").rstrip(".")
    return text


def format_rate(bps: float | None) -> str:
    """20e6 -> `20mbit`; None -> `unlimited`. The result parses back with `parse_rate`."""
    if bps is None:
        return "unlimited"
    for unit in ("tbit", "gbit", "mbit", "kbit"):
        if abs(bps) >= float(RATE_UNITS[unit]):
            return f"{_num(bps / float(RATE_UNITS[unit]))}{unit}"
    return f"{_num(bps)}bit"


def format_duration(seconds: float) -> str:
    """0.008 -> `8ms`; 90 -> `90s`; 3600 -> `1h`. The result parses back with `parse_duration`."""
    s = abs(seconds)
    if s == 0:
        return "0s"
    if s < 1e-3:
        return f"{_num(seconds * 1e6)}us"
    if s < 1:
        return f"{_num(seconds * 1e3)}ms"
    # Whole hours, or whole minutes from 10 minutes on; "90s" reads better than "1.5m".
    if s >= 3600 and s % 3600 == 0:
        return f"{_num(seconds / 3600)}h"
    if s >= 600 and s % 60 == 0:
        return f"{_num(seconds / 60)}m"
    return f"{_num(seconds)}s"


def format_percent(fraction: float) -> str:
    """0.005 -> `0.5%`."""
    return f"{_num(fraction * 100)}%"
