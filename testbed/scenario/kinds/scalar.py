"""The kinds read from one YAML scalar: the value types a scenario author meets, `Duration`,
`Rate`, `Percent`, `Int`, `Float`, `Enum`, `Str`... Each converts what was written to SI units,
says what it expected in words (`expected`, with its range) and writes its JSON Schema.
"""

from __future__ import annotations

import ipaddress
import math
import re
from collections.abc import Callable, Sequence
from typing import Any

from yaml.nodes import Node, ScalarNode

from testbed import units
from testbed.scenario.issues import did_you_mean
from testbed.scenario.kinds.base import (
    BOOL,
    FLOAT,
    INT,
    NULL,
    SPELLING_CUTOFF,
    STR,
    Context,
    Invalid,
    Kind,
    describe,
    one_of,
    scalar_value,
)

#: The ceiling of every `Rate`.
MAX_RATE_BPS = 100e9


class Scalar(Kind):
    """A kind read from one YAML scalar with one of `tags`."""

    tags: tuple[str, ...] = (STR,)

    def accepts(self, node: Node) -> bool:
        return isinstance(node, ScalarNode) and node.tag in self.tags

    def check(self, node: Node, ctx: Context, path: str) -> Any:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node), self.hint_for(node))
        return self.convert(scalar_value(node), node)

    def hint_for(self, node: Node) -> str | None:
        return None

    def convert(self, value: Any, node: ScalarNode) -> Any:
        return value


def _range_text(lo: float | None, hi: float | None, lo_open: bool, fmt: Callable) -> str:
    if lo is not None and hi is not None:
        if lo_open:
            return f"above {fmt(lo)} and at most {fmt(hi)}"
        return f"between {fmt(lo)} and {fmt(hi)}"
    if lo is not None:
        return f"above {fmt(lo)}" if lo_open else f"of at least {fmt(lo)}"
    if hi is not None:
        return f"of at most {fmt(hi)}"
    return ""


def _bounds_schema(lo: float | None, hi: float | None, lo_open: bool) -> dict[str, float]:
    out: dict[str, float] = {}
    if lo is not None:
        out["exclusiveMinimum" if lo_open else "minimum"] = lo
    if hi is not None:
        out["maximum"] = hi
    return out


class _Ranged(Scalar):
    """A number (or a quantity with a unit) that must lie in [lo, hi] or (lo, hi]."""

    noun = "a number"
    lo: float | None = None
    hi: float | None = None
    lo_open = False

    def fmt(self, value: float) -> str:
        return f"{value:g}"

    def in_range(self, value: float, found: str) -> float:
        too_low = self.lo is not None and (value < self.lo or (self.lo_open and value == self.lo))
        too_high = self.hi is not None and value > self.hi
        if too_low or too_high:
            raise Invalid(
                f"{self.noun} {_range_text(self.lo, self.hi, self.lo_open, self.fmt)}", found
            )
        return value

    def range_doc(self) -> str:
        text = _range_text(self.lo, self.hi, self.lo_open, self.fmt)
        return f" ({text})" if text else ""


class Int(_Ranged):
    """A whole number."""

    tags = (INT,)

    def __init__(self, lo: int | None = None, hi: int | None = None, noun: str = "a whole number"):
        self.lo, self.hi, self.noun = lo, hi, noun
        self.expected = noun + self.range_doc()

    def fmt(self, value: float) -> str:
        return str(int(value))

    def hint_for(self, node: Node) -> str | None:
        if isinstance(node, ScalarNode) and node.tag == FLOAT:
            return "write a whole number without a decimal point"
        if isinstance(node, ScalarNode) and node.tag == STR and re.fullmatch(r"-?\d+", node.value):
            return "remove the quotes"
        return None

    def convert(self, value: Any, node: ScalarNode) -> int:
        return int(self.in_range(value, describe(node)))

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"type": "integer", **_bounds_schema(self.lo, self.hi, self.lo_open)}


class Float(_Ranged):
    """A real number (integers are accepted)."""

    tags = (INT, FLOAT)

    def __init__(
        self,
        lo: float | None = None,
        hi: float | None = None,
        lo_open: bool = False,
        noun: str = "a number",
    ) -> None:
        self.lo, self.hi, self.lo_open, self.noun = lo, hi, lo_open, noun
        self.expected = noun + self.range_doc()

    def hint_for(self, node: Node) -> str | None:
        if isinstance(node, ScalarNode) and node.tag == STR:
            try:
                float(node.value)
            except ValueError:
                return None
            return "remove the quotes"
        return None

    def convert(self, value: Any, node: ScalarNode) -> float:
        value = float(value)
        if not math.isfinite(value):
            raise Invalid(self.expected, describe(node))
        return self.in_range(value, describe(node))

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"type": "number", **_bounds_schema(self.lo, self.hi, self.lo_open)}


class Bool(Scalar):
    tags = (BOOL,)
    expected = "true or false"

    def hint_for(self, node: Node) -> str | None:
        if isinstance(node, ScalarNode) and node.value.lower() in ("true", "false"):
            return "remove the quotes"
        return None

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"type": "boolean"}


class Const(Scalar):
    """Exactly one allowed value (the schema `version`)."""

    tags = (INT,)

    def __init__(self, value: int, expected: str) -> None:
        self.value, self.expected = value, expected

    def convert(self, value: Any, node: ScalarNode) -> Any:
        if value != self.value:
            raise Invalid(self.expected, describe(node))
        return value

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"const": self.value}


class Enum(Scalar):
    """One of a few words."""

    def __init__(self, values: Sequence[str]) -> None:
        self.values = tuple(values)
        self.expected = f"one of {one_of(self.values)}"

    def hint_for(self, node: Node) -> str | None:
        if isinstance(node, ScalarNode):
            return did_you_mean(str(node.value), self.values, SPELLING_CUTOFF, any_case=True)
        return None

    def convert(self, value: Any, node: ScalarNode) -> str:
        if value not in self.values:
            raise Invalid(self.expected, describe(node), self.hint_for(node))
        return value

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"type": "string", "enum": list(self.values)}


class Str(Scalar):
    """A string, optionally matching `pattern` (an anchored regex, also used by the schema)."""

    def __init__(self, expected: str, pattern: str | None = None, why: str | None = None) -> None:
        self.expected, self.pattern, self.why = expected, pattern, why

    def hint_for(self, node: Node) -> str | None:
        return "put it in quotes" if isinstance(node, ScalarNode) and node.tag != NULL else None

    def convert(self, value: Any, node: ScalarNode) -> str:
        if value == "" or (self.pattern and not re.search(self.pattern, value)):
            raise Invalid(self.expected, describe(node), self.why)
        return value

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = {"type": "string", "minLength": 1}
        if self.pattern:
            out["pattern"] = self.pattern
        return out


class Duration(_Ranged):
    """A time span written with a unit (`8ms`, `1.5s`, `2m`); a bare 0 is allowed."""

    tags = (STR, INT, FLOAT)

    def __init__(
        self,
        hi: float,
        lo: float = 0.0,
        lo_open: bool = False,
        noun: str = "a duration",
        signed: bool = False,
    ) -> None:
        self.lo, self.hi, self.lo_open, self.noun, self.signed = lo, hi, lo_open, noun, signed
        self.expected = f"{units.DURATION_EXPECTED}{self.range_doc()}"

    def fmt(self, value: float) -> str:
        return ("-" if value < 0 else "") + units.format_duration(abs(value))

    def convert(self, value: Any, node: ScalarNode) -> float:
        try:
            seconds = units.parse_duration(value, signed=self.signed)
        except units.UnitError as err:
            raise Invalid(self.expected, err.found, err.hint) from None
        return self.in_range(seconds, describe(node))

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        pattern = units.DURATION_PATTERN
        if self.signed:
            pattern = "^-?" + pattern.removeprefix("^")
        return {"anyOf": [{"type": "string", "pattern": pattern}, {"const": 0}]}

    def to_yaml(self, value: Any) -> Any:
        return self.fmt(value)


class Rate(_Ranged):
    """A bit rate written with tc's units (`20mbit`), or `unlimited` where allowed."""

    def __init__(self, unlimited: bool, noun: str = "a rate") -> None:
        self.lo, self.hi, self.lo_open, self.noun = 0.0, MAX_RATE_BPS, True, noun
        self.unlimited = unlimited
        self.expected = units.RATE_EXPECTED + (" (or unlimited)" if unlimited else "")
        self.tags = (STR, INT, FLOAT)

    def fmt(self, value: float) -> str:
        return units.format_rate(value)

    def convert(self, value: Any, node: ScalarNode) -> float | None:
        if self.unlimited and value == "unlimited":
            return None
        try:
            bps = units.parse_rate(value)
        except units.UnitError as err:
            raise Invalid(self.expected, err.found, err.hint) from None
        return self.in_range(bps, describe(node))

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        pattern = units.RATE_OR_UNLIMITED_PATTERN if self.unlimited else units.RATE_PATTERN
        return {"type": "string", "pattern": pattern}

    def to_yaml(self, value: Any) -> Any:
        return units.format_rate(value)


class Percent(_Ranged):
    """A share written as a percentage (`0.5%`); a bare 0 is allowed. Converts to a fraction."""

    tags = (STR, INT, FLOAT)

    def __init__(self, noun: str = "a percentage") -> None:
        self.lo, self.hi, self.noun = 0.0, 1.0, noun
        self.expected = f"{units.PERCENT_EXPECTED} between 0% and 100%"

    def fmt(self, value: float) -> str:
        return units.format_percent(value)

    def convert(self, value: Any, node: ScalarNode) -> float:
        try:
            fraction = units.parse_percent(value)
        except units.UnitError as err:
            raise Invalid(self.expected, err.found, err.hint) from None
        return self.in_range(fraction, describe(node))

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"anyOf": [{"type": "string", "pattern": units.PERCENT_PATTERN}, {"const": 0}]}

    def to_yaml(self, value: Any) -> Any:
        return units.format_percent(value)


_PRIVATE_V4 = tuple(
    ipaddress.IPv4Network(n) for n in ("10.0.0.0/8", "172.16.0.0/12", "192.168.0.0/16")
)


class PrivateNetwork(Scalar):
    """A private IPv4 network in CIDR form (RFC 1918), for the link addresses of a run."""

    expected = (
        "a private IPv4 network like 10.77.0.0/16 "
        "(inside 10.0.0.0/8, 172.16.0.0/12 or 192.168.0.0/16)"
    )
    pattern = r"^[0-9]{1,3}(\.[0-9]{1,3}){3}/[0-9]{1,2}$"

    def convert(self, value: Any, node: ScalarNode) -> ipaddress.IPv4Network:
        if not re.fullmatch(self.pattern, value):
            raise Invalid(self.expected, describe(node), "write an address and a prefix length")
        try:
            net = ipaddress.IPv4Network(value, strict=False)
        except ValueError as err:
            raise Invalid(self.expected, describe(node), str(err)) from None
        if str(net) != value:
            raise Invalid(
                self.expected, describe(node), f"it has host bits set; did you mean {net}?"
            )
        if not any(net.subnet_of(p) for p in _PRIVATE_V4):
            raise Invalid(
                self.expected,
                describe(node),
                "traffic must stay between the namespaces of this host, so only private "
                "addresses are used",
            )
        return net

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"type": "string", "pattern": self.pattern}


class Word(Scalar):
    """One word of a command line or an environment value: a string, or a number or boolean
    written bare (`[ping, -c, 3]`), kept as the text it was written as."""

    tags = (STR, INT, FLOAT, BOOL)

    def __init__(self, expected: str) -> None:
        self.expected = expected

    def check(self, node: Node, ctx: Context, path: str) -> Any:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node))
        assert isinstance(node, ScalarNode)
        return str(node.value)

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"type": ["string", "number", "boolean"]}
