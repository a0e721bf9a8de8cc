"""The YAML-node kinds a scenario schema is declared with: how each value is checked, converted
and described, whatever the schema version.

A kind does two jobs from one declaration:
- `Kind.check` reads a composed YAML node (which keeps its line and column), converts it to SI
  units and reports what is wrong as an `Issue` at that node;
- `Kind.schema` writes the JSON Schema of the value, for an editor (`testbed schema`).

Kinds are the value types a scenario author meets: `Duration`, `Rate`, `Percent`, `Int`,
`Enum`, `Str`..., and containers: `Obj` (a mapping with declared `Field`s), `ListOf`,
`Nullable`, `Either` and `Tagged` (mappings told apart by an action key). `Obj(model=...)`
takes the defaults it shows from a dataclass, so the model stays the one place that says what
an omitted knob means. Nothing here names a scenario field: the concrete declaration of
version 1 is `schema_v1.py`, the rules that join fields are in `loader.py`.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import re
import shlex
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from testbed import units
from testbed.scenario.issues import Issue, did_you_mean

_TAG = "tag:yaml.org,2002:"
STR, INT, FLOAT, BOOL, NULL = (_TAG + t for t in ("str", "int", "float", "bool", "null"))
MERGE = _TAG + "merge"
MAP, SEQ = _TAG + "map", _TAG + "seq"
# Tags PyYAML's resolver gives to plain YAML; anything else (`!!python/...`, `!foo`) is refused.
_PLAIN_TAGS = frozenset((STR, INT, FLOAT, BOOL, NULL, MAP, SEQ, _TAG + "timestamp"))

#: The ceiling of every `Rate`.
MAX_RATE_BPS = 100e9
#: How close a misspelt key or word of the schema must be to get a "did you mean" (a word
#: written in another case is suggested too).
SPELLING_CUTOFF = 0.6

#: What an author wrote for an omitted field is "nothing": fields without a default.
NO_DEFAULT: Any = object()


# ---- reporting ------------------------------------------------------------------------------


class Invalid(Exception):
    """A value is wrong. The container that asked for it turns this into an `Issue`."""

    def __init__(self, expected: str, found: str, hint: str | None = None) -> None:
        super().__init__(expected)
        self.expected, self.found, self.hint = expected, found, hint


class Context:
    """Collects the issues of one scenario file while it is checked."""

    def __init__(self, file: str) -> None:
        self.file = file
        self.issues: list[Issue] = []
        # The key under which each mapping value was written: a missing key inside it is
        # reported on the line of that key (`topology:`), where an author looks for it.
        self.key_of: dict[int, Node] = {}

    def add(
        self,
        node: Node | None,
        path: str,
        expected: str,
        found: str,
        hint: str | None = None,
        *,
        file: str | None = None,
        line: int | None = None,
    ) -> None:
        """Record an issue at `node` (or at `line` of `file`, for a trace file)."""
        if node is not None:
            line, column = node.start_mark.line + 1, node.start_mark.column + 1
        else:
            column = 1 if line is not None else None
        self.issues.append(Issue(file or self.file, line, column, path, expected, found, hint))

    def count(self) -> int:
        return len(self.issues)


def child(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def item(path: str, index: int) -> str:
    return f"{path}[{index}]"


def _clip(text: str, limit: int = 40) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def scalar_value(node: ScalarNode) -> Any:
    """The Python value of a plain scalar (str, int, float, bool, null), as PyYAML's safe
    loader would build it. Other tags are never constructed."""
    return yaml.constructor.SafeConstructor().construct_object(node)


def describe(node: Node) -> str:
    """What an author wrote, as a short phrase for `found`."""
    if node.tag not in _PLAIN_TAGS:
        return f"a value tagged {node.tag!r}"
    if isinstance(node, MappingNode):
        return "a mapping"
    if isinstance(node, SequenceNode):
        return f"a list of {len(node.value)} item(s)"
    if node.tag == STR:
        return repr(_clip(node.value))
    if node.tag == NULL:
        return "nothing (null)"
    if node.tag == BOOL:
        return str(scalar_value(node)).lower()
    if node.tag in (INT, FLOAT):
        return node.value
    return f"a date ({node.value})"


def _one_of(values: Sequence[object]) -> str:
    shown = [repr(v) if isinstance(v, str) else str(v) for v in values]
    if len(shown) == 1:
        return shown[0]
    return ", ".join(shown[:-1]) + " or " + shown[-1]


# ---- value kinds ----------------------------------------------------------------------------


class Kind:
    """A value type of the scenario language: how to check it and how to describe it."""

    expected: str = "a value"

    def accepts(self, node: Node) -> bool:
        """Whether `node` has the shape of this kind (used by `Either` to pick one)."""
        return True

    def check(self, node: Node, ctx: Context, path: str) -> Any:
        """The value in SI units; raises `Invalid`, or reports nested issues to `ctx`."""
        raise NotImplementedError

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        raise NotImplementedError

    def to_yaml(self, value: Any) -> Any:
        """How an author would write `value` (an SI value), for defaults in the schema."""
        return value


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
        self.expected = f"one of {_one_of(self.values)}"

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


class Nullable(Kind):
    """`null` (meaning "not set") or a value of `inner`."""

    def __init__(self, inner: Kind) -> None:
        self.inner = inner
        self.expected = f"{inner.expected} or null"

    def accepts(self, node: Node) -> bool:
        return (isinstance(node, ScalarNode) and node.tag == NULL) or self.inner.accepts(node)

    def check(self, node: Node, ctx: Context, path: str) -> Any:
        if isinstance(node, ScalarNode) and node.tag == NULL:
            return None
        try:
            return self.inner.check(node, ctx, path)
        except Invalid as err:
            raise Invalid(self.expected, err.found, err.hint) from None

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"anyOf": [self.inner.schema(defs), {"type": "null"}]}

    def to_yaml(self, value: Any) -> Any:
        return None if value is None else self.inner.to_yaml(value)


class Either(Kind):
    """One of several kinds, chosen by the shape of the node (e.g. `0.5%` or a mapping)."""

    def __init__(self, *alternatives: Kind) -> None:
        self.alternatives = alternatives
        self.expected = " or ".join(a.expected for a in alternatives)

    def accepts(self, node: Node) -> bool:
        return any(a.accepts(node) for a in self.alternatives)

    def check(self, node: Node, ctx: Context, path: str) -> Any:
        for alternative in self.alternatives:
            if alternative.accepts(node):
                return alternative.check(node, ctx, path)
        raise Invalid(self.expected, describe(node))

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"anyOf": [a.schema(defs) for a in self.alternatives]}

    def to_yaml(self, value: Any) -> Any:
        if isinstance(value, list | tuple):  # a list value: the list alternative writes it
            for alt in self.alternatives:
                if isinstance(alt, ListOf):
                    return alt.to_yaml(value)
        return self.alternatives[0].to_yaml(value)


class Items(list):
    """A checked list: its values (`BAD` where an item was wrong) and the nodes they came from."""

    def __init__(self, values: list[Any], nodes: list[Node], node: Node, path: str) -> None:
        super().__init__(values)
        self.nodes, self.node, self.path = nodes, node, path

    def good(self) -> Iterator[tuple[int, Any, Node]]:
        """(index, value, node) of every item that checked out."""
        for i, (value, node) in enumerate(zip(self, self.nodes, strict=True)):
            if value is not BAD:
                yield i, value, node


BAD: Any = type("Bad", (), {"__repr__": lambda self: "BAD"})()


class ListOf(Kind):
    """A YAML list of `item`s."""

    def __init__(self, item_kind: Kind, min_items: int = 0, unique: bool = False) -> None:
        self.item, self.min_items, self.unique = item_kind, min_items, unique
        at_least = f"at least {min_items} " if min_items else ""
        self.expected = f"a list of {at_least}item(s), each {item_kind.expected}"

    def accepts(self, node: Node) -> bool:
        return isinstance(node, SequenceNode) and node.tag == SEQ

    def check(self, node: Node, ctx: Context, path: str) -> Items:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node))
        if len(node.value) < self.min_items:
            raise Invalid(self.expected, describe(node))
        values: list[Any] = []
        seen: dict[Any, int] = {}
        for i, sub in enumerate(node.value):
            try:
                value = self.item.check(sub, ctx, item(path, i))
            except Invalid as err:
                ctx.add(sub, item(path, i), err.expected, err.found, err.hint)
                value = BAD
            if self.unique and value is not BAD:
                if value in seen:
                    ctx.add(
                        sub,
                        item(path, i),
                        "each item once",
                        f"{describe(sub)} again (also at {item(path, seen[value])})",
                    )
                    value = BAD
                else:
                    seen[value] = i
            values.append(value)
        return Items(values, list(node.value), node, path)

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        out: dict[str, Any] = {"type": "array", "items": self.item.schema(defs)}
        if self.min_items:
            out["minItems"] = self.min_items
        if self.unique:
            out["uniqueItems"] = True
        return out

    def to_yaml(self, value: Any) -> Any:
        return None if value is None else [self.item.to_yaml(v) for v in value]


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


class MapOf(Kind):
    """A mapping of free keys (each matching `key`) to values of one kind (`env:`)."""

    def __init__(self, key: Str, value: Kind) -> None:
        self.key, self.value = key, value
        self.expected = f"a mapping of {key.expected} to {value.expected}"

    def accepts(self, node: Node) -> bool:
        return isinstance(node, MappingNode) and node.tag == MAP

    def check(self, node: Node, ctx: Context, path: str) -> dict[str, Any]:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node))
        assert isinstance(node, MappingNode)
        out: dict[str, Any] = {}
        for key_node, value_node in mapping_pairs(node, ctx, path):
            try:
                key = self.key.check(key_node, ctx, path)
            except Invalid as err:
                ctx.add(key_node, path, err.expected, err.found, err.hint)
                continue
            try:
                out[key] = self.value.check(value_node, ctx, child(path, key))
            except Invalid as err:
                ctx.add(value_node, child(path, key), err.expected, err.found, err.hint)
        return out

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {
            "type": "object",
            "propertyNames": self.key.schema(defs),
            "additionalProperties": self.value.schema(defs),
        }


class Argv(ListOf):
    """A command line as a list of words. A shell string is refused with the list it would
    be: the testbed runs no shell, so quoting, `$VAR` and `|` would mean nothing."""

    def __init__(self) -> None:
        super().__init__(Word("a word of the command line"), min_items=1)
        self.expected = "a command as a list of words (argv), like [python, app.py, --rate, 10]"

    def check(self, node: Node, ctx: Context, path: str) -> Items:
        if isinstance(node, ScalarNode) and node.tag == STR:
            try:
                words = shlex.split(node.value)
            except ValueError:
                words = node.value.split()
            hint = "no shell runs it; write it as a list: [" + ", ".join(words) + "]"
            raise Invalid(self.expected, f"a shell string {_clip(node.value)!r}", hint)
        return super().check(node, ctx, path)


# ---- mappings -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Field:
    """One key of a mapping: its kind, what it means, and whether/what it defaults to.

    `attr` is the attribute of the Obj's model dataclass this key fills (default: the key
    itself; None: no attribute, e.g. the action key of an event). `default`, when given, is
    in SI units; otherwise the model dataclass's default is used.
    """

    key: str
    kind: Kind
    doc: str
    required: bool = False
    default: Any = NO_DEFAULT
    attr: str | None = ""

    @property
    def model_attr(self) -> str | None:
        return self.key if self.attr == "" else self.attr


@dataclass
class Section:
    """A checked mapping: the values of its valid keys (SI units) and where each was written."""

    obj: Obj
    node: MappingNode
    path: str
    values: dict[str, Any] = field(default_factory=dict)
    nodes: dict[str, Node] = field(default_factory=dict)  # value node of each key written
    clean: bool = True  # no issue anywhere inside
    tag: str | None = None  # for timeline events: the action key

    def __contains__(self, key: str) -> bool:
        return key in self.values

    def __getitem__(self, key: str) -> Any:
        return self.values[key]

    def get(self, key: str, default: Any = None) -> Any:
        return self.values.get(key, default)

    def at(self, key: str) -> Node:
        """Where `key` was written (its value), or the mapping itself when it was not."""
        return self.nodes.get(key, self.node)

    def path_of(self, key: str) -> str:
        return child(self.path, key)

    def written(self, key: str) -> bool:
        return key in self.nodes


def mapping_pairs(node: MappingNode, ctx: Context, path: str) -> list[tuple[Node, Node]]:
    """The key/value pairs of a mapping with YAML merge keys (`<<: *anchor`) expanded.

    Keys written twice are reported: PyYAML would silently keep the last one.
    """
    explicit: list[tuple[Node, Node]] = []
    merged: list[tuple[Node, Node]] = []
    first_seen: dict[str, Node] = {}
    for key_node, value_node in node.value:
        if key_node.tag == MERGE:
            sources = value_node.value if isinstance(value_node, SequenceNode) else [value_node]
            for source in sources:
                if not isinstance(source, MappingNode):
                    ctx.add(source, path, "a mapping to merge (<<: *anchor)", describe(source))
                    continue
                merged.extend(mapping_pairs(source, Context(ctx.file), path))
            continue
        if isinstance(key_node, ScalarNode) and key_node.tag == STR:
            if key_node.value in first_seen:
                first = first_seen[key_node.value].start_mark.line + 1
                ctx.add(
                    key_node,
                    child(path, key_node.value),
                    "each key once",
                    f"{key_node.value!r} again (first on line {first})",
                    "YAML would silently keep only the last one; remove one of them",
                )
                continue
            first_seen[key_node.value] = key_node
        explicit.append((key_node, value_node))
    # Merged keys come first; explicit keys override them, and earlier merge sources win.
    out: dict[str, tuple[Node, Node]] = {}
    for key_node, value_node in merged:
        out.setdefault(str(key_node.value), (key_node, value_node))
    pairs = [p for k, p in out.items() if k not in first_seen]
    return pairs + explicit


class Obj(Kind):
    """A mapping with declared fields; unknown keys are errors (with a "did you mean").

    `model` is the dataclass the section builds (its defaults are the schema's defaults);
    `fill_defaults=False` leaves omitted keys out of the section (link profiles, which merge
    over other profiles). `require_any`: at least one of these keys must be written.
    `ref`: emit the schema once under `$defs` and refer to it.
    """

    def __init__(
        self,
        doc: str,
        fields: Sequence[Field],
        model: type | None = None,
        fill_defaults: bool = True,
        require_any: Sequence[str] = (),
        ref: str | None = None,
        extensions: bool = False,
    ) -> None:
        self.doc, self.fields, self.model = doc, tuple(fields), model
        self.by_key = {f.key: f for f in self.fields}
        self.fill_defaults, self.require_any, self.ref = fill_defaults, tuple(require_any), ref
        self.extensions = extensions  # `x-...` keys allowed (a place for YAML anchors)
        self.expected = f"a mapping with the keys {', '.join(self.by_key)}"
        self.expected_key = f"one of the keys {', '.join(self.by_key)}"

    def accepts(self, node: Node) -> bool:
        return isinstance(node, MappingNode) and node.tag == MAP

    def default_of(self, f: Field) -> Any:
        """The SI default of a field: its own, else the model dataclass's; NO_DEFAULT if none."""
        if f.default is not NO_DEFAULT:
            return f.default
        if self.model is None or not f.model_attr:
            return NO_DEFAULT
        for mf in dataclasses.fields(self.model):
            if mf.name == f.model_attr and mf.default is not dataclasses.MISSING:
                return mf.default
        return NO_DEFAULT

    def check(self, node: Node, ctx: Context, path: str) -> Section:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node))
        assert isinstance(node, MappingNode)
        before = ctx.count()
        section = Section(self, node, path)
        for key_node, value_node in mapping_pairs(node, ctx, path):
            if not (isinstance(key_node, ScalarNode) and key_node.tag == STR):
                ctx.add(key_node, path, self.expected_key, describe(key_node))
                continue
            key = key_node.value
            f = self.by_key.get(key)
            if f is None:
                if self.extensions and key.startswith("x-"):
                    continue
                ctx.add(
                    key_node,
                    child(path, key),
                    self.expected_key,
                    f"unknown key {key!r}",
                    did_you_mean(key, list(self.by_key), SPELLING_CUTOFF, any_case=True),
                )
                continue
            section.nodes[key] = value_node
            ctx.key_of[id(value_node)] = key_node
            try:
                section.values[key] = f.kind.check(value_node, ctx, child(path, key))
            except Invalid as err:
                ctx.add(value_node, child(path, key), err.expected, err.found, err.hint)
        for f in self.fields:
            if f.key in section.nodes:
                continue
            if f.required:
                ctx.add(
                    ctx.key_of.get(id(node), node),
                    child(path, f.key),
                    f"the key {f.key!r} ({f.kind.expected})",
                    f"{path or 'the top level'} without it",
                )
            elif self.fill_defaults and (default := self.default_of(f)) is not NO_DEFAULT:
                section.values[f.key] = default
        if self.require_any and not any(k in section.nodes for k in self.require_any):
            ctx.add(
                node,
                path,
                f"at least one of the keys {_one_of(self.require_any)}",
                "none of them",
            )
        section.clean = ctx.count() == before
        return section

    def build(self, section: Section) -> Any:
        """The model dataclass filled from a section (nested sections built recursively)."""
        assert self.model is not None
        kwargs: dict[str, Any] = {}
        for f in self.fields:
            if f.key not in section.values or not f.model_attr:
                continue
            value = section.values[f.key]
            if isinstance(value, Section) and value.obj.model is not None:
                value = value.obj.build(value)
            elif isinstance(value, list):
                value = tuple(v for v in value if v is not BAD)
            kwargs[f.model_attr] = value
        return self.model(**kwargs)

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        if self.ref and self.ref in defs:
            return {"$ref": f"#/$defs/{self.ref}"}
        if self.ref:
            defs[self.ref] = {}  # reserve the name first: a recursive reference finds it
        properties: dict[str, Any] = {}
        for f in self.fields:
            prop = dict(f.kind.schema(defs))
            prop["description"] = f.doc
            default = self.default_of(f)
            if default is not NO_DEFAULT:
                prop["default"] = f.kind.to_yaml(default)
            properties[f.key] = prop
        out: dict[str, Any] = {
            "type": "object",
            "description": self.doc,
            "properties": properties,
            "additionalProperties": False,
        }
        if self.extensions:
            out["patternProperties"] = {"^x-": {"description": "free space for YAML anchors"}}
        required = [f.key for f in self.fields if f.required]
        if required:
            out["required"] = required
        if self.require_any:
            out["anyOf"] = [{"required": [k]} for k in self.require_any]
        if self.ref:
            defs[self.ref] = out
            return {"$ref": f"#/$defs/{self.ref}"}
        return out


class Tagged(Kind):
    """A mapping whose kind is told by which one of several action keys it has."""

    def __init__(self, noun: str, variants: dict[str, Obj]) -> None:
        self.noun, self.variants = noun, variants
        self.expected = f"{noun}: a mapping with exactly one of the keys {_one_of(list(variants))}"

    def accepts(self, node: Node) -> bool:
        return isinstance(node, MappingNode) and node.tag == MAP

    def check(self, node: Node, ctx: Context, path: str) -> Section:
        if not self.accepts(node):
            raise Invalid(self.expected, describe(node))
        assert isinstance(node, MappingNode)
        keys = [k for k, _ in node.value if isinstance(k, ScalarNode) and k.tag == STR]
        actions = [k for k in keys if k.value in self.variants]
        if not actions:
            hints = [
                h
                for k in keys
                if (h := did_you_mean(k.value, list(self.variants), SPELLING_CUTOFF, any_case=True))
            ]
            written = ", ".join(repr(k.value) for k in keys) or "none"
            raise Invalid(
                f"{self.noun} with one action key ({_one_of(list(self.variants))})",
                f"only the keys {written}",
                hints[0] if hints else None,
            )
        if len({a.value for a in actions}) > 1:
            second = actions[1]
            ctx.add(
                second,
                child(path, second.value),
                "one action per event",
                f"both {actions[0].value!r} and {second.value!r}",
                "split them into two events at the same time",
            )
            return Section(self.variants[actions[0].value], node, path, clean=False)
        section = self.variants[actions[0].value].check(node, ctx, path)
        section.tag = actions[0].value
        return section

    def schema(self, defs: dict[str, Any]) -> dict[str, Any]:
        return {"oneOf": [obj.schema(defs) for obj in self.variants.values()]}
