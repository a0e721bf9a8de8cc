"""The kinds made of other kinds: `Nullable`, `Either` (chosen by the shape of the node),
`ListOf`, `MapOf` (free keys) and `Argv` (a command line as a list of words).
"""

from __future__ import annotations

import shlex
from typing import Any

from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from testbed.scenario.kinds.base import (
    BAD,
    MAP,
    NULL,
    SEQ,
    STR,
    Context,
    Invalid,
    Items,
    Kind,
    child,
    clip,
    describe,
    item,
)
from testbed.scenario.kinds.mapping import mapping_pairs
from testbed.scenario.kinds.scalar import Str, Word


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
            raise Invalid(self.expected, f"a shell string {clip(node.value)!r}", hint)
        return super().check(node, ctx, path)
