"""Units of the scenario language: rates, durations, percentages, and their formatting."""

from __future__ import annotations

import re
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from testbed import units
from testbed.units import (
    DurationError,
    PercentError,
    RateError,
    UnitError,
    format_duration,
    format_percent,
    format_rate,
    parse_duration,
    parse_percent,
    parse_rate,
)


@pytest.mark.parametrize(
    ("text", "bps"),
    [
        ("20mbit", 20e6),
        ("1.5gbit", 1.5e9),
        ("500kbit", 500e3),
        ("64000bit", 64000.0),
        ("20Mbit", 20e6),
        ("20MBIT/s", 20e6),
        ("1tbit", 1e12),
        ("0.1mbit", 100e3),
        (".5gbit", 0.5e9),
        ("20 mbit", 20e6),
    ],
)
def test_parse_rate(text: str, bps: float) -> None:
    assert parse_rate(text) == bps


@pytest.mark.parametrize(
    ("text", "hint"),
    [
        ("20mbps", "'mbps' is ambiguous: tc reads it as megabytes/s; write 20mbit for megabits/s"),
        ("5kbps", "'kbps' is ambiguous: tc reads it as kilobytes/s; write 5kbit for kilobits/s"),
        ("1Gbps", "'Gbps' is ambiguous: tc reads it as gigabytes/s; write 1gbit for gigabits/s"),
        ("20mb", "'mb' is ambiguous (megabytes or megabits?); write 20mbit for megabits/s"),
        ("20", "add a unit: 20mbit or 20bit"),
        ("-5mbit", "a rate cannot be negative"),
        ("fast", None),
        ("20 m bit", None),
        ("1e6bit", None),
    ],
)
def test_parse_rate_refuses_with_a_reason(text: str, hint: str | None) -> None:
    with pytest.raises(RateError) as info:
        parse_rate(text)
    err = info.value
    assert isinstance(err, ValueError)
    assert err.expected == "a rate like 20mbit, 1.5gbit or 500kbit"
    assert err.found == repr(text)
    assert err.hint == hint
    assert str(err).startswith(f"expected a rate like 20mbit, 1.5gbit or 500kbit, found {text!r}")


def test_bare_numbers_are_not_rates() -> None:
    with pytest.raises(RateError, match="a bare number has no unit; write 20mbit or 20bit"):
        parse_rate(20)  # type: ignore[arg-type]
    with pytest.raises(RateError):
        parse_rate(True)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("text", "seconds"),
    [
        ("8ms", 0.008),
        ("9ms", 0.009),
        ("1.5s", 1.5),
        ("500us", 0.0005),
        ("2m", 120.0),
        ("24h", 86400.0),
        ("0s", 0.0),
        (0, 0.0),
        (0.0, 0.0),
        ("250ms", 0.25),
    ],
)
def test_parse_duration(text: str | int, seconds: float) -> None:
    assert parse_duration(text) == seconds


@pytest.mark.parametrize(
    ("text", "hint"),
    [
        ("90", "add a unit: 90s or 90ms"),
        (90, "add a unit: 90s or 90ms"),
        ("8MS", "units are lowercase: 8ms"),
        ("5sec", "write 5s"),
        ("2min", "write 2m"),
        ("-1s", "a duration cannot be negative"),
        ("soon", None),
        (True, None),
    ],
)
def test_parse_duration_refuses_with_a_reason(text: object, hint: str | None) -> None:
    with pytest.raises(DurationError) as info:
        parse_duration(text)  # type: ignore[arg-type]
    assert info.value.hint == hint
    assert info.value.expected == "a duration like 8ms, 1.5s or 500us"


@pytest.mark.parametrize(
    ("text", "fraction"),
    [("0.5%", 0.005), ("100%", 1.0), ("0%", 0.0), (0, 0.0), ("30%", 0.3), ("0.1 %", 0.001)],
)
def test_parse_percent(text: str | int, fraction: float) -> None:
    assert parse_percent(text) == fraction


@pytest.mark.parametrize(
    ("text", "hint"),
    [
        (0.5, "a bare number could be a fraction or a percentage; write 0.5% or 50%"),
        ("0.5", "add the percent sign: 0.5%"),
        ("-1%", "a percentage cannot be negative"),
        ("half", None),
    ],
)
def test_parse_percent_refuses_with_a_reason(text: object, hint: str | None) -> None:
    with pytest.raises(PercentError) as info:
        parse_percent(text)  # type: ignore[arg-type]
    assert info.value.hint == hint


def test_unit_errors_share_a_base() -> None:
    for cls in (RateError, DurationError, PercentError):
        assert issubclass(cls, UnitError)
        assert issubclass(cls, ValueError)


def test_huge_numbers_are_refused() -> None:
    with pytest.raises(DurationError, match="too large"):
        parse_duration("9" * 400 + "s")


@pytest.mark.parametrize(
    ("bps", "text"),
    [
        (20e6, "20mbit"),
        (1.5e9, "1.5gbit"),
        (500e3, "500kbit"),
        (64000, "64kbit"),
        (999, "999bit"),
        (None, "unlimited"),
    ],
)
def test_format_rate(bps: float | None, text: str) -> None:
    assert format_rate(bps) == text


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0.008, "8ms"),
        (0.0005, "500us"),
        (0.25, "250ms"),
        (90, "90s"),
        (0, "0s"),
        (600, "10m"),
        (3600, "1h"),
        (86400, "24h"),
    ],
)
def test_format_duration(seconds: float, text: str) -> None:
    assert format_duration(seconds) == text


def test_format_percent() -> None:
    assert format_percent(0.005) == "0.5%"
    assert format_percent(1.0) == "100%"


@given(st.floats(min_value=1.0, max_value=1e11, allow_nan=False))
def test_format_rate_parses_back_closely(bps: float) -> None:
    assert parse_rate(format_rate(bps)) == pytest.approx(bps, rel=1e-5)


@given(st.floats(min_value=1e-6, max_value=86400.0, allow_nan=False))
def test_format_duration_parses_back_closely(seconds: float) -> None:
    assert parse_duration(format_duration(seconds)) == pytest.approx(seconds, rel=1e-5)


def _rate_or_unlimited(text: str) -> float | None:
    return None if text == "unlimited" else units.parse_rate(text)


@pytest.mark.parametrize(
    ("pattern", "parse", "good", "bad"),
    [
        (units.RATE_PATTERN, units.parse_rate, ["20mbit", "1.5GBit/s", "64000bit"],
         ["20mbps", "20", "unlimited"]),
        (units.RATE_OR_UNLIMITED_PATTERN, _rate_or_unlimited, ["unlimited", "20mbit"],
         ["Unlimited", "mbit"]),
        (units.DURATION_PATTERN, units.parse_duration, ["8ms", "1.5s", "2m", "500us"],
         ["8MS", "90", "-1s"]),
        (units.PERCENT_PATTERN, units.parse_percent, ["0.5%", "100%"], ["0.5", "%"]),
    ],
    ids=["rate", "rate_or_unlimited", "duration", "percent"],
)  # fmt: skip
def test_schema_patterns_agree_with_the_parsers(
    pattern: str, parse: Any, good: list[str], bad: list[str]
) -> None:
    # The JSON Schema uses these patterns verbatim: an editor must accept what the loader's
    # parser accepts, and flag what it refuses.
    for text in good:
        assert re.search(pattern, text), text
        parse(text)  # raises UnitError if the parser refuses what the schema allows
    for text in bad:
        assert not re.search(pattern, text), text
        with pytest.raises(units.UnitError):
            parse(text)


def test_signed_durations_only_where_asked() -> None:
    from testbed.units import DurationError, parse_duration

    assert parse_duration("-150ms", signed=True) == pytest.approx(-0.15)
    assert parse_duration("150ms", signed=True) == pytest.approx(0.15)
    with pytest.raises(DurationError):
        parse_duration("-150ms")  # a delay or a duration is never negative
