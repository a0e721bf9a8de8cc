"""What every kind stands on: the tags of plain YAML, the `Invalid` a wrong value raises, the
`Context` that collects a file's issues, how a node an author wrote is described (`found`), the
`Kind` protocol itself and the `Items` a checked list gives.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from testbed.scenario.issues import Issue

_TAG = "tag:yaml.org,2002:"
STR, INT, FLOAT, BOOL, NULL = (_TAG + t for t in ("str", "int", "float", "bool", "null"))
MERGE = _TAG + "merge"
MAP, SEQ = _TAG + "map", _TAG + "seq"
# Tags PyYAML's resolver gives to plain YAML; anything else (`!!python/...`, `!foo`) is refused.
_PLAIN_TAGS = frozenset((STR, INT, FLOAT, BOOL, NULL, MAP, SEQ, _TAG + "timestamp"))

#: How close a misspelt key or word of the schema must be to get a "did you mean" (a word
#: written in another case is suggested too).
SPELLING_CUTOFF = 0.6

#: What an author wrote for an omitted field is "nothing": fields without a default.
NO_DEFAULT: Any = object()


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


def clip(text: str, limit: int = 40) -> str:
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
        return repr(clip(node.value))
    if node.tag == NULL:
        return "nothing (null)"
    if node.tag == BOOL:
        return str(scalar_value(node)).lower()
    if node.tag in (INT, FLOAT):
        return node.value
    return f"a date ({node.value})"


def one_of(values: Sequence[object]) -> str:
    shown = [repr(v) if isinstance(v, str) else str(v) for v in values]
    if len(shown) == 1:
        return shown[0]
    return ", ".join(shown[:-1]) + " or " + shown[-1]


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
